"""Calibration: least squares of measured minus predicted depth over a whole study (§6-7).

All experiments of a study run in one compiled function (schedules padded to a common
length), and that one function returns the residuals, the exact forward-mode Jacobian
through the whole wear loop (`jax.jacfwd`), and the model's snapshots. Everything the fit
needs (the robust start, every Levenberg-Marquardt trial, both passes, the standard errors)
is an evaluation of it, so a problem compiles once. The Levenberg-Marquardt iteration runs
on the host on p × p matrices (p = number of fitted parameters, a handful), or with
`engine="optimistix"` as `optimistix.LevenbergMarquardt` in one jit whose residual function
has a custom JVP taking (r, J) from that same compiled evaluation through a host callback:
letting optimistix differentiate the wear loop itself (`jax.linearize`) would trace and
compile the loop a second time. Measured, the host loop is as fast cached and ~1 s faster
cold (it compiles nothing else), hence the default (README, "Calibration output").

Parameterisation: positive parameters (K_d, clearances, S_r) are fitted as log-multipliers
of their start, nested effect strengths linearly around their "off" value in units of a
typical scale. The clearance-tolerance prior of DESIGN §6 adds one residual per fitted
clearance, (c - c_nominal)/τ, in units of the noise level (estimated from a first pass);
τ = inf gives zero rows (free clearances), τ = 0 removes the clearances from the fit.
With `[fit] angle_tolerance_deg` > 0 each profile's angular registration is fitted too
(`angle_offset_deg/EXP`, linear, started at the given offset, the same kind of prior row):
the model is read at the shifted angles by a periodic interpolation differentiable in the
offset (docs/measurements.md).

Robust start: depth is nearly proportional to K_d, so before the iteration K_d is divided
by 10 until the model no longer wears through the layer, then rescaled so that the model's
depth matches the data in least squares. This brings a start 100x off to within a few
percent, where Levenberg-Marquardt converges in a few steps.

Outcome semantics: a fit that stops without meeting its convergence test still returns its
result, with `converged = False` and a `message` saying why; only a start that cannot be
evaluated at all (worn through whatever K_d, or non-finite) raises `FitError`.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._config import ModelConfig
from ._errors import InputError
from ._params import PARAMETER_KEYS, Params, key_to_si
from ._schedule import Schedule, pad_schedule
from ._study import Study
from ._wear import adaptive_attempts, build_schedule, schedule_numerics, wear_loop
from .effects import effect_parameter_specs, get_effect


class FitError(RuntimeError):
    """The fit could not start: the model cannot be evaluated at any usable start."""


@dataclass(frozen=True)
class FitParameter:
    """One fitted quantity. `name` is its output name (DESIGN §7), `key` its study key,
    `experiment` the index it belongs to (None: shared by all experiments)."""

    name: str
    key: str
    experiment: int | None
    log: bool
    scale: float  # user units per unit of u (linear parameters)


_UNITS = (("_m_per_Pa_s", "m/(Pa·s)"), ("_N_per_m", "N/m"), ("_m_per_s2", "m/s²"),
          ("_per_Pa", "1/Pa"), ("_ratio", "-"), ("_GPa", "GPa"), ("_rpm", "r/min"),
          ("_deg", "deg"), ("_mm", "mm"), ("_um", "µm"), ("_kg", "kg"), ("_N", "N"),
          ("_s", "s"), ("_m", "m"))


def unit_of(name: str) -> str:
    """Unit named by a study key's suffix (`clearance_mm/EXP` → mm); dimensionless → "-"."""
    key = name.split("/")[0]
    for suffix, unit in _UNITS:
        if key.endswith(suffix):
            return unit
    return "-"


def parse_fit(study: Study, fit: str | list[str] | None) -> list[str]:
    """Study keys to fit from `--fit` (aliases K_d, clearance) plus enabled effects' strengths."""
    items = fit.split(",") if isinstance(fit, str) else list(fit or [])
    items = [s.strip() for s in items if s.strip()] or ["K_d", "clearance"]
    alias = {"K_d": "K_d_per_Pa", "clearance": "clearance_mm",
             "angle_offset": "angle_offset_deg"}
    specs = effect_parameter_specs()
    keys = []
    for it in items:
        key = alias.get(it, it)
        if key not in PARAMETER_KEYS and key not in specs and key != "angle_offset_deg":
            raise InputError(f"--fit: unknown parameter {it!r}; expected K_d, clearance or a "
                             f"study key such as spring_N_per_m")
        keys.append(key)
    for eff in study.config.effects:
        for k in get_effect(eff).parameters:
            if k not in keys:
                keys.append(k)
    return list(dict.fromkeys(keys))


def with_registration(study: Study, keys: list[str]) -> list[str]:
    """`keys` plus the scans' angular registration (`angle_offset_deg`, one per profile
    experiment) when the study's `[fit] angle_tolerance_deg` is > 0."""
    if study.angle_tolerance_deg > 0 and "angle_offset_deg" not in keys:
        return [*keys, "angle_offset_deg"]
    return list(keys)


def fit_parameters(study: Study, keys: list[str]) -> list[FitParameter]:
    specs = effect_parameter_specs()
    out = []
    for key in keys:
        if key == "clearance_mm":
            if study.clearance_tolerance_um == 0:
                continue  # fixed at nominal by the prior's zero width
            for i, e in enumerate(study.experiments):
                out.append(FitParameter(f"clearance_mm/{e.name}", key, i, True, 1.0))
        elif key == "angle_offset_deg":
            if not study.angle_tolerance_deg > 0:
                continue  # registration known: fixed at the given offset
            for i, e in enumerate(study.experiments):
                if e.profile is not None:  # a history (maximum depth) has no angle
                    out.append(FitParameter(f"angle_offset_deg/{e.name}", key, i, False, 1.0))
        elif key in specs:
            s = specs[key]
            out.append(FitParameter(key, key, None, s.log, s.scale))
        else:
            out.append(FitParameter(key, key, None, PARAMETER_KEYS[key].positive, 1.0))
    return out


