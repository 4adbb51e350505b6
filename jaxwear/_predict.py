"""Forecasts of wear and remaining life with stated uncertainty: `jaxwear.predict` (DESIGN §7).

The study is calibrated (as `calibrate` does, with its effects) on the measurements at or
before `train_until`; the fitted model is then run to every forecast point, and its
uncertainty is carried there.

`laplace` (default): the fit's Gauss-Newton covariance C of the parameters u (the residual
variance σ̂² of the data rows and the clearance prior's rows, DESIGN §6) is pushed through
the model by the exact Jacobian g = ∂(max depth)/∂u at each forecast point (`jacfwd`
through the wear loop): var_model = g C gᵀ. Two bands:
- confidence band (where the model's depth is): depth ± q √var_model;
- prediction band (where a new measurement will fall): depth ± q √(var_model + σ²), which
  is the one reported as `lower_um/upper_um`.
q is the Student-t quantile with the residual degrees of freedom n - p when σ is estimated
from the residuals (exact for a linear model with Gaussian noise, and it matters when n - p
is a handful), the normal quantile when the noise level is given (`noise_um`).

Life: the first count at which the forecast maximum depth reaches `limit_um` (default: the
layer thickness), with the interval given by the prediction band's crossings (upper band
→ earliest, lower band → latest). Searched up to 10x the experiment's last measured count;
not reached there gives `at = None` with a `reason`. Under the adaptive integrator the
forecast stops, past the last `--at` point, once its depth passes 2x the layer (each NUTS
draw: the layer; `stop_past_layer`); later points hold the last computed depth, so a band
edge that had not reached the limit by then is reported as not reached, not guessed.

`nuts` (`_predict_nuts.py`): a posterior by NUTS through the same differentiable model;
`importance` (`_predict_importance.py`): the same posterior by Pareto-smoothed importance
sampling from the Laplace fit (forward runs only); both forecast their draws with
`_predict_draws`.

One compile per answer: the forecast's points are known before the fit, so the training
problem is laid out (`forecast_layout`) to hold them and the life's refinements, and the
forecast runs in the fit's compiled Jacobian (`forecast_problem`: the same packing, rows
and correction, another schedule of the same shapes); where the fit's answer is corrected
to a finer level, the forecast's depths come from a forward run there.
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace

import jax.numpy as jnp
import numpy as np
from scipy import stats

from . import _resolution
from ._calibrate import (
    FitResult,
    build_problem,
    check_noise_determined,
    fit,
    fit_study,
    study_fit_keys,
)
from ._config import timed
from ._errors import InputError
from ._optional import check_method_packages
from ._outside import OUTSIDE, forecast_flags
from ._predict_result import Curve, Life, Prediction, PredictResult, _jf  # noqa: F401
from ._residual import (
    Layout,
    evaluate,
    experiment_schedules,
    forward_run,
    integration_report,
    traces,
    traces_since,
)
from ._resolution import at_level
from ._study import Experiment, History, Profile, Study

# The forecast's fit stops when the next step would move every parameter by < 0.1 of its
# standard error (calibrate's reported values: 0.01): a forecast then moves by < 0.1 of
# its model band, which is what a band can show; on the boom with running-in, 3 training
# rows, the last 0.1 -> 0.01 took 6 more evaluations along the amplitude/distance valley.
FORECAST_SE_TOL = 0.1
LIFE_HORIZON = 10.0  # life is searched up to this multiple of the last measured count
LAPLACE_STOP_LAYERS = 2.0  # Laplace forecasts stop past this multiple of the layer (life tail)
METHODS = ("laplace", "nuts", "importance")
# Life crossings are searched on the forecast grid. Maximum depth never decreases in time, so
# each crossing lies inside its grid bracket: the bracket's width bounds the life's numerical
# error (reported). The forecast is refined (as many new points inside each bracket as
# bring it within LIFE_RTOL of its crossing in one round, at most LIFE_REFINE_POINTS, up to
# LIFE_REFINE_ROUNDS times; the sampling methods re-forecast every draw each round) until
# every bracket is within LIFE_RTOL of its crossing. Measured on the boom with the 48-point
# grid alone (5.2 h steps across its 1 h fast / 4 h slow duty blocks): life 39.55 h
# [37.81, 41.42] against 40.54 h [40.13, 40.98] on a 0.1 h grid.
LIFE_RTOL = 0.005
LIFE_REFINE_POINTS = 24
LIFE_REFINE_ROUNDS = 3
LIFE_ROOM_ROUNDS = 2  # refinement rounds the fit's compiled layout holds (a third recompiles)
MAX_REGIME_POINTS = 1000  # duty-block boundaries added to the grid at most


def _log(verbose, msg):
    if verbose:
        print(msg, file=sys.stderr, flush=True)


# ---------------------------------------------------------------- training subset, forecast


def unit_of_study(study: Study) -> str:
    return "hours" if timed(study.config) else "revolutions"


def training_study(study: Study, train_until: float | None) -> Study:
    """The study with only the measurements at or before `train_until` (revolutions for a
    crank-slider study, hours for an oscillating one). Experiments keep their place even when
    none of their rows remain: their clearance is then known from the prior only."""
    if train_until is None:
        return study
    lim = float(train_until) * (1 + 1e-12)
    exps = []
    for e in study.experiments:
        prof, hist = e.profile, e.history
        if prof is not None:
            keep = np.asarray(prof.revolutions) <= lim
            prof = replace(prof, angle=prof.angle[keep], depth=prof.depth[keep],
                           revolutions=prof.revolutions[keep]) if keep.any() else None
        if hist is not None:
            keep = np.asarray(hist.hours) <= lim
            hist = replace(hist, hours=hist.hours[keep],
                           depth=hist.depth[keep]) if keep.any() else None
        exps.append(replace(e, profile=prof, history=hist))
    if all(e.profile is None and e.history is None for e in exps):
        raise InputError(f"--train-until {train_until:g}: no measurement of {study.path} is "
                         f"at or before it (unit: {unit_of_study(study)})")
    return study.with_experiments(exps)


def measured_max(e: Experiment) -> tuple[np.ndarray, np.ndarray]:
    """Measured maximum depth per measured point [µm] (history rows, or a scan's deepest row)."""
    if e.history is not None:
        return np.asarray(e.history.hours, float), np.asarray(e.history.depth) * 1e6
    if e.profile is not None:
        pts = np.array(e.snapshot_points)
        r = np.asarray(e.profile.revolutions)
        return pts, np.array([np.max(e.profile.depth[r == s]) * 1e6 for s in pts])
    return np.zeros(0), np.zeros(0)


def _last_count(e: Experiment) -> float:
    pts = e.snapshot_points
    return float(max(pts)) if pts else float(e.hours or e.revolutions)


def forecast_points(study: Study, e: Experiment, at: list[float], n_dense: int = 48,
                    life: bool = True) -> np.ndarray:
    """Snapshot points of one experiment: the `at` points, the measured points, a fan-chart
    grid to max(at) and (with `life`) a life grid to 10x the last measured count (sorted,
    unique)."""
    crank = not timed(study.config)
    top = max(at)
    horizon = max(LIFE_HORIZON * _last_count(e), top) if life else top
    grid = np.concatenate([np.linspace(0, top, n_dense // 2 + 1)[1:],
                           np.linspace(0, horizon, n_dense + 1)[1:]])
    if not crank:
        grid = np.concatenate([grid, regime_boundaries(study, horizon)])
    grid = np.round(grid) if crank else np.round(grid, 6)  # whole revolutions
    pts = np.concatenate([np.asarray(at, float), np.asarray(e.snapshot_points, float), grid])
    return np.unique(pts[pts > 0])


def regime_boundaries(study: Study, horizon: float) -> np.ndarray:
    """Hours at which the duty cycle changes block, up to `horizon` (none past
    MAX_REGIME_POINTS). Within a block the depth grows smoothly; at a change its rate jumps
    (the boom: 1 h at 20°, then 4 h at 1°), so a grid that straddles a change misplaces a
    crossing by up to the grid step. The adaptive wear loop already ends a piece at each
    change, so snapshots there cost no integration steps."""
    blocks = study.config.duty_cycle
    if len(blocks) < 2:
        return np.zeros(0)
    ends = np.cumsum([b.duration_h for b in blocks])
    period = float(ends[-1])
    n = int(math.ceil(horizon / period))
    if n * len(blocks) > MAX_REGIME_POINTS:
        return np.zeros(0)
    t = (np.arange(n)[:, None] * period + ends[None, :]).ravel()
    return t[t <= horizon * (1 + 1e-12)]


def forecast_study(study: Study, points: list[np.ndarray]) -> Study:
    """The study with placeholder rows at `points` per experiment (so that `build_problem`
    makes one snapshot per point); the rows' values are never used."""
    exps = []
    for e, pts in zip(study.experiments, points):
        pts = np.asarray(pts, float)
        z = np.zeros(len(pts))
        if timed(study.config):
            exps.append(replace(e, hours=float(pts.max()), profile=None,
                                history=History(hours=pts, depth=z, path="<forecast>")))
        else:
            exps.append(replace(e, revolutions=float(pts.max()), history=None,
                                profile=Profile(angle=z, depth=z, revolutions=pts,
                                                path="<forecast>")))
    return study.with_experiments(exps)


def forecast_snapshots(problem, u):
    """Snapshots (E, S, N) [µm], their exact Jacobian (E, S, N, p) w.r.t. u and the
    integration report of the forecast: one evaluation of the residual model over the
    forecast points (`_residual.evaluate`, whose attempt count is doubled where a history
    was truncated rather than returned)."""
    ev, used = evaluate(problem, u, doublings=4)
    return ev.snaps, ev.J_snaps, integration_report(used, ev)


def forecast_layout(study: Study, train: Study, points, refine: bool = True) -> Layout:
    """Capacities (`_residual.Layout`) that hold the training problem and the forecast over
    `points` with room for the life's refinement rounds (`LIFE_ROOM_ROUNDS` x 3
    brackets x `LIFE_REFINE_POINTS` more points per experiment), rounded up to buckets:
    the fit and every forecast then share one compiled function. Attempts: the forecast's
    at the study's values (a fit raises them where its values need more)."""
    from ._schedule import bucket

    plist = [study.params(e) for e in study.experiments]
    fs = experiment_schedules(forecast_study(study, points), plist)
    ts = experiment_schedules(train, plist)
    room = LIFE_ROOM_ROUNDS * 3 * LIFE_REFINE_POINTS if refine else 0
    return Layout(updates=bucket(max(fs.cycles.shape[-1], ts.cycles.shape[-1]) + room),
                  snapshots=bucket(max(fs.n_snapshots, ts.n_snapshots) + room),
                  attempts=max(fs.attempts, ts.attempts))


def forecast_problem(train: Study, base, points, layout: Layout | None = None):
    """The problem `base` (a training problem, or a `FitResult` whose problem it is) over
    the forecast `points` (one array per experiment): the same packing, parameters, rows
    and row correction, its rows read from the forecast's snapshots (`train`: the training
    study whose snapshot points the rows index), the schedule to max(points) padded to
    `layout` (when it holds it; else bucketed capacities, so that refinement rounds share
    a compilation). Its u is the training problem's: u = `result.u` is the fit."""
    from ._schedule import bucket

    base = getattr(base, "problem", base)
    plist = [train.params(e) for e in train.experiments]
    fstudy = forecast_study(train, points)
    sched = experiment_schedules(fstudy, plist)
    if layout is None or not layout.holds(sched):
        layout = Layout(bucket(sched.cycles.shape[-1]), bucket(sched.n_snapshots),
                        sched.attempts)
    attempts = max(layout.attempts, base.schedule.attempts)
    sched = experiment_schedules(fstudy, plist, replace(layout, attempts=attempts))
    d = base.data
    exp, snap = np.asarray(d.exp), np.asarray(d.snap)
    new = np.empty_like(snap)
    for i, (e, s) in enumerate(zip(exp, snap)):
        t = train.experiments[e].snapshot_points[s]
        j = int(np.argmin(np.abs(np.asarray(points[e]) - t)))
        if not math.isclose(float(points[e][j]), float(t), rel_tol=1e-9, abs_tol=1e-9):
            raise RuntimeError(f"forecast points of experiment {e} miss the training point "
                               f"{t:g}")
        new[i] = j
    data = replace(d, snap=jnp.asarray(new, jnp.int32))
    return replace(base, schedule=sched, data=data)


def stop_past_layer(study: Study, fprob, points, at, factor: float = 1.0):
    """`fprob` whose (adaptive) runs stop once, past the last `at` point, the maximum depth
    has reached `factor` x the layer (≥ every allowed limit): the points after serve only
    the life estimate, which needs to know that the forecast is past the limit, not by how
    much; their snapshots come back +inf (`fill_past_stop`). Integrating on through the
    substrate to 10x the last measurement cost the boom's forecasts over 30x the steps (and
    ran out of attempts). Eq-23 schedules are returned unchanged."""
    sched = fprob.schedule
    if not sched.adaptive:
        return fprob
    depth, after = [], []
    snap = np.asarray(sched.snapshot)
    ends = np.asarray(sched.cycle_end)
    for i, (e, pts) in enumerate(zip(study.experiments, points)):
        k = int(np.argmin(np.abs(np.asarray(pts) - max(at))))
        j = np.nonzero(snap[i] == k)[0]
        after.append(float(ends[i, j[0]]) if len(j) else float(ends[i].max()))
        depth.append(factor * float(study.params(e).layer_thickness))
    return replace(fprob, schedule=sched.stopping_at(np.array(depth), np.array(after)))


def fill_past_stop(snaps, J=None):
    """Snapshots (E, S, N) (and their Jacobian (E, S, N, p)) with the rows after an early
    stop (+inf) replaced by the last computed row of their experiment: the depth never
    decreases, so a lower bound, past every allowed limit (the stop comes only past the
    layer). A band edge that had not reached the limit by the stop stays below it: "not
    reached" rather than a guess."""
    bad = np.isinf(snaps).any(axis=-1)  # (E, S)
    if not bad.any():
        return snaps, J
    idx = np.where(bad, 0, np.arange(snaps.shape[1])[None, :])
    idx = np.maximum.accumulate(idx, axis=1)
    snaps = np.take_along_axis(snaps, idx[..., None], axis=1)
    if J is not None:
        J = np.take_along_axis(J, idx[..., None, None], axis=1)
    return snaps, J


# ---------------------------------------------------------------- covariance, quantiles


def draw_quantile(y, q: float):
    """Quantile `q` over the draws (axis 0) by NumPy's default linear interpolation, where
    +inf (a draw past the limit) is allowed: between two +inf order statistics it is +inf
    (np.quantile gives NaN from inf - inf), at an exact order statistic it is that one."""
    s = np.sort(np.asarray(y, float), axis=0)
    pos = q * (s.shape[0] - 1)
    k = int(math.floor(pos))
    g = pos - k
    lo, hi = s[k], s[min(k + 1, s.shape[0] - 1)]
    with np.errstate(invalid="ignore"):
        return np.where((g == 0) | (lo == hi), lo, lo + g * (hi - lo))


def t_quantile(level: float, dof: float) -> float:
    """Two-sided central quantile: Student-t with `dof` (normal when dof is inf)."""
    p = 0.5 + level / 2
    return float(stats.norm.ppf(p) if not math.isfinite(dof) else stats.t.ppf(p, dof))


def _band(g, cov, null_dirs, noise, q):
    """(sd_model, sd_prediction) for gradient rows g (..., p)."""
    var = np.einsum("...i,ij,...j->...", g, cov, g)
    sd = np.sqrt(np.clip(var, 0, None))
    if null_dirs.shape[1]:
        # A forecast that moves along an undetermined direction has no finite band. "Moves":
        # by more than 1 % of the noise level per unit step along it (u's units are a
        # typical change: a factor e of a log parameter, `scale` of a linear one). A
        # relative test alone flagged forecasts whose derivative along it is the
        # integrator's round-off: the boom's running-in distance S_r, once running-in ends
        # before the first measurement, fixes nothing the forecast at 20 h depends on.
        along = np.linalg.norm(g @ null_dirs, axis=-1)
        leak = along > np.maximum(1e-6 * np.linalg.norm(g, axis=-1), 0.01 * noise)
        sd = np.where(leak, np.inf, sd)
    return sd, np.sqrt(sd ** 2 + noise ** 2)


def crossing(t, y, limit):
    """(t_x, t_before, t_after): the first t at which y reaches `limit` (linear
    interpolation from (0, 0)) and the grid step it lies in; None if never. Non-finite y
    counts as reached at its point (the layer is worn through there)."""
    tt = np.concatenate([[0.0], t])
    yy = np.concatenate([[0.0], y])
    for k in range(1, len(tt)):
        if not np.isfinite(yy[k]):
            return float(tt[k]), float(tt[k - 1]), float(tt[k])
        if yy[k] >= limit:
            y0 = yy[k - 1]
            x = tt[k - 1] + (limit - y0) / (yy[k] - y0) * (tt[k] - tt[k - 1])
            return float(x), float(tt[k - 1]), float(tt[k])
    return None


def life_of(name, t, depth, lower, upper, limit, unit, horizon) -> Life:
    found = [crossing(t, y, limit) for y in (depth, upper, lower)]
    at, lo, hi = (None if c is None else c[0] for c in found)
    brackets = tuple((a, b, x) for x, a, b in filter(None, found))
    reason = None
    if at is None:
        reason = (f"the forecast does not reach {limit:g} µm within {LIFE_HORIZON:g}x the last "
                  f"measured count ({horizon:g} {unit})")
    elif hi is None:
        reason = (f"the lower band does not reach {limit:g} µm within {horizon:g} {unit}: "
                  f"no upper bound")
    return Life(name, float(limit), at, lo, hi, unit, reason,
                max((b - a for a, b, _ in brackets), default=None), brackets)


def _parts(a: float, b: float) -> int:
    """Equal parts of [a, b] each within LIFE_RTOL of any crossing in it (≥ a)."""
    return math.ceil((b - a) / (LIFE_RTOL * max(abs(a), 1e-300)) * (1 - 1e-12))


def _merged(pts: np.ndarray, new: np.ndarray, crank: bool) -> np.ndarray:
    """`pts` with the points `new` (whole revolutions for a crank-slider study), sorted and
    unique."""
    new = np.round(new) if crank else np.round(new, 6)
    return np.unique(np.concatenate([pts, new[new > 0]]))


def refine_count(a: float, b: float) -> int:
    """Points to add inside the bracket [a, b] so that each part is within LIFE_RTOL of any
    crossing in it (≥ a), at most LIFE_REFINE_POINTS: one round where that suffices (each
    round of a sampled forecast runs every draw again: ~185 s on the boom's importance
    posterior, which took three rounds of 8 points)."""
    return int(min(max(_parts(a, b) - 1, 1), LIFE_REFINE_POINTS))


def refined_points(study: Study, res: PredictResult, points: list[np.ndarray]):
    """`points` with `refine_count` more inside every life bracket wider than LIFE_RTOL of
    its crossing (whole revolutions for a crank-slider study); None when none is."""
    crank = not timed(study.config)
    out, more = [], False
    for pts, life in zip(points, res.life):
        new = [np.linspace(a, b, refine_count(a, b) + 2)[1:-1]
               for a, b, x in life.brackets if b - a > LIFE_RTOL * abs(x)]
        merged = _merged(pts, np.concatenate(new) if new else np.zeros(0), crank)
        more |= len(merged) > len(pts)
        out.append(merged)
    return out if more else None


def guided_points(study: Study, res: PredictResult, points: list[np.ndarray]):
    """`points` with a grid every LIFE_RTOL of the crossing over the span of each
    experiment's life brackets in `res` (a Laplace forecast's: the sampled band's crossings
    lie near its), where that takes at most LIFE_ROOM_ROUNDS x 3 x LIFE_REFINE_POINTS points
    (the room the layout keeps for refinements); None where no experiment gets any."""
    crank = not timed(study.config)
    out, more = [], False
    for pts, life in zip(points, res.life):
        if not life.brackets:
            out.append(pts)
            continue
        a, b = min(x[0] for x in life.brackets), max(x[1] for x in life.brackets)
        n = _parts(a, b)
        if not (a > 0 and 1 < n <= LIFE_ROOM_ROUNDS * 3 * LIFE_REFINE_POINTS):
            out.append(pts)
            continue
        merged = _merged(pts, np.linspace(a, b, n + 1)[1:-1], crank)
        more |= len(merged) > len(pts)
        out.append(merged)
    return out if more else None


# ---------------------------------------------------------------- the API


def _check_args(study, at, train_until, level, limit_um, method, noise_um):
    if method not in METHODS:
        raise InputError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
    check_method_packages(method)
    if not (isinstance(level, (int, float)) and 0 < level < 1):
        raise InputError(f"--level must be in (0, 1), got {level!r}")
    at = [float(a) for a in (at if np.ndim(at) else [at])]
    if not at or not all(math.isfinite(a) and a > 0 for a in at):
        raise InputError(f"--at must be a list of counts > 0 ({unit_of_study(study)}), "
                         f"got {at}")
    if train_until is not None and not (math.isfinite(train_until) and train_until > 0):
        raise InputError(f"--train-until must be > 0, got {train_until}")
    layer_um = min(float(study.params(e).layer_thickness) for e in study.experiments) * 1e6
    if limit_um is None:
        limit_um = layer_um
    if not (math.isfinite(limit_um) and 0 < limit_um <= layer_um * (1 + 1e-12)):
        raise InputError(f"--limit-um must be in (0, {layer_um:g}] (the layer thickness), "
                         f"got {limit_um}")
    if noise_um is not None and not (math.isfinite(noise_um) and noise_um > 0):
        raise InputError(f"--noise-um must be > 0, got {noise_um}")
    return sorted(set(at)), float(limit_um)


def predict(study: Study, at, *, train_until: float | None = None, level: float = 0.9,
            limit_um: float | None = None, method: str = "laplace", fit_spec=None,
            noise_um: float | None = None, verbose: bool = False, nuts_options=None,
            n_dense: int = 48, life: bool = True) -> PredictResult:
    """Forecast every experiment's maximum depth at `at` with central bands at `level`.

    **Arguments:**
    - `study`: a loaded study with data (profiles with a `revolutions` column, or histories).
    - `at`: forecast points, revolutions (crank-slider) or hours (oscillating joint).
    - `train_until`: fit only the measurements at or before it (same unit); None: all.
    - `level`: central probability of the bands. `limit_um`: depth limit for the life
      estimate (default: the layer thickness).
    - `method`: "laplace" (linearised, default), "nuts" (posterior by NUTS) or
      "importance" (posterior by PSIS importance sampling from the Laplace fit).
    - `fit_spec`: parameters to fit (as `calibrate`; default the study's [fit] parameters,
      else K_d,clearance; enabled effects' strengths are always added).
    - `noise_um`: measurement noise σ [µm] if known; default: estimated from the residuals.
    - `nuts_options`: dict for the sampling methods (`_predict_nuts.run_nuts`,
      `_predict_importance.run_importance`).
    - `n_dense`: points of the forecast grid (fan chart, life search); `life=False` skips
      the life estimate (and the forecast to 10x the last measured count).

    **Returns:** a `PredictResult` (`.to_json()` is the DESIGN §7 document).
    """
    at, limit_um = _check_args(study, at, train_until, level, limit_um, method, noise_um)
    unit = unit_of_study(study)
    keys = study_fit_keys(study, fit_spec)
    if noise_um is None:
        noise_um = study.noise_um
    if study.auto_resolution:  # the fit's Jacobian runs at the coarsest level
        study = at_level(study, _resolution.LEVELS[0])
    train = training_study(study, train_until)
    problem = build_problem(train, keys)
    # known before any evaluation: σ̂ needs more training rows than fitted parameters
    check_noise_determined(problem, noise_um, hint="--noise-um (or [fit] noise_um)")
    # the forecast's points are known before the fit: the training problem is laid out to
    # hold them (and the life's refinements), so the forecast runs in the fit's compiled
    # function
    points = [forecast_points(study, e, at, n_dense, life) for e in study.experiments]
    layout = forecast_layout(study, train, points, refine=life)
    _log(verbose, f"predict: fitting {', '.join(problem.names)} to {problem.n_data} rows "
                  f"(first call compiles the model, laid out for {layout.snapshots} forecast "
                  f"points)")
    before = traces()
    # the fit re-checks its integration error at the answer (refitting at a tighter
    # tolerance if above it) and chooses its resolution where the study leaves it open
    # (its Jacobian at the coarsest level, its rows corrected to the level it needs); the
    # forecast runs at the tolerance the fit ended with, its Jacobian at the fit's level
    # and its depths at the level the answer is corrected to
    result = fit_study(train, keys, noise_um=noise_um, verbose=verbose,
                       se_tol=FORECAST_SE_TOL, layout=layout)
    problem = result.problem
    flags = []
    resolution = result.resolution
    fine_level = None
    if resolution.get("auto") and resolution.get("corrected_to"):
        c = resolution["corrected_to"]
        fine_level = (c["nodes"], c["steps_per_rev"])
    tol = (result.integration or {}).get("tolerance_um")
    if study.integrator != "paper" and tol is not None and tol < study.wear_tolerance_um:
        study = replace(study, wear_tolerance_um=tol)
        train = training_study(study, train_until)
    m_stable = stable_update(study, result) if study.integrator == "paper" else math.inf
    if study.revolutions_per_update > m_stable:
        # The explicit update is near its stability limit at the fitted K_d: the depth may
        # look smooth while its Jacobian (and so the band) blows up at some points
        # (measured on the boom at M = 10, stable estimate ~5). Refit at a stable M.
        m_new = float(max(1, math.floor(m_stable / 2)))
        flags.append(f"[numerics] revolutions_per_update = {study.revolutions_per_update:g} "
                     f"exceeds the stable amplification ~{m_stable:.3g} at the fitted K_d; "
                     f"fitted and forecast with {m_new:g} instead")
        _log(verbose, f"predict: {flags[-1]}")
        study = replace(study, revolutions_per_update=m_new)
        train = training_study(study, train_until)
        layout = forecast_layout(study, train, points, refine=life)
        problem = build_problem(train, keys, dict(zip(result.names, map(float, result.values))),
                                layout)
        problem = problem.with_defect(result.problem.defect)
        result = replace(fit(problem, noise_um=noise_um, verbose=verbose,
                             se_tol=FORECAST_SE_TOL), resolution=resolution)
        problem = result.problem
    flags += result.flags  # a fit that did not converge says so there
    # the errors the data support (`_noise`, `lsq.error_scale`): the noise level, or the
    # training misfit where it is larger, with its degrees of freedom (inf: σ given)
    noise, dof = result.error_scale_um, result.error_dof
    q = t_quantile(level, dof)
    cov, null_dirs = result.covariance.cov, result.covariance.null_directions
    if null_dirs.shape[1]:
        flags.append(f"{null_dirs.shape[1]} parameter direction(s) not determined by the "
                     f"training data and prior: forecasts that depend on them have no band")
    fine_train = fine_base = None
    if fine_level is not None:
        fine_train = at_level(train, fine_level)
        fine_base = build_problem(fine_train, keys, dict(zip(
            problem.names, map(float, np.asarray(problem.start)))), layout)

    def forecast_at(points, factor):
        """(Jacobian-level forecast problem, the corrected level's or None) at `points`,
        each stopping past `factor` x the layer after the last `--at` point."""
        fp = stop_past_layer(train, forecast_problem(train, problem, points, layout), points,
                             at, factor)
        ff = None if fine_base is None else stop_past_layer(
            fine_train, forecast_problem(fine_train, fine_base, points, layout), points, at,
            factor)
        return fp, ff

    def assemble(points, flags, snaps, J, draws, extra):
        return _assemble(study, train, at, points, limit_um, level, method, unit, train_until,
                         result, cov, null_dirs, noise, result.noise_given, dof, q,
                         list(flags), snaps, J, draws, extra, life)

    def laplace(points, rnd):
        """The linearised (Laplace) result with the forecast at `points` (round `rnd` of the
        life refinement)."""
        _log(verbose, f"predict: forecasting {sum(len(x) for x in points)} points"
                      + (f"; life refinement {rnd}" if rnd else ""))
        # past 2x the layer the lower band's crossing of the limit is not looked for
        # (a relative band over 50 %): "no upper bound" there
        fp, ff = forecast_at(points, LAPLACE_STOP_LAYERS)
        snaps, J, integ = forecast_snapshots(fp, result.u)
        snaps, J = fill_past_stop(snaps, J)
        if ff is not None:
            # the answer is corrected to a finer level: its depths are that level's (a
            # forward run), their Jacobian the fit's, read at its nodes
            snaps = fill_past_stop(forward_run(ff, result.u, worn_ok=True).snaps)[0]
            J = on_nodes(J, snaps.shape[2])
        run_flags = list(flags)
        err_um = float(integ["error_estimate_um"]) if integ["integrator"] == "adaptive" else 0
        if not math.isfinite(err_um):
            run_flags.append(f"the forecast's integration did not reach its end in "
                             f"{integ['steps']} steps (attempts exhausted): its later points "
                             f"are not computed")
        elif integ["integrator"] == "adaptive" and not err_um <= integ["tolerance_um"]:
            run_flags.append(f"integration error estimate {integ['error_estimate_um']} µm of "
                             f"the forecast exceeds the tolerance {integ['tolerance_um']:g} "
                             f"µm: lower numerics.wear_tolerance_um")
        return assemble(points, run_flags, snaps, J, None, {"integration": integ})

    draws = extra = forecast_draws = None  # sampled posteriors: draws' forecasts, JSON
    sampled = method in ("nuts", "importance")
    if sampled:
        if method == "nuts":
            from ._predict_nuts import run_nuts as run_sampler
        else:
            from ._predict_importance import run_importance as run_sampler

        if life:
            # Each life refinement round forecasts every draw again (~80 s on the boom's
            # 200 draws): the draws' first forecast is as fine as the life needs where the
            # Laplace band crosses the limit (one Jacobian run of the answer, ~2 s there).
            guided = guided_points(study, laplace(points, 0), points)
            if guided is not None:
                _log(verbose, f"predict/{method}: the Laplace forecast's life brackets: "
                              f"the draws are forecast every {LIFE_RTOL:.1%} there "
                              f"({sum(len(x) for x in guided) - sum(len(x) for x in points)}"
                              f" more points)")
                points = guided
        _log(verbose, f"predict: forecasting {sum(len(x) for x in points)} points")
        sampler_kw = dict(nuts_options or {})
        draws_at = forecast_at  # the draws' forecast problems, at the level they ran at
        s_problem = problem
        coarse = (sampling_level(train, keys, problem, result, layout, noise_um, verbose)
                  if method == "importance" else None)
        if coarse is not None:
            s_problem, c_train, c_base = coarse

            def draws_at(points, factor):
                """The draws' forecast problems at the sampling level, corrected to the
                answer's level (its finer one, where it has one)."""
                fp, ff = forecast_at(points, factor)
                fc = stop_past_layer(c_train, forecast_problem(c_train, c_base, points,
                                                               layout), points, at, factor)
                return fc, (fp if ff is None else ff)

            sampler_kw["exact"] = {"problem": problem, "forecast": forecast_at(points, 1.0),
                                   "level": (c_train.config.nodes,
                                             c_train.config.steps_per_rev),
                                   "fit_level": (train.config.nodes,
                                                 train.config.steps_per_rev)}
            _log(verbose, f"predict/{method}: sampling at {c_train.config.nodes} x "
                          f"{c_train.config.steps_per_rev}, the rows corrected to "
                          f"{train.config.nodes} x {train.config.steps_per_rev} at the "
                          f"answer (max {np.max(np.abs(s_problem.defect)):.3g} µm); "
                          f"checked at posterior draws")
        draws, extra, forecast_draws = run_sampler(
            s_problem, result, *draws_at(points, 1.0), noise_um=noise_um, level=level,
            verbose=verbose, cov=cov, **sampler_kw)
        if coarse is not None and not extra["importance"]["level"]["used"]:
            draws_at = forecast_at  # it fell back to the fit's level

    def evaluate(points, rnd):
        """The result with the forecast at `points` (round `rnd` of the life refinement)."""
        nonlocal draws
        if sampled:
            if rnd:  # the same posterior draws, forecast at the refined points
                _log(verbose, f"predict/{method}: life refinement {rnd}: forecasting the "
                              f"draws at {sum(len(x) for x in points)} points")
                draws = forecast_draws(*draws_at(points, 1.0))
            return assemble(points, flags, None, None, draws, extra)
        return laplace(points, rnd)

    res, rnd = evaluate(points, 0), 0
    while life and rnd < LIFE_REFINE_ROUNDS:
        points = refined_points(study, res, points)
        if points is None:
            break
        rnd += 1
        res = evaluate(points, rnd)
    res.flags.extend(
        f"life of {x.experiment}: after {rnd} refinements the crossings are placed only to "
        f"±{x.numerical_error_bound:.3g} {unit}" for x in res.life
        if any(b - a > LIFE_RTOL * abs(c) for a, b, c in x.brackets))
    # compilations of the whole answer (fit, checks and every forecast), by kind
    res.extra["compiles"] = traces_since(before)
    # answers outside the model first: the fit's values, forecasts below measured depths
    outside = list(dict.fromkeys(
        [f for f in res.flags if f.startswith(OUTSIDE)]
        + forecast_flags(res.predictions, res.measured, res.noise_um, res.unit)))
    res.flags[:] = outside + [f for f in res.flags if f not in outside]
    return replace(res, outside=outside)


SAMPLING_NODES_SHARE = 0.5  # the importance sampler's level: this share of the fit's nodes
SAMPLING_NODES_MIN = 40  # ... and at least this many
SAMPLING_DEFECT_REACH = 1.0  # the level's row correction's bound in log likelihood, at most


def sampling_level(train: Study, keys, problem, result: FitResult, layout, noise_um=None,
                   verbose=False):
    """(training problem, training study, base problem) of the importance sampler's level:
    half the nodes of the fit's level (90 x 72: 45 x 72, a log density in ~45 % of the time
    on the boom), its rows corrected by the difference to the answer's level at
    the answer (defect correction, `ResidualModel.defect_um`: the rows agree exactly at û
    and, as the discretisation error moves slowly with the parameters, closely across the
    posterior; `_predict_importance.run_importance` checks that at posterior draws and
    falls back to the fit's level where it does not hold). None where the level would
    have fewer than `SAMPLING_NODES_MIN` nodes, the model does not run there at û, or the
    correction itself could move the log likelihood by more than `SAMPLING_DEFECT_REACH`
    (a level that does not resolve the scar: on the rig's narrow scar at 48 of 64 nodes
    the check at the draws found ±0.36, so it would be sampled twice)."""
    nodes = int(round(train.config.nodes * SAMPLING_NODES_SHARE))
    if nodes < SAMPLING_NODES_MIN:
        return None
    c_train = at_level(train, (nodes, train.config.steps_per_rev))
    start = dict(zip(problem.names, map(float, np.asarray(problem.start))))
    c_base = build_problem(c_train, keys, start, layout)
    fit_rows = forward_run(problem, result.u).rows
    # with a (zero) row correction: the same program as the corrected problem's runs
    c_rows = forward_run(c_base.with_defect(np.zeros(c_base.n_data)), result.u).rows
    level = f"{nodes} x {train.config.steps_per_rev}"
    if not (np.all(np.isfinite(fit_rows)) and np.all(np.isfinite(c_rows))):
        _log(verbose, f"predict/importance: the model at {level} does not run to its rows at "
                      f"the answer: sampled at the fit's level")
        return None
    defect = fit_rows - c_rows
    # the whole correction's reach in log likelihood, |Σ r δ|/σ² ≤ ‖δ‖ √χ² / σ with
    # χ² ≤ 2 (n + d) (as `_predict_nuts.sampling_tolerance_m`): only its change across the
    # posterior matters, a fraction of it where the level resolves the scar
    d = len(problem.names) + (0 if noise_um is not None else 1)
    sigma = float(noise_um if noise_um is not None else result.noise_um)
    reach = float(np.linalg.norm(defect)) * math.sqrt(2.0 * (len(defect) + d)) / sigma
    if not reach <= SAMPLING_DEFECT_REACH:
        _log(verbose, f"predict/importance: the rows at {level} differ from the fit's level "
                      f"by {reach:.3g} in log likelihood at the answer (> "
                      f"{SAMPLING_DEFECT_REACH:g}): sampled at the fit's level")
        return None
    return c_base.with_defect(defect), c_train, c_base


def on_nodes(a, nodes: int):
    """`a` (E, S, N, ...) periodic-linearly interpolated along its node axis to `nodes`
    equally spaced nodes (a Jacobian at the fit's nodes read at a finer level's)."""
    a = np.asarray(a)
    n = a.shape[2]
    if n == nodes:
        return a
    x = np.arange(nodes) * n / nodes
    i0 = np.floor(x).astype(int) % n
    w = (x - np.floor(x)).reshape((1, 1, nodes) + (1,) * (a.ndim - 3))
    return a[:, :, i0] * (1 - w) + a[:, :, (i0 + 1) % n] * w


def stable_update(study: Study, result: FitResult) -> float:
    """Largest stable amplification M at the fitted K_d (`stable_amplification`, smallest
    over the experiments); inf when K_d is not fitted."""
    from ._wear import stable_amplification

    vals = dict(zip(result.names, (float(v) for v in result.values)))
    if "K_d_per_Pa" not in vals:
        return math.inf
    return min(stable_amplification(study.params(e).with_values(
        {"K_d_per_Pa": vals["K_d_per_Pa"]}), study.config) for e in study.experiments)


def _param_table(result: FitResult, cov, q, null_dirs):
    prob = result.problem
    vals = np.asarray(result.values)
    # a parameter with a component along an undetermined direction has no standard error
    unknown = np.sum(null_dirs ** 2, axis=1) > 1e-6
    G = prob.packing.value_jacobian(result.u)  # diagonal but for product pairs
    out = {}
    for i, (name, f) in enumerate(zip(result.names, prob.columns)):
        touches = np.any((np.abs(G[i]) > 0) & unknown)
        se_u = math.inf if unknown[i] else math.sqrt(max(cov[i, i], 0.0))
        if f.log:
            se, lo, hi = vals[i] * se_u, vals[i] * math.exp(-q * se_u), vals[i] * math.exp(q * se_u)
        else:
            se = math.inf if touches else math.sqrt(max(float(G[i] @ cov @ G[i]), 0.0))
            lo, hi = vals[i] - q * se, vals[i] + q * se
        out[name] = {"value": float(vals[i]), "stderr": _jf(se), "lower": _jf(lo),
                     "upper": _jf(hi)}
    return out


def _assemble(study, train, at, points, limit_um, level, method, unit, train_until, result,
              cov, null_dirs, noise, noise_given, dof, q, flags, snaps, J, draws, extra,
              life=True):
    preds, lives, curves, profiles, measured = [], [], {}, {}, {}
    trained_on = []
    alpha = (1 - level) / 2
    for ei, e in enumerate(study.experiments):
        pts = points[ei]
        S = len(pts)
        if draws is None:
            s = snaps[ei, :S]  # (S, N)
            k = np.argmax(s, axis=1)
            depth = s[np.arange(S), k]
            g = J[ei, np.arange(S), k]  # (S, p)
            sd_m, sd_p = _band(g, cov, null_dirs, noise, q)
            c_lo, c_hi = depth - q * sd_m, depth + q * sd_m
            p_lo, p_hi = depth - q * sd_p, depth + q * sd_p
        else:
            d = draws["max_um"][:, ei, :S]  # (draws, S)
            y = draws["new_um"][:, ei, :S]
            depth = np.median(d, axis=0)
            c_lo, c_hi = np.quantile(d, alpha, axis=0), np.quantile(d, 1 - alpha, axis=0)
            p_lo, p_hi = draw_quantile(y, alpha), draw_quantile(y, 1 - alpha)
            with np.errstate(invalid="ignore"):  # NaN past worn-through draws (unused)
                sd_m, sd_p = np.std(d, axis=0), np.std(y, axis=0)
        layer = float(study.params(e).layer_thickness) * 1e6
        valid = np.isfinite(depth) & (np.maximum.accumulate(np.nan_to_num(depth, nan=np.inf))
                                      < layer)
        curves[e.name] = Curve(pts, depth, p_lo, p_hi, c_lo, c_hi, valid)
        mpts, mmax = measured_max(e)
        te = train.experiments[ei]
        tpts = set(te.snapshot_points)
        measured[e.name] = (mpts, mmax, np.array([m in tpts for m in mpts], bool))
        if tpts:
            trained_on.append({"experiment": e.name, "unit": unit, "points": sorted(tpts),
                               "rows": int(np.sum(np.asarray(result.problem.data.exp) == ei))})
        for a in at:
            j = int(np.argmin(np.abs(pts - a)))
            hit = np.isclose(mpts, a, rtol=1e-9, atol=1e-9)
            meas = float(mmax[hit][0]) if hit.any() else None
            bad = not valid[j]
            preds.append(Prediction(
                e.name, float(a), unit, np.inf if bad else float(depth[j]),
                *(np.nan if bad else float(v) for v in (p_lo[j], p_hi[j])), meas,
                *(np.nan if bad else float(v) for v in (c_lo[j], c_hi[j], sd_m[j], sd_p[j]))))
            if bad:
                flags.append(f"{e.name} at {a:g} {unit}: the layer is worn through (no forecast)")
        horizon = LIFE_HORIZON * _last_count(te if te.snapshot_points else e)
        life_mask = pts <= horizon * (1 + 1e-12)
        # Past the central forecast's wear-through the model is extrapolated (first point
        # beyond the layer): its values still place the crossing between two grid points.
        def fin(v):
            # NaN (worn through) counts as reached; a band of ±inf (no band: an
            # undetermined direction) stays as it is: the upper reaches at once, the lower
            # never
            return np.where(np.isnan(v), np.inf, v)[life_mask]

        if life:
            lives.append(life_of(e.name, pts[life_mask], fin(depth), fin(p_lo), fin(p_hi),
                                 limit_um, unit, horizon))
        j = int(np.argmin(np.abs(pts - max(at))))
        if draws is None:
            prof = snaps[ei, j]
            sdm, sdp = _band(J[ei, j], cov, null_dirs, noise, q)
            plo, phi, clo, chi = prof - q * sdp, prof + q * sdp, prof - q * sdm, prof + q * sdm
        else:
            pr = draws["snapshots_um"][:, ei, j]  # (draws, N)
            prof = np.median(pr, axis=0)
            clo, chi = np.quantile(pr, alpha, axis=0), np.quantile(pr, 1 - alpha, axis=0)
            yy = pr + draws["noise"][:, None] * np.random.default_rng(ei).standard_normal(
                pr.shape)
            plo, phi = np.quantile(yy, alpha, axis=0), np.quantile(yy, 1 - alpha, axis=0)
        if prof is not None:
            n = len(prof)
            profiles[e.name] = {"at": float(pts[j]), "angle_deg": np.arange(n) * 360.0 / n,
                                "depth_um": prof, "lower_um": plo, "upper_um": phi,
                                "conf_lower_um": clo, "conf_upper_um": chi}
    return PredictResult(level=float(level), method=method, unit=unit,
                         train_until=None if train_until is None else float(train_until),
                         trained_on=trained_on, predictions=preds, life=lives,
                         parameters=_param_table(result, cov, q, null_dirs), noise_um=float(noise),
                         noise_given=noise_given, dof=float(dof), quantile=float(q),
                         fit_converged=bool(result.converged), fit_message=result.message,
                         fit_resolution=result.resolution,
                         fit_evaluations=int(result.iterations),
                         noise_source=(result.noise.describe() if result.noise else ""),
                         flags=flags, curves=curves, profiles=profiles, measured=measured,
                         extra=extra)