class Data(eqx.Module):
    """Measured rows, flattened over experiments: where each lives in the model output."""

    exp: jax.Array  # experiment index (rows,)
    snap: jax.Array  # snapshot index
    i0: jax.Array  # interpolation nodes and weight (profiles)
    i1: jax.Array
    w: jax.Array
    is_max: jax.Array  # True: maximum depth (history rows)
    depth_um: jax.Array  # measured [µm]
    x: jax.Array  # angle [deg] (profiles) or hours (history), for reports only
    angle: jax.Array  # bushing-frame angle at the given registration [rad] (0: history)
    offset_fit: jax.Array  # index of the row's fitted angle offset among the fits, or -1


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def _schedules(study: Study, plist: list[Params]) -> Schedule:
    scheds = [build_schedule(p, study.config, revolutions=e.revolutions, hours=e.hours,
                             snapshots=e.snapshot_points or [e.hours or e.revolutions],
                             pad=False, **schedule_numerics(study))
              for p, e in zip(plist, study.experiments)]
    U = max(s.updates for s in scheds)
    S = max(s.n_snapshots for s in scheds)
    A = max(s.attempts for s in scheds)
    return _stack([pad_schedule(s, U, S, A) for s in scheds])


def _data(study: Study, fits=()) -> Data:
    n = study.config.nodes
    offset_fit = {f.experiment: i for i, f in enumerate(fits) if f.key == "angle_offset_deg"}
    rows = {k: [] for k in ("exp", "snap", "i0", "i1", "w", "is_max", "depth_um", "x",
                            "angle", "offset_fit")}
    for ei, e in enumerate(study.experiments):
        points = e.snapshot_points
        if e.profile is not None:
            # periodic linear interpolation between the two nodes around each measured angle
            x = np.mod(e.profile.angle / (2 * np.pi) * n, n)
            i0 = np.floor(x).astype(int) % n
            for j in range(len(x)):
                rows["exp"].append(ei)
                rows["snap"].append(points.index(float(e.profile.revolutions[j])))
                rows["i0"].append(i0[j]), rows["i1"].append((i0[j] + 1) % n)
                rows["w"].append(x[j] - np.floor(x[j])), rows["is_max"].append(False)
                rows["depth_um"].append(e.profile.depth[j] * 1e6)
                rows["x"].append(float(np.degrees(e.profile.angle[j])))
                rows["angle"].append(float(e.profile.angle[j]))
                rows["offset_fit"].append(offset_fit.get(ei, -1))
        if e.history is not None:
            for t, d in zip(e.history.hours, e.history.depth):
                rows["exp"].append(ei), rows["snap"].append(points.index(float(t)))
                rows["i0"].append(0), rows["i1"].append(0), rows["w"].append(0.0)
                rows["is_max"].append(True), rows["depth_um"].append(d * 1e6)
                rows["x"].append(float(t))
                rows["angle"].append(0.0), rows["offset_fit"].append(-1)
    if not rows["exp"]:
        raise InputError(f"{study.path}: no measured data (profile or history) to fit")
    return Data(exp=jnp.asarray(rows["exp"]), snap=jnp.asarray(rows["snap"]),
                i0=jnp.asarray(rows["i0"]), i1=jnp.asarray(rows["i1"]),
                w=jnp.asarray(rows["w"], jnp.float64), is_max=jnp.asarray(rows["is_max"]),
                depth_um=jnp.asarray(rows["depth_um"], jnp.float64),
                x=jnp.asarray(rows["x"], jnp.float64),
                angle=jnp.asarray(rows["angle"], jnp.float64),
                offset_fit=jnp.asarray(rows["offset_fit"], jnp.int32))


class Problem(eqx.Module):
    """A study's least-squares problem: parameters u ↦ residuals [µm].

    `tolerance_um` is an array (not a static field), so changing the prior's width reuses
    the compiled function.
    """

    cfg: ModelConfig = eqx.field(static=True)
    fits: tuple = eqx.field(static=True)
    names: tuple = eqx.field(static=True)
    exp_names: tuple = eqx.field(static=True)
    params: Params  # batched over experiments (leading axis)
    schedule: Schedule  # batched
    data: Data
    start: jax.Array  # start values of the fitted parameters, user units (p,)
    nominal_clearance_mm: jax.Array  # (experiments,)
    tolerance_um: jax.Array  # clearance prior's standard deviation (inf: no prior)
    nominal_angle_deg: jax.Array  # given registration offsets (experiments,)
    angle_tolerance_deg: jax.Array  # their prior's standard deviation

    @property
    def n_data(self) -> int:
        return int(self.data.depth_um.shape[0])

    @property
    def has_prior(self) -> bool:
        """True when fitted clearances or angle offsets carry a finite-width prior (the fit
        needs 2 passes)."""
        return (math.isfinite(float(self.tolerance_um)) and any(
            f.key == "clearance_mm" for f in self.fits)) or self.fits_angles

    @property
    def fits_angles(self) -> bool:
        return any(f.key == "angle_offset_deg" for f in self.fits)

    def values(self, u):
        """Fitted parameters in user units from u (p,)."""
        out = []
        for i, f in enumerate(self.fits):
            if f.log:
                out.append(self.start[i] * jnp.exp(u[i]))
            else:
                out.append(self.start[i] + f.scale * u[i])
        return jnp.stack(out) if out else jnp.zeros(0)

    def u_of(self, values):
        """Inverse of `values` (numpy in, numpy out)."""
        v = np.asarray(values, float)
        s = np.asarray(self.start)
        out = []
        for i, f in enumerate(self.fits):
            out.append(np.log(v[i] / s[i]) if f.log else (v[i] - s[i]) / f.scale)
        return np.array(out)

    def batched_params(self, u) -> Params:
        vals = self.values(u)
        p = self.params
        n_exp = len(self.exp_names)
        updates: dict = {}
        for i, f in enumerate(self.fits):
            if f.key == "angle_offset_deg":
                continue  # a property of the measurement, not of the joint
            si = vals[i] * key_to_si(f.key)
            cur = updates.get(f.key, p.get(f.key))
            if f.experiment is None:
                updates[f.key] = jnp.broadcast_to(si, (n_exp,))
            else:
                updates[f.key] = jnp.asarray(cur).at[f.experiment].set(si)
        return p.with_values(updates) if updates else p

    def snapshots(self, u):
        """Model snapshots (experiments, snapshots, nodes) [µm] and the batched WearResult."""
        # lax.map, not vmap: on CPU the experiments gain nothing from batching, and mapping
        # keeps the contact solver's data-dependent branches and loop counts per experiment.
        res = jax.lax.map(lambda ps: wear_loop(ps[0], self.cfg, ps[1]),
                          (self.batched_params(u), self.schedule))
        return res.snapshots * 1e6, res

    def predict_from(self, snaps_um, u=None):
        """Model depth at every measured row [µm] from snapshots (experiments, snaps, nodes).

        With fitted angle offsets (and u given), each profile row is read at its angle
        shifted by (fitted - given) offset, by periodic linear interpolation written so that
        it is differentiable in the offset: the weight w is smooth in the angle and the node
        indices (floor) are locally constant, so d(depth)/d(offset) is the slope of the
        profile between the two nodes."""
        d = self.data
        prof = snaps_um[d.exp, d.snap]  # (rows, nodes)
        if self.fits_angles and u is not None:
            n = prof.shape[1]
            vals = self.values(u)
            k = jnp.clip(d.offset_fit, 0, None)
            shift = jnp.where(d.offset_fit >= 0,
                              vals[k] - self.nominal_angle_deg[d.exp], 0.0)  # deg
            x = jnp.mod((d.angle + jnp.deg2rad(shift)) / (2 * jnp.pi) * n, n)
            fl = jnp.floor(x)
            i0 = fl.astype(jnp.int32) % n
            i1 = (i0 + 1) % n
            w = x - fl
        else:
            i0, i1, w = d.i0, d.i1, d.w
        at = jnp.take_along_axis(prof, i0[:, None], 1)[:, 0] * (1 - w) + \
            jnp.take_along_axis(prof, i1[:, None], 1)[:, 0] * w
        return jnp.where(d.is_max, jnp.max(prof, axis=1), at)

    def predict(self, u):
        """Model depth at every measured row [µm]."""
        return self.predict_from(self.snapshots(u)[0], u)

    def data_residuals(self, u):
        return self.predict(u) - self.data.depth_um

    def prior_residuals(self, u, noise_um):
        """(c - c_nominal)/τ per fitted clearance, scaled to µm of depth by the noise level.

        τ = inf gives rows of zeros (no prior) with the same shapes as a finite τ.
        """
        vals = self.values(u)
        out = [(vals[i] - self.nominal_clearance_mm[f.experiment]) * 1e3 / self.tolerance_um
               for i, f in enumerate(self.fits) if f.key == "clearance_mm"]
        # angle offsets: (δ - δ_given)/τ_angle, the same Gaussian prior as the clearances
        out += [(vals[i] - self.nominal_angle_deg[f.experiment]) / self.angle_tolerance_deg
                for i, f in enumerate(self.fits) if f.key == "angle_offset_deg"]
        return noise_um * jnp.stack(out) if out else jnp.zeros(0)

    def residuals(self, u, noise_um):
        return jnp.concatenate([self.data_residuals(u), self.prior_residuals(u, noise_um)])

    # The interface `jaxwear.diagnose` builds its extended model from (host-side copies).

    def fitted(self) -> list[tuple[FitParameter, float]]:
        """The fitted parameters with their start values (user units)."""
        return list(zip(self.fits, np.asarray(self.start).tolist()))

    def experiments(self) -> tuple[Params, Schedule, tuple[str, ...]]:
        """Batched parameters (SI), batched schedules and names of the experiments."""
        return self.params, self.schedule, self.exp_names

    def measured_rows(self) -> dict[str, np.ndarray]:
        """The data rows as numpy arrays: `exp`, `snap` (indices), `i0`, `i1`, `w` (profile
        interpolation between nodes), `is_max` (history rows), `depth_um`, `x` (angle [deg]
        or hours)."""
        d = self.data
        return {k: np.asarray(getattr(d, k))
                for k in ("exp", "snap", "i0", "i1", "w", "is_max", "depth_um", "x")}

    def nominal_clearances_mm(self) -> np.ndarray:
        """The study's clearance of each experiment [mm] (the prior's centre)."""
        return np.asarray(self.nominal_clearance_mm)


def build_problem(study: Study, keys: list[str], start: dict | None = None) -> Problem:
    """The least-squares problem for fitting study keys `keys` (see `parse_fit`).

    `start`: optional start values by output name (user units), else the study's values.
    """
    fits = fit_parameters(study, keys)
    plist = [study.params(e) for e in study.experiments]
    nominal = [float(p.clearance) * 1e3 for p in plist]
    nominal_angle = [e.profile.angle_offset_deg if e.profile is not None else 0.0
                     for e in study.experiments]
    start = dict(start or {})
    unknown = sorted(set(start) - {f.name for f in fits})
    if unknown:
        raise InputError(f"start values for {unknown}, which are not fitted; fitted: "
                         f"{[f.name for f in fits]}")
    s0 = []
    specs = effect_parameter_specs()
    for f in fits:
        if f.name in start:
            s0.append(float(start[f.name]))
        elif f.key == "angle_offset_deg":
            s0.append(nominal_angle[f.experiment])  # the given registration
        elif f.experiment is not None:
            s0.append(float(plist[f.experiment].get(f.key)) / key_to_si(f.key))
        elif f.key in specs and not f.log:
            s0.append(specs[f.key].off)  # nested: the fit starts from the base model
        else:
            s0.append(float(plist[0].get(f.key)) / key_to_si(f.key))
    for f, v in zip(fits, s0):
        if f.log and not v > 0:
            raise InputError(f"start value of {f.name} must be > 0 to fit it, got {v}")
    return Problem(cfg=study.config, fits=tuple(fits), names=tuple(f.name for f in fits),
                   exp_names=tuple(e.name for e in study.experiments),
                   params=_stack(plist), schedule=_schedules(study, plist),
                   data=_data(study, fits), start=jnp.asarray(s0, jnp.float64),
                   nominal_clearance_mm=jnp.asarray(nominal),
                   tolerance_um=jnp.asarray(study.clearance_tolerance_um, jnp.float64),
                   nominal_angle_deg=jnp.asarray(nominal_angle, jnp.float64),
                   angle_tolerance_deg=jnp.asarray(study.angle_tolerance_deg or 1.0,
                                                   jnp.float64))


class Evaluation(eqx.Module):
    """One evaluation of a problem at u (numpy arrays after `_evaluate`).

    `residuals` (rows + prior rows,) [µm]; `jacobian` (rows + prior rows, p) w.r.t. u;
    `predicted` (rows,) [µm]; `snapshots` (experiments, snapshots, nodes) [µm];
    `max_residual`: largest relative contact residual; `worn`: largest worn-through cycle
    (-1: none).
    """

    residuals: jax.Array
    jacobian: jax.Array
    predicted: jax.Array
    snapshots: jax.Array
    max_residual: jax.Array
    worn: jax.Array
    error_estimate: jax.Array | None = None  # integration error [µm], largest experiment
    steps: jax.Array | None = None  # accepted integration steps, largest experiment


@eqx.filter_jit
def _evaluate_jit(problem: Problem, u, noise_um) -> Evaluation:
    def f(v):
        snaps, res = problem.snapshots(v)
        pred = problem.predict_from(snaps, v)
        r = jnp.concatenate([pred - problem.data.depth_um, problem.prior_residuals(v, noise_um)])
        return r, (r, pred, snaps, jnp.max(res.max_residual), jnp.max(res.worn_through_cycle),
                   jnp.max(res.error_estimate) * 1e6, jnp.max(res.steps))

    # Forward mode: p (a handful) tangents through the wear loop, pushed alongside the primal.
    J, (r, pred, snaps, mres, worn, err, steps) = jax.jacfwd(f, has_aux=True)(u)
    # an adaptive loop that ran out of attempts stopped early: not a usable model
    r = jnp.where(jnp.isfinite(err), r, jnp.nan)
    return Evaluation(r, J, pred, snaps, mres, worn, err, steps)


def _enough_attempts(problem: Problem, u) -> Problem:
    """`problem` with the adaptive loop's static attempt count raised (to a power of 2, so
    that few compilations arise) where the parameters at u need more than it has (the
    stiffness-limited step count grows with K_d, which the fit moves by orders)."""
    sched = problem.schedule
    if not sched.adaptive:
        return problem
    pb = problem.batched_params(jnp.asarray(u, jnp.float64))
    need = 0
    for i in range(sched.cycles.shape[0]):
        p_i = jax.tree.map(lambda x: x[i], pb)
        one = dataclasses.replace(jax.tree.map(lambda x: x[i], sched), attempts=1)
        need = max(need, adaptive_attempts(p_i, problem.cfg, one))
    if need <= sched.attempts:
        return problem
    more = 2 ** math.ceil(math.log2(need))
    return dataclasses.replace(problem, schedule=dataclasses.replace(sched, attempts=more))


def evaluate(problem: Problem, u, noise_um: float = 1.0) -> Evaluation:
    """Residuals, Jacobian and snapshots at u, as numpy arrays (one compiled function)."""
    problem = _enough_attempts(problem, u)
    u, noise_um = jnp.asarray(u, jnp.float64), jnp.asarray(noise_um, jnp.float64)
    ev = _evaluate_jit(problem, u, noise_um)
    # The attempt count is an estimate: where the loop did not reach the end (a stiff
    # layer's rejections), double it (a recompilation) rather than hand LM a NaN.
    for _ in range(3):
        if not (problem.schedule.adaptive and not np.isfinite(float(ev.error_estimate))):
            break
        sched = problem.schedule
        problem = dataclasses.replace(
            problem, schedule=sched.more_attempts())
        ev = _evaluate_jit(problem, u, noise_um)
    return jax.tree.map(np.asarray, ev)


def _usable(ev: Evaluation) -> bool:
    return bool(np.all(np.isfinite(ev.residuals)) and np.all(np.isfinite(ev.jacobian))
                and float(ev.worn) < 0)


def _log(verbose, msg):
    if verbose:
        print(msg, file=sys.stderr, flush=True)


def robust_start(problem: Problem, u, noise_um: float = 1.0, *, verbose=False):
    """Bring K_d (if fitted) to the data's scale before Levenberg-Marquardt.

    1. While the model wears through the layer (or is not finite), divide K_d by 10.
    2. Depth is nearly proportional to K_d: multiply K_d by the least-squares factor
       a = Σ m·d / Σ d·d between measured m and predicted d (repeated while |ln a| > 2 %,
       at most 3 times, since wear slightly changes the contact).

    Returns (u, evaluation at u). Raises `FitError` if no K_d down to 1e-8 of the start
    gives a usable model.
    """
    u = np.array(u, dtype=np.float64)
    ev = evaluate(problem, u, noise_um)
    k = next((i for i, f in enumerate(problem.fits) if f.key == "K_d_per_Pa"), None)
    tries = 0
    while not _usable(ev):
        if k is None or tries >= 8:
            why = ("the layer wears through" if float(ev.worn) >= 0
                   else "the model is not finite")
            raise FitError(f"cannot start the fit: {why} at the start values "
                           f"{dict(zip(problem.names, np.asarray(problem.values(u))))}"
                           + ("" if k is None else " even with K_d reduced 1e8-fold"))
        u[k] -= math.log(10.0)
        tries += 1
        _log(verbose, f"  start: layer worn through or model not finite; K_d / 10 → "
                      f"{float(problem.values(u)[k]):.3e}")
        ev = evaluate(problem, u, noise_um)
    if k is None:
        return u, ev
    meas = np.asarray(problem.data.depth_um)
    for _ in range(3):
        d = ev.predicted
        dd = float(d @ d)
        if not dd > 0:
            break
        a = float(d @ meas) / dd
        if not (a > 0 and math.isfinite(a)) or abs(math.log(a)) < 0.02:
            break
        trial = u.copy()
        trial[k] += math.log(a)
        ev_t = evaluate(problem, trial, noise_um)
        if not _usable(ev_t):
            break
        u, ev = trial, ev_t
        _log(verbose, f"  start: K_d rescaled x{a:.3g} to the data → "
                      f"{float(problem.values(u)[k]):.3e} 1/Pa")
    return u, ev


@dataclass
class LMOutcome:
    u: np.ndarray
    evaluation: Evaluation
    converged: bool
    evaluations: int
    message: str


def levenberg_marquardt(problem: Problem, u0, noise_um: float, *, ev0: Evaluation | None = None,
                        max_evaluations: int = 60, xtol: float = 1e-8, ftol: float = 1e-10,
                        gtol: float = 1e-8, setol: float = 1e-3,
                        verbose: bool = False) -> LMOutcome:
    """Levenberg-Marquardt with Marquardt's diagonal scaling and Nielsen's damping update.

    Every trial point is one call of the compiled residual/Jacobian function; an accepted
    trial's Jacobian is the next linearisation. Converged when an accepted step changes u
    by < xtol (u is a log-multiplier: relative change) or by < setol standard errors of
    every parameter (at the misfit's noise level: moving further cannot matter to the
    result), the misfit by < ftol relative, or the residual is orthogonal to every Jacobian
    column to within gtol (MINPACK's tests).
    Trial points where the model wears through or is not finite are rejected.
    """
    u = np.array(u0, dtype=np.float64)
    ev = evaluate(problem, u, noise_um) if ev0 is None else ev0
    evals = 0 if ev0 is not None else 1
    if not _usable(ev):
        return LMOutcome(u, ev, False, evals, "the model is not usable at the start values "
                         "(worn through or not finite)")
    r, J = ev.residuals, ev.jacobian
    F = 0.5 * float(r @ r)
    p = J.shape[1]
    n = problem.n_data
    if p == 0:
        return LMOutcome(u, ev, True, evals, "nothing to fit")
    A, g = J.T @ J, J.T @ r
    lam, nu = 1e-3, 2.0
    t0 = time.perf_counter()
    _log(verbose, f"    LM start: rms residual {math.sqrt(2 * F / max(n, 1)):.4f} µm")
    while True:
        col = np.sqrt(np.maximum(np.diag(A), 1e-300))
        if np.max(np.abs(g) / col) <= gtol * math.sqrt(2 * F + 1e-300):
            return LMOutcome(u, ev, True, evals, "converged (gradient orthogonal to residuals)")
        if evals >= max_evaluations:
            return LMOutcome(u, ev, False, evals, f"did not converge within {max_evaluations} "
                             f"model evaluations")
        if lam > 1e16:
            return LMOutcome(u, ev, False, evals, "stalled: no step reduces the misfit "
                             "(damping exhausted)")
        D = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
        try:
            step = np.linalg.solve(A + lam * np.diag(D), -g)
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(A + lam * np.diag(D), -g, rcond=None)[0]
        trial = u + step
        ev_t = evaluate(problem, trial, noise_um)
        evals += 1
        r_t = ev_t.residuals
        F_t = 0.5 * float(r_t @ r_t) if _usable(ev_t) else math.inf
        predicted = -(float(step @ g) + 0.5 * float(step @ A @ step))
        rho = (F - F_t) / predicted if predicted > 0 else -1.0
        if F_t < F and rho > 0:
            rel = (F - F_t) / max(F, 1e-300)
            u, ev, F = trial, ev_t, F_t
            A, g = ev.jacobian.T @ ev.jacobian, ev.jacobian.T @ ev.residuals
            lam *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
            nu = 2.0
            _log(verbose, f"    LM {evals:3d}: rms residual {math.sqrt(2 * F / n):.4f} µm, "
                          f"step {np.max(np.abs(step)):.2e}, λ {lam:.1e} "
                          f"({time.perf_counter() - t0:.1f} s)")
            if np.max(np.abs(step)) <= xtol * (1 + np.max(np.abs(u))):
                return LMOutcome(u, ev, True, evals, "converged (step below tolerance)")
            cov, unidentified = _covariance(A)
            se_u = np.sqrt(np.clip(np.diag(cov), 0, None) * 2 * F / max(len(r_t) - p, 1))
            if np.all((np.abs(step) <= setol * se_u) | unidentified):
                return LMOutcome(u, ev, True, evals, f"converged (last step < {setol:g} "
                                 f"standard errors)")
            if rel <= ftol:
                return LMOutcome(u, ev, True, evals, "converged (misfit no longer falls)")
        else:
            lam *= nu
            nu *= 2.0
            _log(verbose, f"    LM {evals:3d}: step rejected, λ → {lam:.1e}")


@dataclass
class FitResult:
    """Outcome of a calibration. Values and standard errors in the names' units."""

    names: list[str]
    values: np.ndarray
    stderr: np.ndarray
    correlation: np.ndarray
    u: np.ndarray
    rmse_um: float
    rmse_per_experiment: dict
    noise_um: float
    residuals_um: np.ndarray  # data rows
    predicted_um: np.ndarray
    measured_um: np.ndarray
    row_experiment: np.ndarray
    converged: bool
    iterations: int
    message: str
    flags: list[str]
    jacobian: np.ndarray  # of the residuals [µm] w.r.t. u (rows incl. prior)
    problem: Problem
    snapshots_um: np.ndarray  # (experiments, snapshots, nodes)
    max_contact_residual: float
    integration: dict | None = None  # error estimate at the fitted values (see `calibrate`)

    def parameters_json(self) -> dict:
        return {n: {"value": float(v), "stderr": (float(s) if np.isfinite(s) else None)}
                for n, v, s in zip(self.names, self.values, self.stderr)}

    def to_json(self) -> dict:
        """The DESIGN §7 document: `parameters` and `rmse_um`, then diagnostics."""
        tol = float(self.problem.tolerance_um)
        return {
            "parameters": self.parameters_json(),
            "rmse_um": float(self.rmse_um),
            "rmse_per_experiment_um": {k: float(v) for k, v in self.rmse_per_experiment.items()},
            "noise_um": float(self.noise_um),
            "units": {n: unit_of(n) for n in self.names},
            "correlation": {"names": list(self.names),
                            "matrix": [[float(x) if np.isfinite(x) else None for x in row]
                                       for row in np.asarray(self.correlation)]},
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "message": self.message,
            "flags": list(self.flags),
            "n_data": int(self.n_data),
            "clearance_tolerance_um": tol if math.isfinite(tol) else "inf",
            "max_contact_residual": float(self.max_contact_residual),
            "integration": self.integration,
        }

    @property
    def n_data(self) -> int:
        return len(self.residuals_um)

    @property
    def rss(self) -> float:
        return float(np.sum(self.residuals_um ** 2))


# optimistix engine. optimistix differentiates its residual function itself (jax.linearize
# at every step); through the wear loop that traces the loop a second time (primal and
# recomputed tangent copies, ~2x the compile of `_evaluate_jit`). Instead the residual
# function handed to optimistix has a custom JVP whose rule returns J·du with (r, J) from
# one forward-mode evaluation: from the study's compiled `_evaluate_jit` through a host
# callback (the engine's path: the wear loop is compiled once per study, shared with the
# robust start and the standard errors), or traced inline (`inline=True`: one more compile
# of the loop, kept for measurement). The callback memoises evaluations, so the Jacobian at
# the solution (for the covariance) is the one optimistix used, and it counts evaluations.

_HOST_MODELS: dict = {}  # token -> (u ↦ (r, J) in numpy, default device), during one solve


def _call_host_model(token, u):
    model, device = _HOST_MODELS[int(token)]
    # JAX runs callbacks under `default_device(<the CPU>)`, which is part of the jit cache
    # key: without restoring the caller's setting, `_evaluate_jit` would trace and compile
    # again (measured: +9 s on a 48-node grid).
    with jax.default_device(device):
        return model(np.asarray(u, np.float64))


@eqx.filter_jit
def _optimistix_solve(problem: Problem | None, u0, noise_um, token, n_rows: int,
                      max_steps: int, rtol: float, atol: float):
    """optimistix Levenberg-Marquardt in one jit; (u, success, steps)."""
    p = u0.shape[0]
    shapes = (jax.ShapeDtypeStruct((n_rows,), jnp.float64),
              jax.ShapeDtypeStruct((n_rows, p), jnp.float64))

    def model(v):
        if problem is None:
            return jax.pure_callback(_call_host_model, shapes, token, v)
        ev = _evaluate_jit(problem, v, noise_um)
        # a trial where the layer wears through is a misfit, not a minimum (as in "lm")
        bad = (ev.worn >= 0) | ~jnp.all(jnp.isfinite(ev.residuals))
        return jnp.where(bad, 1e100, ev.residuals), jnp.where(bad, 0.0, ev.jacobian)

    @jax.custom_jvp
    def residuals(v):
        return model(v)[0]

    @residuals.defjvp
    def residuals_jvp(primals, tangents):
        r, J = model(primals[0])
        return r, J @ tangents[0]

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(lambda v, _: residuals(v), solver, u0, max_steps=max_steps,
                             throw=False)
    return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


_OPTX_RTOL, _OPTX_ATOL = 1e-6, 1e-5


def _n_rows(problem: Problem) -> int:
    """Residual rows: data plus one prior row per fitted clearance or angle offset."""
    return problem.n_data + sum(f.key in ("clearance_mm", "angle_offset_deg")
                                for f in problem.fits)


def _run_optimistix(problem, u0, noise_um, host_model, n_rows, max_steps, rtol, atol):
    """`_optimistix_solve` with `host_model` (u ↦ (r, J), numpy) registered for its callback."""
    token = id(host_model)
    _HOST_MODELS[token] = (host_model, jax.config.jax_default_device)
    try:
        return _optimistix_solve(
            problem, jnp.asarray(u0, jnp.float64), jnp.asarray(noise_um, jnp.float64),
            jnp.asarray(token, jnp.int64), n_rows, max_steps, rtol, atol)
    finally:
        del _HOST_MODELS[token]


def _fit_optimistix(problem: Problem, u0, noise_um: float, *, ev0: Evaluation | None = None,
                    max_evaluations: int = 60, rtol: float = _OPTX_RTOL,
                    atol: float = _OPTX_ATOL, inline: bool = False,
                    verbose: bool = False) -> LMOutcome:
    """`optx.LevenbergMarquardt` on the study's residuals (see the comment above).

    Converged when optimistix's Cauchy test holds: the last accepted step changes every
    u (log-multipliers: relative) by < atol + rtol·|u| and every residual by < atol +
    rtol·|r| µm. atol carries the test: rtol·|u| would depend on how far the start was off
    (u is measured from it). With 1e-5 it lands within 2e-4 standard errors of "lm"'s
    minimum on the benchmark's rig study, with as many model evaluations (64 nodes) or one
    more (360 nodes: "lm" stops on a step < 1e-3 standard errors, one step earlier).
    Trial points where the model wears through or is not finite get residuals of 1e100
    (rejected by the trust region). Returns the same `LMOutcome` as `levenberg_marquardt`.
    """
    u0 = np.asarray(u0, np.float64)
    cache: dict = {} if ev0 is None else {u0.tobytes(): ev0}
    count = [0]
    t0 = time.perf_counter()

    def host_model(v):
        key = v.tobytes()
        ev = cache.get(key)
        if ev is None:
            ev = evaluate(problem, v, noise_um)
            cache[key] = ev
            count[0] += 1
            r = ev.residuals
            _log(verbose, f"    optimistix {count[0]:3d}: rms residual "
                          f"{math.sqrt(float(r @ r) / max(problem.n_data, 1)):.4f} µm "
                          f"({time.perf_counter() - t0:.1f} s)")
        if not _usable(ev):
            return np.full_like(ev.residuals, 1e100), np.zeros_like(ev.jacobian)
        return ev.residuals, ev.jacobian

    u_new, ok, steps = _run_optimistix(problem if inline else None, u0, noise_um, host_model,
                                       _n_rows(problem), max_evaluations, rtol, atol)
    u_new = np.asarray(u_new)
    ev = cache.get(u_new.tobytes())
    if ev is None:  # inline, or optimistix returned a point it did not evaluate
        ev = evaluate(problem, u_new, noise_um)
    ok = bool(ok) and _usable(ev)
    msg = ("converged (optimistix Levenberg-Marquardt: step and residual change below "
           "tolerance)" if ok else f"optimistix Levenberg-Marquardt did not converge within "
           f"{max_evaluations} steps")
    return LMOutcome(u_new, ev, ok, count[0] if not inline else int(steps), msg)


def fit(problem: Problem, u0=None, *, max_steps: int = 60, rtol: float = 1e-8,
        verbose: bool = False, robust: bool = True, engine: str = "lm") -> FitResult:
    """Levenberg-Marquardt fit, then Gauss-Newton standard errors and correlations.

    **Arguments:**
    - `u0`: start in the problem's parameterisation (default: the problem's start values).
    - `max_steps`: model evaluations allowed per pass. `rtol`: step tolerance on u
      (`"lm"`; optimistix's tests: `_fit_optimistix`).
    - `verbose`: progress of every step on stderr. `robust`: rescale K_d first (see
      `robust_start`).
    - `engine`: `"lm"` (default): Levenberg-Marquardt on the host around the study's one
      compiled residual-and-Jacobian evaluation; `"optimistix"`: `optx.LevenbergMarquardt`
      in one jit, its residual function taking (r, J) from that same evaluation (see
      `_fit_optimistix`). Both reach the same minimum (tested) with the same robust
      start, priors and standard errors (from the Jacobian at the solution). `"lm"` stays
      the default because it was measured faster cold (optimistix compiles its own solver
      loop, ~1 s) and as fast cached (README, "Calibration output").

    Two passes when fitted clearances have a finite prior: the first weights the prior with
    a 1 µm noise guess, the second with the noise level estimated from the first pass's
    residuals. Both reuse the one compiled evaluation.
    """
    if engine not in ("optimistix", "lm"):
        raise ValueError(f"engine must be 'optimistix' or 'lm', got {engine!r}")
    p = len(problem.fits)
    n = problem.n_data
    u = np.zeros(p) if u0 is None else np.asarray(u0, np.float64)
    noise = 1.0
    if robust and p:
        u, ev = robust_start(problem, u, noise, verbose=verbose)
    else:
        ev = evaluate(problem, u, noise)
    converged, evals, message = True, 0, "nothing to fit"
    passes = 2 if problem.has_prior else 1
    for stage in range(passes if p else 0):
        _log(verbose, f"  fit pass {stage + 1}/{passes} ({p} parameters, {n} data rows"
                      + (f", prior weighted with noise {noise:.3g} µm)" if passes == 2 else ")"))
        if engine == "optimistix":
            out = _fit_optimistix(problem, u, noise, ev0=ev, max_evaluations=max_steps,
                                  verbose=verbose)
        else:
            out = levenberg_marquardt(problem, u, noise, ev0=ev, max_evaluations=max_steps,
                                      xtol=rtol, verbose=verbose)
        u, ev = out.u, out.evaluation
        converged, evals, message = out.converged, evals + out.evaluations, out.message
        r = ev.residuals[:n]
        new_noise = max(float(np.sqrt(np.sum(r ** 2) / max(n - p, 1))), 1e-6)
        if stage + 1 < passes:
            # The prior rows scale with the noise: re-evaluate them at the new weight.
            noise = new_noise
            ev = evaluate(problem, u, noise)
    return summarize(problem, u, noise, converged, evals, message=message, evaluation=ev)


def _covariance(JtJ):
    """Gauss-Newton covariance (JᵀJ)⁻¹ of u and a mask of parameters the data leave
    undetermined (with a component along a null direction of JᵀJ). A pseudo-inverse alone
    would give those a zero variance, i.e. claim that they are known exactly."""
    p = JtJ.shape[0]
    if not np.all(np.isfinite(JtJ)):
        return np.full((p, p), np.nan), np.ones(p, bool)
    w, V = np.linalg.eigh(JtJ)
    null = w <= 1e-10 * max(float(np.max(w)), 1e-300)
    unidentified = np.sum(V[:, null] ** 2, axis=1) > 1e-6
    inv = np.where(null, 0.0, 1.0 / np.where(null, 1.0, w))
    return (V * inv) @ V.T, unidentified


def summarize(problem: Problem, u, noise_guess, converged=True, steps=0, *, message=None,
              evaluation: Evaluation | None = None) -> FitResult:
    """FitResult at u: RMSE, noise estimate, Gauss-Newton standard errors, flags.

    `noise_guess` is the noise level the prior rows were weighted with.
    """
    u = np.asarray(u, np.float64)
    ev = evaluate(problem, u, noise_guess) if evaluation is None else evaluation
    n = problem.n_data
    p = len(problem.fits)
    pred = np.asarray(ev.predicted)
    meas = np.asarray(problem.data.depth_um)
    r = pred - meas
    dof = max(n - p, 1)
    noise = float(np.sqrt(np.sum(r ** 2) / dof))
    flags = []
    J = np.asarray(ev.jacobian)
    if p:
        Jn = J / max(noise, 1e-12)  # residuals in units of the noise
        Jn[n:] = J[n:] / max(noise_guess, 1e-12)  # prior rows: in units of τ already
        JtJ = Jn.T @ Jn
        cov_u, unidentified = _covariance(JtJ)
        vals = np.asarray(problem.values(u))
        deriv = np.array([vals[i] if f.log else f.scale for i, f in enumerate(problem.fits)])
        se = np.sqrt(np.clip(np.diag(cov_u), 0, None)) * np.abs(deriv)
        se[unidentified] = np.inf
        d = np.sqrt(np.clip(np.diag(cov_u), 1e-300, None))
        corr = cov_u / np.outer(d, d)
        corr[unidentified, :] = np.nan
        corr[:, unidentified] = np.nan
        if np.any(unidentified):
            names = [n for n, bad in zip(problem.names, unidentified) if bad]
            flags.append(f"the data do not determine {', '.join(names)} (Jacobian rank "
                         f"deficient: no standard error)")
        for i, name in enumerate(problem.names):
            f = problem.fits[i]
            if f.log:
                rel = se[i] / max(abs(vals[i]), 1e-300)
                if rel > 1.0:
                    flags.append(f"{name}: standard error {rel:.0%} of the value "
                                 f"(not identifiable from these data)")
            elif se[i] > 10 * f.scale:
                flags.append(f"{name}: standard error {se[i]:.3g} is > 10x its typical size "
                             f"{f.scale:g} (not identifiable from these data)")
            for j in range(i + 1, p):
                if abs(corr[i, j]) > 0.99:
                    flags.append(f"{name} and {problem.names[j]}: correlation "
                                 f"{corr[i, j]:+.3f} (|r| > 0.99, not separately identifiable)")
    else:
        vals, se, corr = np.zeros(0), np.zeros(0), np.zeros((0, 0))
    exp_idx = np.asarray(problem.data.exp)
    per = {}
    for i, name in enumerate(problem.exp_names):
        m = exp_idx == i
        if m.any():
            per[name] = float(np.sqrt(np.mean(r[m] ** 2)))
    msg = message or ("converged" if converged else "did not converge within the step limit")
    if float(ev.worn) >= 0:
        msg += "; the layer wears through at the fitted values"
        converged = False
    if not float(ev.max_residual) < 1e-9:
        msg += f"; contact residual {float(ev.max_residual):.1e} ≥ 1e-9 (try more nodes)"
        converged = False
    return FitResult(names=list(problem.names), values=np.asarray(vals), stderr=np.asarray(se),
                     correlation=np.asarray(corr), u=np.asarray(u),
                     rmse_um=float(np.sqrt(np.mean(r ** 2))), rmse_per_experiment=per,
                     noise_um=noise, residuals_um=r, predicted_um=pred, measured_um=meas,
                     row_experiment=exp_idx, converged=converged, iterations=int(steps),
                     message=msg, flags=flags, jacobian=J, problem=problem,
                     snapshots_um=np.asarray(ev.snapshots),
                     max_contact_residual=float(ev.max_residual),
                     integration=_integration(problem, ev))


def calibrate(study: Study, fit_spec="K_d,clearance", *, start=None, verbose=False,
              max_steps: int = 60, engine: str = "lm") -> FitResult:
    """Fit a study's parameters to its data (DESIGN §7 `calibrate`).

    **Arguments:**
    - `study`: a loaded study with profile and/or history data.
    - `fit_spec`: "K_d,clearance" (default) or any comma-separated study keys; strengths of
      the effects the study switches on are always added.
    - `start`: optional start values by output name (user units), e.g.
      `{"K_d_per_Pa": 1e-12, "clearance_mm/n276": 0.06}`.
    - `engine`: `"lm"` (default) or `"optimistix"` (see `fit`).

    **Returns:** a `FitResult` (`.to_json()` gives the DESIGN §7 document).
    """
    keys = with_registration(study, parse_fit(study, fit_spec))
    problem = build_problem(study, keys, start)
    result = fit(problem, max_steps=max_steps, verbose=verbose, engine=engine)
    return recheck_integration(study, result, max_steps=max_steps, verbose=verbose,
                               engine=engine)


def _integration(problem: Problem, ev: Evaluation) -> dict:
    sched = problem.schedule
    adaptive = sched.adaptive
    tol = float(np.max(np.asarray(sched.tolerance))) * 1e6 if adaptive else None
    err = None if ev.error_estimate is None else float(ev.error_estimate)
    return {"integrator": "adaptive" if adaptive else "paper",
            "error_estimate_um": err if err is None or math.isfinite(err) else "inf",
            "steps": None if ev.steps is None else int(ev.steps), "tolerance_um": tol}


def recheck_integration(study: Study, result: FitResult, *, refits: int = 2, **fit_kw
                        ) -> FitResult:
    """Re-check the integration error at the **fitted** parameters (the schedule, its
    attempt count and the error all depend on K_d): adaptive fits whose error estimate
    exceeds the tolerance are refitted from the fitted values with the tolerance divided
    by 4 and schedules built at the fitted values, up to `refits` times; the paper
    integrator gets the M-stability warning at the fitted values. What remains above
    tolerance is said in the message and flags."""
    problem = result.problem
    names = list(problem.exp_names)

    def per_exp(u):
        pb = problem.batched_params(jnp.asarray(u))
        return [jax.tree.map(lambda x: x[i], pb) for i in range(len(names))]

    if study.integrator == "paper":
        from ._simulate_study import amplification_warnings

        for line in amplification_warnings(study, per_exp(result.u)):
            result.flags.append(line.removeprefix("warning: "))
        return result
    tol = study.wear_tolerance_um
    for k in range(refits + 1):
        # schedules (and attempt counts) at the fitted values
        fitted = dataclasses.replace(problem, schedule=_schedules(
            dataclasses.replace(study, wear_tolerance_um=tol), per_exp(result.u)))
        ev = evaluate(fitted, result.u)
        err = float(ev.error_estimate)
        if err <= study.wear_tolerance_um or k == refits:
            break
        tol /= 4
        _log(fit_kw.get("verbose"), f"  integration error {err:.3g} µm above tolerance at "
                                    f"the fitted values: refit at {tol:.3g} µm")
        result = fit(dataclasses.replace(problem, schedule=_schedules(
            dataclasses.replace(study, wear_tolerance_um=tol), per_exp(result.u))),
            result.u, **fit_kw)
        problem = result.problem
    result.integration = _integration(fitted, ev)
    if err <= study.wear_tolerance_um:
        return result
    note = (f"integration error estimate {err:.3g} µm at the fitted values exceeds the "
            f"tolerance {study.wear_tolerance_um:g} µm (after {refits} refits); lower "
            f"[numerics] wear_tolerance_um")
    result.flags.append(note)
    result.message += "; " + note
    return result
