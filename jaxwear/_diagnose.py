"""Diagnosis: find the physics the base model is missing (DESIGN §5, §7 `diagnose`).

The steps, each a function below:

1. **Base fit.** The study's own model and fitted parameters (`parse_fit`, `build_problem`
   of the calibration: K_d, the clearances with their tolerance prior, the strengths of
   effects the study switches on), fitted by Levenberg-Marquardt (`fit_masked`).
2. **Where it fails.** Residuals per experiment, over angle, over revolutions (or hours)
   and across speed and clearance (`where_it_fails`). The noise level comes from the data:
   each residual against the straight line through its two neighbours (angle order within
   one profile, time order within a history), normalised (`line_residuals`); the smooth
   profile and any smooth misfit cancel, white noise does not. Stated tests say whether the
   misfit is noise (`Tests`): a chi-square test of RSS/(n-k) against that noise level
   (F distribution: the noise level has ν degrees of freedom), a lag-1 autocorrelation
   (Durbin-Watson) test of the angle-ordered residuals, and the candidates' score tests,
   Bonferroni-combined at α = 1e-3.
3. **Rank the candidates.** A score (Lagrange-multiplier) test per candidate (`screen`)
   from the Jacobian column of its strength at the base fit: every candidate is switched
   on at its `off` value, where the model is the base model exactly (nesting), so one
   forward-mode Jacobian of the extended model gives every candidate's column at once.
   The leading candidates are refitted and compared by the `evidence`, the BIC log Bayes
   factor against the base model with the noise level unknown (`evidence_from`).
4. **Refit with the winner**: RMSE per experiment before and after, and left-out-experiment
   prediction error before and after (`loo`: one Gauss-Newton step from the full fit).
   A candidate is named when its evidence is very strong (> ln 150) and its residuals pass
   the tests of step 2; when the best explains over half the misfit but leaves a
   systematic remainder, pairs with it are tried; otherwise the verdict is `unexplained`
   and names nothing. Candidates within ln 20 of the winner that also fit to noise are
   reported as alternatives the data cannot tell apart.
5. **Verdict** (`adequate` / `effect_found` / `unexplained`) in the DESIGN §7 JSON
   (`Diagnosis.to_json`), and a self-contained HTML report (`_html.py`).

Why one extended model: compiling the wear loop costs far more than evaluating it, so the
base model, every candidate and every pair of candidates are evaluated by the same
compiled function (all candidates switched on, the unused ones held at `off`). Only the
structural candidate that changes the contact model (`unsymmetric`) needs a second one.
The compiled function depends on the shapes of the model (experiments, snapshots, nodes,
updates), not on the measured rows, so studies with the same design share it (`synth`
uses it to make data; the tests reuse it across seeds).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._config import ModelConfig
from ._errors import InputError
from ._params import Params, key_to_si
from ._schedule import Schedule
from ._study import Study
from ._wear import wear_loop
from .effects import (
    STRUCTURAL_CANDIDATES,
    effect_parameter_specs,
    get_effect,
    registered_effects,
)

# --------------------------------------------------------------------------------------
# The extended model: base parameters and every candidate strength in one vector
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Column:
    """One entry of the extended parameter vector u.

    `key`: study key (or structural strength key); `experiment`: index for a per-experiment
    parameter (clearances), else None; `log`: u is ln(value/start), else
    u = (value - start)/scale; `group`: "" for the base model's parameters, else the name of
    the candidate it belongs to; `lower`, `upper`: bounds in the key's unit.
    """

    key: str
    experiment: int | None
    log: bool
    scale: float
    to_si: float
    group: str
    lower: float
    upper: float
    strength: bool = False  # a nested strength (score-tested at its off value)


class Extended(eqx.Module):
    """The study's model with every candidate switched on; u ↦ snapshots [µm].

    Candidate strengths at their `off` values (u = 0 for them) give the base model.
    """

    cfg: ModelConfig = eqx.field(static=True)
    columns: tuple = eqx.field(static=True)
    params: Params  # batched over experiments
    schedule: Schedule  # batched
    start: jax.Array  # (P,) start values, key units

    def values(self, u):
        out = []
        for i, c in enumerate(self.columns):
            out.append(self.start[i] * jnp.exp(u[i]) if c.log else self.start[i] + c.scale * u[i])
        return jnp.stack(out)

    def batched_params(self, u) -> Params:
        vals = self.values(u)
        p = self.params
        n_exp = self.schedule.cycles.shape[0]
        updates: dict = {}
        structural: dict = {}
        for i, c in enumerate(self.columns):
            si = vals[i] * c.to_si
            if c.group in STRUCTURAL_CANDIDATES:
                structural.setdefault(c.group, {})[c.key] = jnp.broadcast_to(si, (n_exp,))
            elif c.experiment is None:
                updates[c.key] = jnp.broadcast_to(si, (n_exp,))
            else:
                cur = updates.get(c.key, p.get(c.key))
                updates[c.key] = jnp.asarray(cur).at[c.experiment].set(si)
        p = p.with_values(updates)
        for name, vals_si in structural.items():
            p = STRUCTURAL_CANDIDATES[name].set_strength(p, vals_si)
        return p

    def snapshots(self, u):
        res = jax.lax.map(lambda ps: wear_loop(ps[0], self.cfg, ps[1]),
                          (self.batched_params(u), self.schedule))
        return res.snapshots * 1e6, res


@eqx.filter_jit
def _evaluate_ext(ext: Extended, u):
    def g(v):
        snaps, res = ext.snapshots(v)
        return snaps, (snaps, jnp.max(res.max_residual), jnp.max(res.worn_through_cycle),
                       res.sliding_distance)

    J, (snaps, mres, worn, sliding) = jax.jacfwd(g, has_aux=True)(u)
    return snaps, J, mres, worn, sliding


@dataclass
class Eval:
    """Extended model at u: rows and prior rows in µm, their Jacobian w.r.t. u."""

    u: np.ndarray
    pred: np.ndarray  # (rows,)
    r: np.ndarray  # data residuals, model - measured (rows,)
    J: np.ndarray  # (rows, P)
    r_prior: np.ndarray  # (n_prior,)
    J_prior: np.ndarray  # (n_prior, P)
    snaps: np.ndarray  # (E, S, N)
    max_residual: float
    worn: float
    sliding_m: np.ndarray  # (E,) total sliding distance of each experiment [m]

    @property
    def usable(self) -> bool:
        return bool(np.all(np.isfinite(self.r)) and np.all(np.isfinite(self.J))
                    and self.worn < 0)


def candidate_names(cfg: ModelConfig) -> list[str]:
    """Candidates a study can be missing: registered effects it does not switch on, then
    the structural choices it does not make."""
    names = [n for n in registered_effects() if n not in cfg.effects]
    names += [n for n, c in STRUCTURAL_CANDIDATES.items() if c.applies(cfg)]
    return names


def _candidate_parameters(name):
    if name in STRUCTURAL_CANDIDATES:
        return STRUCTURAL_CANDIDATES[name].parameters
    return get_effect(name).parameters


class Model:
    """A study's data with the extended model: evaluation, fits and statistics on the host.

    Built from the calibration's `Problem` (data rows, clearance prior, start values,
    schedules), so its base model is the model `calibrate` fits, to the same data. One
    difference: the prior rows are weighted with the noise level estimated from the data
    (`calibrate` uses its first pass's RMSE).
    """

    evaluations = 0  # process-wide count of compiled-model evaluations (for progress)

    def __init__(self, study: Study, problem=None, *, candidates=None, contact=None):
        from ._calibrate import build_problem, parse_fit

        self.study = study
        if problem is None:
            problem = build_problem(study, parse_fit(study, "K_d,clearance"))
        self.problem = problem
        cfg = study.config
        self.candidates = candidate_names(cfg) if candidates is None else list(candidates)
        parametric = [c for c in self.candidates if c not in STRUCTURAL_CANDIDATES]
        cfg_ext = cfg.replace(effects=tuple(cfg.effects) + tuple(parametric))
        if "double_layer" in self.candidates:
            cfg_ext = STRUCTURAL_CANDIDATES["double_layer"].configure(cfg_ext)
        if contact is not None:
            cfg_ext = cfg_ext.replace(contact=contact)
        self.base_cfg = cfg
        columns, names, start = [], [], []
        specs = effect_parameter_specs()
        for f, s in zip(problem.fits, np.asarray(problem.start)):
            if f.key in specs:  # a strength of an effect the study switches on
                lower, upper = specs[f.key].lower, specs[f.key].upper
            else:
                lower, upper = (0.0, math.inf) if f.log else (-math.inf, math.inf)
            columns.append(Column(f.key, f.experiment, f.log, f.scale, key_to_si(f.key), "",
                                  lower, upper))
            names.append(f.name)
            start.append(float(s))
        p0 = problem.params
        for cand in self.candidates:
            if cand == "unsymmetric":
                continue
            for key, spec in _candidate_parameters(cand).items():
                columns.append(Column(key, None, spec.log, spec.scale, spec.to_si, cand,
                                      spec.lower, spec.upper, strength=not spec.log))
                names.append(key)
                if spec.log:
                    v = float(np.asarray(p0.effect_params[key])[0]) / spec.to_si
                    start.append(v if v > 0 else spec.default)
                else:
                    start.append(spec.off)
        self.columns = tuple(columns)
        self.names = names
        self.index = {n: i for i, n in enumerate(names)}
        # Candidate strengths at `off` in the batched parameters as well (a study may set
        # a value for an effect it does not switch on); the structural strength maps to the
        # backing thickness, which is zero in the single-layer base model.
        u0 = np.zeros(len(columns))
        self.ext = Extended(cfg=cfg_ext, columns=self.columns, params=p0,
                            schedule=problem.schedule, start=jnp.asarray(start, jnp.float64))
        self.ext = eqx.tree_at(lambda e: e.params, self.ext, self.ext.batched_params(u0))
        d = problem.data
        self.row_exp = np.asarray(d.exp)
        self.row_snap = np.asarray(d.snap)
        self._i0 = np.asarray(d.i0)
        self._i1 = np.asarray(d.i1)
        self._w = np.asarray(d.w)
        self._is_max = np.asarray(d.is_max)
        self.measured = np.asarray(d.depth_um)
        self.n = len(self.measured)
        self.exp_names = list(problem.exp_names)
        self.tolerance_um = float(study.clearance_tolerance_um)
        self.nominal_mm = np.asarray(problem.nominal_clearance_mm)
        self.prior_cols = [i for i, c in enumerate(columns)
                           if c.key == "clearance_mm" and c.group == ""]
        if not math.isfinite(self.tolerance_um):
            self.prior_cols = []
        self.base_mask = np.array([c.group == "" for c in columns])
        self.noise_weight = 1.0  # µm: prior rows are (c - c_nom)/τ times this
        self._rows_x, self._rows_t = _row_coordinates(study, d, self.row_exp,
                                                       self.row_snap)

    def group_mask(self, groups) -> np.ndarray:
        """Free columns: the base parameters and those of the named candidates."""
        groups = set(groups)
        return np.array([c.group == "" or c.group in groups for c in self.columns])

    def with_contact(self, contact: str) -> Model:
        """The same model with another contact choice (one more compiled function)."""
        other = object.__new__(Model)
        other.__dict__.update(self.__dict__)
        other.ext = Extended(cfg=self.ext.cfg.replace(contact=contact), columns=self.columns,
                             params=self.ext.params, schedule=self.ext.schedule,
                             start=self.ext.start)
        return other

    def values(self, u) -> np.ndarray:
        return np.asarray(self.ext.values(jnp.asarray(u, jnp.float64)))

    def u_of(self, name: str, value: float) -> float:
        i = self.index[name]
        c, s = self.columns[i], float(self.ext.start[i])
        return math.log(value / s) if c.log else (value - s) / c.scale

    def bounds_u(self):
        lo, hi = [], []
        for c, s in zip(self.columns, np.asarray(self.ext.start)):
            if c.log:
                lo.append(math.log(c.lower / s) if c.lower > 0 else -math.inf)
                hi.append(math.log(c.upper / s) if math.isfinite(c.upper) else math.inf)
            else:
                lo.append((c.lower - s) / c.scale)
                hi.append((c.upper - s) / c.scale)
        return np.array(lo), np.array(hi)

    def evaluate(self, u) -> Eval:
        """The model at u: rows, prior rows, Jacobian (one compiled call)."""
        Model.evaluations += 1
        u = np.asarray(u, np.float64)
        snaps, J, mres, worn, sliding = _evaluate_ext(self.ext, jnp.asarray(u))
        snaps, J = np.asarray(snaps), np.asarray(J)
        prof = snaps[self.row_exp, self.row_snap]  # (rows, N)
        Jp = J[self.row_exp, self.row_snap]  # (rows, N, P)
        rows = np.arange(self.n)
        w = self._w
        pred = prof[rows, self._i0] * (1 - w) + prof[rows, self._i1] * w
        Jr = Jp[rows, self._i0] * (1 - w)[:, None] + Jp[rows, self._i1] * w[:, None]
        if self._is_max.any():
            # maximum depth: the derivative is the one of the deepest node (a subgradient)
            jmax = np.argmax(prof, axis=1)
            m = self._is_max
            pred = np.where(m, prof[rows, jmax], pred)
            Jr[m] = Jp[rows[m], jmax[m]]
        vals = self.values(u)
        r_prior, J_prior = [], []
        for i in self.prior_cols:
            c = self.columns[i]
            k = self.noise_weight * 1e3 / self.tolerance_um
            r_prior.append(k * (vals[i] - self.nominal_mm[c.experiment]))
            row = np.zeros(len(u))
            row[i] = k * (vals[i] if c.log else c.scale)
            J_prior.append(row)
        P = len(u)
        return Eval(u=u, pred=pred, r=pred - self.measured, J=Jr,
                    r_prior=np.array(r_prior).reshape(-1),
                    J_prior=np.array(J_prior).reshape(-1, P), snaps=snaps,
                    max_residual=float(mres), worn=float(worn),
                    sliding_m=np.asarray(sliding))

    # Row coordinates for the residual analysis
    @property
    def row_x(self) -> np.ndarray:
        """Angle [deg] of profile rows, hours of history rows."""
        return self._rows_x

    @property
    def row_time(self) -> np.ndarray:
        """Revolutions (profiles) or hours (history) at which each row was measured."""
        return self._rows_t


def _row_coordinates(study: Study, data, row_exp, row_snap):
    """Angle [deg] (profiles) or hours (histories) of each row, and its measurement time
    (revolutions or hours: the snapshot the row is compared with)."""
    points = [e.snapshot_points for e in study.experiments]
    t = np.array([points[e][s] for e, s in zip(row_exp, row_snap)], float)
    x = getattr(data, "x", None)
    if x is not None:
        return np.asarray(x, float), t
    x = []  # the calibration's row order: each experiment's profile rows, then its history
    for e in study.experiments:
        if e.profile is not None:
            x += list(np.degrees(e.profile.angle))
        if e.history is not None:
            x += list(e.history.hours)
    return np.asarray(x, float), t


# --------------------------------------------------------------------------------------
# Fitting a subset of the extended parameters (host-side Levenberg-Marquardt)
# --------------------------------------------------------------------------------------


@dataclass
class Fit:
    """A fit of the extended model with the columns in `mask` free (the rest fixed)."""

    label: str  # "base", a candidate name, or "a+b"
    groups: tuple  # candidates switched on
    mask: np.ndarray
    ev: Eval
    converged: bool
    evaluations: int
    message: str
    cov_u: np.ndarray | None = None  # (free, free), noise-scaled
    values: np.ndarray | None = None
    stderr: np.ndarray | None = None
    contact: str | None = None
    unstable: bool = False  # the wear loop's derivatives were unstable at the fit

    @property
    def rss(self) -> float:
        return float(self.ev.r @ self.ev.r)

    @property
    def k(self) -> int:
        return int(self.mask.sum())

    @property
    def rmse(self) -> float:
        return float(np.sqrt(np.mean(self.ev.r ** 2)))


def _objective(ev: Eval) -> float:
    return float(ev.r @ ev.r + ev.r_prior @ ev.r_prior)


def _system(ev: Eval, mask):
    J = np.vstack([ev.J[:, mask], ev.J_prior[:, mask]])
    r = np.concatenate([ev.r, ev.r_prior])
    return J, r


def _log(verbose, msg):
    if verbose:
        print(msg, file=sys.stderr, flush=True)


def fit_masked(model: Model, mask, u0, *, label="base", groups=(), ev0: Eval | None = None,
               max_evaluations: int = 40, verbose=False) -> Fit:
    """Levenberg-Marquardt (Marquardt scaling, Nielsen damping) over the free columns,
    with bounds enforced by projection. Every trial is one evaluation of the compiled
    extended model. Stops when an accepted step changes the objective by < 1e-6 relative
    or u by < 1e-8, or when no step reduces it."""
    mask = np.asarray(mask, bool)
    lo, hi = model.bounds_u()
    u = np.clip(np.array(u0, np.float64), lo, hi)
    ev = model.evaluate(u) if ev0 is None else ev0
    evals = 1 if ev0 is None else 0
    if not ev.usable:
        # worn through at the start: K_d down until the model is usable
        kd = model.index.get("K_d_per_Pa")
        for _ in range(8):
            if kd is None or ev.usable:
                break
            u[kd] -= math.log(10.0)
            ev, evals = model.evaluate(u), evals + 1
        if not ev.usable:
            return Fit(label, tuple(groups), mask, ev, False, evals,
                       "the model is not usable at the start (worn through or not finite)")
    F = _objective(ev)
    lam, nu = 1e-3, 2.0
    t0 = time.perf_counter()
    message, converged = f"did not converge within {max_evaluations} evaluations", False
    while evals < max_evaluations:
        J, r = _system(ev, mask)
        A, g = J.T @ J, J.T @ r
        col = np.sqrt(np.maximum(np.diag(A), 1e-300))
        free_u = u[mask]
        # gradient test on the components not pinned at a bound by the gradient's sign
        at_lo = (free_u <= lo[mask] + 1e-12) & (g > 0)
        at_hi = (free_u >= hi[mask] - 1e-12) & (g < 0)
        gt = np.where(at_lo | at_hi, 0.0, g)
        if np.max(np.abs(gt) / col, initial=0.0) <= 1e-9 * math.sqrt(F + 1e-300):
            message, converged = "converged (gradient)", True
            break
        if lam > 1e16:
            message, converged = "converged (no step reduces the misfit)", True
            break
        D = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
        step = np.linalg.lstsq(A + lam * np.diag(D), -g, rcond=None)[0]
        trial = u.copy()
        trial[mask] = np.clip(u[mask] + step, lo[mask], hi[mask])
        step = trial[mask] - u[mask]
        ev_t = model.evaluate(trial)
        evals += 1
        F_t = _objective(ev_t) if ev_t.usable else math.inf
        pred = -(2 * float(step @ g) + float(step @ A @ step))
        rho = (F - F_t) / pred if pred > 0 else -1.0
        if F_t < F and rho > 0:
            rel = (F - F_t) / max(F, 1e-300)
            u, ev, F = trial, ev_t, F_t
            lam *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
            nu = 2.0
            _log(verbose, f"    {label}: rms {math.sqrt(np.mean(ev.r ** 2)):.4f} µm "
                          f"({evals} evaluations, {time.perf_counter() - t0:.1f} s)")
            # 1e-6 of the objective is ~1e-3 of one noise variance here: far below what
            # the evidence or the standard errors resolve
            if rel <= 1e-6 or np.max(np.abs(step)) <= 1e-8 * (1 + np.max(np.abs(u))):
                message, converged = "converged", True
                break
        else:
            lam *= nu
            nu *= 2.0
    return Fit(label, tuple(groups), mask, ev, converged, evals, message)


def finish(model: Model, fit: Fit, noise_um: float) -> Fit:
    """Standard errors of the free parameters (Gauss-Newton, residuals in units of
    max(noise, rms misfit), so an inadequate model does not get falsely small errors)."""
    J, r = _system(fit.ev, fit.mask)
    n, k = model.n, fit.k
    s2 = max(noise_um ** 2, float(fit.ev.r @ fit.ev.r) / max(n - k, 1))
    Jn = J.copy()
    Jn[:n] /= math.sqrt(s2)
    Jn[n:] /= max(model.noise_weight, 1e-12)  # prior rows are (c - c_nom)/τ · weight
    cov = np.linalg.pinv(Jn.T @ Jn, rcond=1e-13, hermitian=True)
    vals = model.values(fit.ev.u)
    idx = np.flatnonzero(fit.mask)
    deriv = np.array([vals[i] if model.columns[i].log else model.columns[i].scale
                      for i in idx])
    se = np.full(len(vals), np.nan)
    se[idx] = np.sqrt(np.clip(np.diag(cov), 0, None)) * np.abs(deriv)
    fit.cov_u, fit.values, fit.stderr = cov, vals, se
    return fit


# --------------------------------------------------------------------------------------
# Noise level from the data alone, and the tests of "systematic or noise"
# --------------------------------------------------------------------------------------


def measurement_series(model: Model) -> list:
    """The data as ordered series: (row indices, coordinate, largest neighbour spacing).

    A profile (one experiment at one revolution count) is ordered by angle, and points
    further apart than 2.5 times its median spacing are not neighbours (the ends of a
    scar, unmeasured arcs); a depth history (one experiment) is ordered by time.
    """
    out = []
    for e in range(len(model.exp_names)):
        hist = np.flatnonzero((model.row_exp == e) & model._is_max)
        if len(hist):
            order = np.argsort(model.row_time[hist])
            out.append((hist[order], model.row_time[hist][order], math.inf))
        prof = (model.row_exp == e) & ~model._is_max
        for t in sorted(set(model.row_time[prof].tolist())):
            rows = np.flatnonzero(prof & (model.row_time == t))
            order = np.argsort(model.row_x[rows])
            x = model.row_x[rows][order]
            gap = 2.5 * float(np.median(np.diff(x))) if len(x) > 1 else math.inf
            out.append((rows[order], x, gap))
    return out


def line_residuals(x, y, gap=math.inf):
    """Each interior point of one series minus the straight line through its two
    neighbours, normalised: for white noise of level σ, e_i = y_i - (w y_{i-1} +
    (1-w) y_{i+1}) has variance σ² (1 + w² + (1-w)²), and a smooth curve (a wear profile,
    or a smooth misfit) nearly cancels. Triples with a spacing > `gap` are skipped.

    Returns (e_i / sqrt(1 + w² + (1-w)²), index of the middle point).
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 3:
        return np.zeros(0), np.zeros(0, int)
    a, b = np.diff(x)[:-1], np.diff(x)[1:]
    ok = (a > 0) & (b > 0) & (a <= gap) & (b <= gap)
    w = np.where(ok, b / np.where(ok, a + b, 1.0), 0.5)
    e = y[1:-1] - (w * y[:-2] + (1 - w) * y[2:])
    e = e / np.sqrt(1 + w * w + (1 - w) ** 2)
    mid = np.arange(1, len(x) - 1)
    return e[ok], mid[ok]


def neighbour_differences(model: Model, values=None):
    """`line_residuals` of every measurement series of `values` (default: the data).
    Returns (normalised differences, row index of each middle point)."""
    y = model.measured if values is None else np.asarray(values)
    es, mids = [np.zeros(0)], [np.zeros(0, int)]
    for rows, x, gap in measurement_series(model):
        e, mid = line_residuals(x, y[rows], gap)
        es.append(e)
        mids.append(rows[mid])
    return np.concatenate(es), np.concatenate(mids)


# For equally spaced white noise the normalised second differences have lag-1 and lag-2
# correlations -2/3 and 1/6, so the mean of their squares has the variance of
# n / (1 + 2 (4/9 + 1/36)) = n / 1.944 independent squares.
_D2_DOF_FACTOR = 1.0 + 2.0 * (4.0 / 9.0 + 1.0 / 36.0)


def noise_level(e) -> tuple[float, float]:
    """Noise level σ = rms of normalised neighbour differences, and its degrees of freedom
    (for an equally spaced series, see `_D2_DOF_FACTOR`)."""
    e = np.asarray(e, float)
    if len(e) == 0:
        return math.nan, 0.0
    return float(np.sqrt(np.mean(e ** 2))), len(e) / _D2_DOF_FACTOR


def _betacf(a, b, x):
    """Continued fraction of the regularised incomplete beta function (Lentz)."""
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 400):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c if abs(1.0 + aa / c) > tiny else tiny
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c if abs(1.0 + aa / c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-14:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    """Regularised incomplete beta function I_x(a, b)."""
    if x <= 0:
        return 0.0
    if x >= 1:
        return 1.0
    lbt = (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x)
           + b * math.log1p(-x))
    if x < (a + 1) / (a + b + 2):
        return math.exp(lbt) * _betacf(a, b, x) / a
    return 1.0 - math.exp(lbt) * _betacf(b, a, 1 - x) / b


def f_sf(F: float, d1: float, d2: float) -> float:
    """P(X > F) for X ~ F(d1, d2)."""
    if not F > 0:
        return 1.0
    if not math.isfinite(d2) or d2 > 1e7:  # σ known: chi-square(d1)/d1
        return chi2_sf(F * d1, d1)
    return betainc(d2 / 2, d1 / 2, d2 / (d2 + d1 * F))


def chi2_sf(x: float, k: float) -> float:
    """P(X > x) for X ~ chi-square(k) (regularised upper incomplete gamma)."""
    if not x > 0:
        return 1.0
    a, z = k / 2.0, x / 2.0
    if z < a + 1:  # series for the lower function
        term = s = 1.0 / a
        n = a
        for _ in range(1000):
            n += 1
            term *= z / n
            s += term
            if abs(term) < abs(s) * 1e-15:
                break
        return max(0.0, 1.0 - s * math.exp(-z + a * math.log(z) - math.lgamma(a)))
    # continued fraction for the upper function
    tiny = 1e-300
    b = z + 1 - a
    c, d = 1 / tiny, 1 / b
    h = d
    for i in range(1, 1000):
        an = -i * (i - a)
        b += 2
        d = an * d + b
        d = 1 / (d if abs(d) > tiny else tiny)
        c = b + an / c
        c = c if abs(c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1) < 1e-15:
            break
    return math.exp(-z + a * math.log(z) - math.lgamma(a)) * h


def norm_sf(z: float) -> float:
    return 0.5 * math.erfc(z / math.sqrt(2.0))


ALPHA = 1e-3  # level of every "is it noise?" decision (family-wise, Bonferroni inside)


@dataclass
class Tests:
    """Is the misfit noise? Two omnibus tests on the data residuals, and (optional) the
    score tests of the candidates not in the model.

    - chi-square (F form): (RSS/(n-k)) / σ̂², σ̂ from neighbour differences with ν degrees
      of freedom; p = P(F(n-k, ν) > observed).
    - lag-1 autocorrelation of the angle-ordered residuals (pairs of neighbouring points,
      same gap rule as the noise estimate): ρ̂ = Σ r_i r_{i+1} / Σ r_i², z = ρ̂ √pairs,
      one-sided p (smooth misfit correlates neighbours; white noise does not). This is the
      Durbin-Watson statistic in another form: DW ≈ 2 (1 - ρ̂).
    """

    rmse_um: float
    noise_um: float
    ratio: float  # (RSS/(n-k))/σ̂²
    p_chi2: float
    rho: float
    z_autocorr: float
    p_autocorr: float
    p_score: float = 1.0  # smallest Bonferroni-corrected score-test p of the candidates left
    score_effect: str | None = None

    @property
    def p_min(self) -> float:
        """Bonferroni over the three tests."""
        return min(1.0, 3 * min(self.p_chi2, self.p_autocorr, self.p_score))

    @property
    def systematic(self) -> bool:
        return self.p_min < ALPHA

    def to_json(self) -> dict:
        return {"rmse_um": self.rmse_um, "noise_um": self.noise_um,
                "chi2_ratio": self.ratio, "p_chi2": self.p_chi2,
                "lag1_autocorrelation": self.rho, "durbin_watson": 2 * (1 - self.rho),
                "z_autocorrelation": self.z_autocorr, "p_autocorrelation": self.p_autocorr,
                "p_score_min": self.p_score, "score_effect": self.score_effect,
                "p_combined": self.p_min, "systematic": self.systematic, "alpha": ALPHA}


def neighbour_pairs(model: Model):
    """Index pairs (i, j) of neighbouring rows of one series (`measurement_series`)."""
    pairs = [np.zeros((0, 2), int)]
    for rows, x, gap in measurement_series(model):
        dx = np.diff(x)
        ok = (dx > 0) & (dx <= gap)
        pairs.append(np.stack([rows[:-1][ok], rows[1:][ok]], axis=1))
    return np.concatenate(pairs)


def lag1_autocorrelation(r, pairs) -> tuple[float, float]:
    """ρ̂ = Σ r_i r_j / Σ r² over neighbouring pairs (i, j), and z = ρ̂ √pairs, which is
    standard normal for white residuals (Durbin-Watson: DW ≈ 2(1 - ρ̂))."""
    r = np.asarray(r, float)
    if len(pairs) == 0:
        return 0.0, 0.0
    used = np.unique(pairs)
    rho = float(r[pairs[:, 0]] @ r[pairs[:, 1]]) / max(float(r[used] @ r[used]), 1e-300)
    return rho, rho * math.sqrt(len(pairs))


def run_tests(model: Model, r, k: int, noise_um: float, nu: float, pairs) -> Tests:
    n = len(r)
    rss = float(r @ r)
    ratio = rss / max(n - k, 1) / noise_um ** 2
    p_chi2 = f_sf(ratio, max(n - k, 1), nu)
    rho, z = lag1_autocorrelation(r, pairs)
    return Tests(rmse_um=math.sqrt(rss / n), noise_um=noise_um, ratio=ratio, p_chi2=p_chi2,
                 rho=rho, z_autocorr=z, p_autocorr=norm_sf(z))


# --------------------------------------------------------------------------------------
# Screening the candidates: score (Lagrange-multiplier) tests at a fit
# --------------------------------------------------------------------------------------

SHAPE_GRID = (0.1, 0.3, 1.0, 3.0, 10.0)  # multiples of a shape parameter's default tried


@dataclass
class Screen:
    """Score test of one candidate at a fit (linearised: one Gauss-Newton step).

    `score`: LM statistic r'Z(Z'Z)⁻¹Z'r / σ̂² with Z the candidate's strength column(s)
    projected off the fitted columns (χ²(df) under the model fitted); `delta_rss`: the
    RSS it would remove [µm²]; `explained`: that as a fraction of the systematic misfit
    RSS - (n-k) σ̂²; `start`: the step's strength and the best shape values (key units).
    A step that leaves a strength's bounds is infeasible (score 0).
    """

    effect: str
    score: float
    df: int
    p: float
    delta_rss: float
    explained: float
    start: dict
    feasible: bool


def _project_out(J, Z):
    """Z minus its least-squares projection on the columns of J."""
    if J.shape[1] == 0:
        return Z
    coef = np.linalg.lstsq(J, Z, rcond=None)[0]
    return Z - J @ coef


def screen(model: Model, fit: Fit, noise_um: float, nu: float = math.inf, *,
           verbose=False) -> list[Screen]:
    """Score tests of every parametric candidate not in `fit` (structural `unsymmetric`
    has no strength and is left to a refit).

    An effect with shape parameters (log-fitted, e.g. the running-in distance) is tested
    at each of `SHAPE_GRID` times their value in `fit` (the strength's column depends on
    them; the model does not, at strength off) and keeps the best; its p-value is
    multiplied by the grid size. p-values use F(df, ν): the noise level is estimated with
    ν degrees of freedom.
    """
    groups = [g for g in model.candidates if g not in fit.groups and g != "unsymmetric"]
    J, r = _system(fit.ev, fit.mask)
    n_prior = len(fit.ev.r_prior)
    q_sys = max(fit.rss - (model.n - fit.k) * noise_um ** 2, 1e-300)
    lo, hi = model.bounds_u()
    out = []
    for g in groups:
        idx = [i for i, c in enumerate(model.columns) if c.group == g]
        s_idx = [i for i in idx if model.columns[i].strength]
        h_idx = [i for i in idx if not model.columns[i].strength]
        grid = [1.0] if not h_idx else list(SHAPE_GRID)
        best = None
        for mult in grid:
            u = fit.ev.u.copy()
            u[h_idx] += math.log(mult)
            ev = fit.ev if mult == 1.0 else model.evaluate(u)
            Z = np.vstack([ev.J[:, s_idx], np.zeros((n_prior, len(s_idx)))])
            Zp = _project_out(J, Z)
            ZZ = Zp.T @ Zp
            if not np.all(np.isfinite(ZZ)) or np.max(np.abs(ZZ)) < 1e-300:
                continue
            coef = np.linalg.lstsq(ZZ, -(Zp.T @ r), rcond=None)[0]  # GN step in u
            d_rss = float(-(Zp.T @ r) @ coef)
            step = u[s_idx] + coef
            # one-sided where the strength sits at a bound (a ≥ 0, μ ≥ 0, C ≥ 0, q ≥ 0):
            # a step out of bounds means the effect cannot explain this misfit
            feasible = bool(np.all(step >= lo[s_idx] - 1e-12)
                            and np.all(step <= hi[s_idx] + 1e-12))
            d_rss = d_rss if feasible else 0.0
            score = d_rss / noise_um ** 2
            if best is None or score > best.score:
                # refit start: the step, capped at 3 typical sizes (the linearisation is
                # only a guide far from the base model)
                u_start = u.copy()
                u_start[s_idx] = np.clip(u[s_idx] + np.clip(coef, -3.0, 3.0), lo[s_idx],
                                         hi[s_idx])
                vals = model.values(u_start)
                best = Screen(g, score, len(s_idx), 1.0, d_rss, d_rss / q_sys,
                              {model.names[i]: float(vals[i]) for i in idx}, feasible)
        if best is not None:
            p = f_sf(best.score / best.df, best.df, nu) if best.score > 0 else 1.0
            best.p = min(1.0, p * len(grid))
            out.append(best)
            share = (f", explains {100 * best.explained:.0f}% of the misfit"
                     if fit.rss > 1.5 * (model.n - fit.k) * noise_um ** 2 else "")
            _log(verbose, f"    score {g:18s} {best.score:10.1f} (p {best.p:.1e}{share})")
    out.sort(key=lambda s: -s.score)
    return out


# --------------------------------------------------------------------------------------
# Refits, evidence, leave-one-experiment-out, the verdict
# --------------------------------------------------------------------------------------

EXPLAINED_FOR_SECOND_STAGE = 0.5  # a first effect must remove this much misfit to look on
AMBIGUOUS_LOG_BF = math.log(20.0)  # evidence gap below which two candidates are a tie
STRONG_LOG_BF = math.log(150.0)  # "very strong" evidence (Kass & Raftery 1995)


def evidence_from(n: int, q_base: float, q_fit: float, dk: int) -> float:
    """ln Bayes factor of a fit against the base model, BIC approximation with the noise
    level unknown: ½ [n ln(Q_base/Q_fit) - Δk ln n], Q the weighted least-squares
    objective. It needs no noise estimate, so it also works for a handful of points
    (a depth-vs-time history), where a noise level from the data alone is uncertain."""
    if not (q_fit > 0 and q_base > 0):
        return -math.inf if q_fit > 0 else math.inf
    return 0.5 * (n * math.log(q_base / q_fit) - dk * math.log(n))


def evidence(model: Model, fit: Fit, base: Fit, noise_um: float = 0.0) -> float:
    """ln Bayes factor of `fit` against `base` (see `evidence_from`)."""
    return evidence_from(model.n, _objective(base.ev), _objective(fit.ev), fit.k - base.k)


def loo(model: Model, fit: Fit) -> dict:
    """Leave-one-experiment-out prediction RMSE [µm] per experiment: the fit without the
    experiment's rows (one Gauss-Newton step from the full fit; the experiment's own
    clearance then returns to its prior, the nominal value), predicting those rows."""
    J, r = _system(fit.ev, fit.mask)
    n = model.n
    out = {}
    for ei, name in enumerate(model.exp_names):
        rows = np.flatnonzero(model.row_exp == ei)
        if len(rows) == 0:
            continue
        keep = np.ones(len(r), bool)
        keep[rows] = False
        step = np.linalg.lstsq(J[keep], -r[keep], rcond=None)[0]
        pred = r[rows] + J[rows] @ step
        out[name] = float(np.sqrt(np.mean(pred ** 2)))
    del n
    return out if len(out) > 1 else {}  # one experiment: nothing to leave out


def rmse_per_experiment(model: Model, r) -> dict:
    return {name: float(np.sqrt(np.mean(r[model.row_exp == i] ** 2)))
            for i, name in enumerate(model.exp_names) if np.any(model.row_exp == i)}


@dataclass
class Candidate:
    effect: str
    screen: Screen | None
    fit: Fit | None
    evidence: float
    rmse_um: float
    tests: Tests | None = None

    @property
    def refit(self) -> bool:
        return self.fit is not None


@dataclass
class Diagnosis:
    """Everything `diagnose` found; `to_json()` is the DESIGN §7 document."""

    study: Study
    model: Model
    noise_um: float
    noise_dof: float
    base: Fit
    base_tests: Tests
    screens: list
    candidates: list  # Candidate, best first
    status: str
    effects: list  # names explaining the misfit (effect_found), else []
    partial: list  # names that explain part of it (unexplained)
    alternatives: list  # candidates the data cannot tell apart from the winner
    final: Fit  # the model after (the winner, or the base)
    final_tests: Tests
    loo_before: dict
    loo_after: dict
    summary: str = ""
    wall_s: float = 0.0
    log: list = field(default_factory=list)
    compare_fits: dict = field(default_factory=dict)

    @property
    def missing_effect(self):
        return self.effects[0] if self.effects else None

    def parameters_json(self, fit: Fit) -> dict:
        out = {}
        for i in np.flatnonzero(fit.mask):
            se = fit.stderr[i] if fit.stderr is not None else math.nan
            out[self.model.names[i]] = {"value": float(fit.values[i]),
                                        "stderr": float(se) if math.isfinite(se) else None}
        out.update({k: {"value": v, "stderr": se if math.isfinite(se) else None, "derived": True}
                    for k, (v, se) in derived(self.model, fit).items()})
        return out

    def to_json(self) -> dict:
        m = self.model
        cands = []
        for c in self.candidates:
            d = {"effect": c.effect, "rmse_um": c.rmse_um, "evidence": c.evidence,
                 "refit": c.refit}
            if c.fit is not None:
                d["parameters"] = self.parameters_json(c.fit)
                d["converged"] = c.fit.converged
            else:
                d["parameters"] = {k: {"value": v, "stderr": None}
                                   for k, v in (c.screen.start if c.screen else {}).items()}
            if c.screen is not None:
                d.update(score=c.screen.score, p_score=c.screen.p,
                         explained_fraction=c.screen.explained)
            if c.tests is not None:
                d["at_noise_level"] = not c.tests.systematic
                d["tests"] = c.tests.to_json()
            cands.append(d)
        base = {"rmse_um": self.base.rmse, "noise_um": self.noise_um,
                "parameters": self.parameters_json(self.base),
                "noise_dof": self.noise_dof, "rmse_per_experiment_um":
                    rmse_per_experiment(m, self.base.ev.r),
                "loo_rmse_per_experiment_um": self.loo_before,
                "loo_rmse_um": _mean_sq(self.loo_before), "tests": self.base_tests.to_json(),
                "converged": self.base.converged, "n_data": m.n,
                "where_it_fails": where_it_fails(m, self.base.ev.r)}
        after = {"model": self.final.label, "effects": list(self.final.groups),
                 "rmse_um": self.final.rmse,
                 "rmse_per_experiment_um": rmse_per_experiment(m, self.final.ev.r),
                 "loo_rmse_per_experiment_um": self.loo_after,
                 "loo_rmse_um": _mean_sq(self.loo_after),
                 "parameters": self.parameters_json(self.final),
                 "tests": self.final_tests.to_json()}
        return {
            "baseline": base,
            "candidates": cands,
            "verdict": {"status": self.status, "missing_effect": self.missing_effect,
                        "summary": self.summary, "effects": list(self.effects),
                        "partial": list(self.partial), "alternatives": list(self.alternatives),
                        "confident": self.status != "effect_found" or not self.alternatives},
            "after": after,
            "study": str(self.study.path),
            "wall_time_s": self.wall_s,
            "method": METHOD_NOTE,
        }


METHOD_NOTE = (
    "noise: rms of each residual minus the line through its two neighbours (angle order), "
    "normalised; misfit is systematic when a Bonferroni combination of a chi-square test "
    "(RSS/(n-k) against the noise level), a lag-1 autocorrelation test of angle-ordered "
    f"residuals and the candidates' score tests rejects at alpha = {ALPHA:g}; evidence = "
    "ln Bayes factor against the base model, BIC approximation with the noise level "
    "unknown; an effect is named when its evidence is very strong (> ln 150) and its "
    "residuals pass the same tests; leave-one-experiment-out errors are one Gauss-Newton "
    "step from the full fit.")


def _mean_sq(d: dict) -> float | None:
    return float(np.sqrt(np.mean(np.square(list(d.values()))))) if d else None


def where_it_fails(model: Model, r) -> dict:
    """Residual summaries (model - measured, µm): per experiment (with speed and clearance),
    per measurement time, and per 30° sector of the bushing."""
    st = model.study
    per_exp = []
    for i, e in enumerate(st.experiments):
        m = model.row_exp == i
        if not m.any():
            continue
        p = st.params(e)
        per_exp.append({"experiment": e.name, "speed_rpm": float(p.speed) * 60 / (2 * math.pi),
                        "clearance_mm": float(p.clearance) * 1e3, "rows": int(m.sum()),
                        "mean_um": float(np.mean(r[m])),
                        "rmse_um": float(np.sqrt(np.mean(r[m] ** 2)))})
    per_time = []
    for t in sorted(set(model.row_time.tolist())):
        m = model.row_time == t
        per_time.append({"at": t, "rows": int(m.sum()), "mean_um": float(np.mean(r[m])),
                         "rmse_um": float(np.sqrt(np.mean(r[m] ** 2)))})
    per_angle = []
    if not model._is_max.all():
        prof = ~model._is_max
        for a in range(0, 360, 30):
            m = prof & (model.row_x >= a) & (model.row_x < a + 30)
            if m.any():
                per_angle.append({"from_deg": a, "to_deg": a + 30, "rows": int(m.sum()),
                                  "mean_um": float(np.mean(r[m])),
                                  "rmse_um": float(np.sqrt(np.mean(r[m] ** 2)))})
    unit = "hours" if st.config.driver == "oscillating" else "revolutions"
    return {"per_experiment": per_exp, "per_time": per_time, "time_unit": unit,
            "per_angle": per_angle}


def derived(model: Model, fit: Fit) -> dict:
    """Identifiable combinations of poorly separated parameters, with delta-method errors:
    `running_in_excess_m` = a·S_r, the running-in's extra wear in metres of steady sliding
    (what depth data fix when they end long after S_r)."""
    out = {}
    ia, isr = model.index.get("running_in_amplitude"), model.index.get("running_in_distance_m")
    if (ia is None or isr is None or not fit.mask[ia] or not fit.mask[isr]
            or fit.values is None or fit.cov_u is None):
        return out
    a, sr = float(fit.values[ia]), float(fit.values[isr])
    free = list(np.flatnonzero(fit.mask))
    g = np.zeros(len(free))
    g[free.index(ia)] = model.columns[ia].scale * sr  # a linear in u
    g[free.index(isr)] = a * sr  # S_r log in u
    out["running_in_excess_m"] = (a * sr, float(np.sqrt(max(g @ fit.cov_u @ g, 0.0))))
    return out


def _tests_for(model, fit, noise, nu, pairs, scores=None) -> Tests:
    t = run_tests(model, fit.ev.r, fit.k, noise, nu, pairs)
    if scores:
        best = min(scores, key=lambda s: s.p)
        t.p_score = min(1.0, best.p * len(scores))
        t.score_effect = best.effect
    return t


def _start_for(model: Model, fit: Fit, scr: Screen | None) -> np.ndarray:
    u = fit.ev.u.copy()
    if scr is not None:
        for k, v in scr.start.items():
            u[model.index[k]] = model.u_of(k, v)
    return u


def _refit(by_contact, from_fit: Fit, groups, scr, noise, verbose) -> Fit:
    contact = "unsymmetric" if "unsymmetric" in groups else None
    mdl = by_contact(contact)
    mask = mdl.group_mask([g for g in groups if g != "unsymmetric"])
    label = "+".join(groups)
    _log(verbose, f"  refit with {label}")
    # Start at the screen's (capped) step with K_d rescaled to the data; where that is
    # worse than the fit we come from, start from that fit instead (strength off): a
    # refit can then only improve on it.
    u0 = _start_for(mdl, from_fit, scr)
    ev0 = mdl.evaluate(u0)
    kd = mdl.index.get("K_d_per_Pa")
    if kd is not None and mask[kd] and ev0.usable:
        d = ev0.pred
        a = float(d @ mdl.measured) / max(float(d @ d), 1e-300)
        if a > 0 and math.isfinite(a) and abs(math.log(a)) > 0.02:
            u0[kd] += math.log(a)
            ev0 = mdl.evaluate(u0)
    same = contact == from_fit.contact
    if not ev0.usable or (same and _objective(ev0) > _objective(from_fit.ev)):
        u0 = from_fit.ev.u.copy()
        ev0 = from_fit.ev if same else mdl.evaluate(u0)
    f = fit_masked(mdl, mask, u0, label=label, groups=tuple(groups), ev0=ev0,
                   verbose=verbose)
    f.contact = contact
    if not _derivatives_ok(mdl, f.ev):
        f.unstable, f.converged = True, False
        f.message += ("; the wear loop's derivatives are unstable here (lower "
                      "revolutions_per_update): this fit is not reliable")
        _log(verbose, f"    {label}: unstable derivatives, not used")
    return finish(mdl, f, noise)


def _derivative_ratio(model: Model, ev: Eval) -> float:
    """(d·∂d/∂ln K_d)/(d·d): about 1, since depth is nearly proportional to K_d."""
    k = model.index.get("K_d_per_Pa")
    if k is None or model.columns[k].group != "" or not model.columns[k].log:
        return 1.0
    d, j = ev.pred, ev.J[:, k]
    if not np.all(np.isfinite(j)):
        return math.nan
    return float(d @ j) / max(float(d @ d), 1e-300)


def _derivatives_ok(model: Model, ev: Eval) -> bool:
    return 0.2 < _derivative_ratio(model, ev) < 5.0


def _check_derivatives(model: Model, fit: Fit):
    """A Jacobian far from d depth/d ln K_d ≈ depth means the forward-mode derivative of the
    wear loop is unstable (too many revolutions per update for a fast-wearing joint): the
    fits would be meaningless, so stop and say what to change."""
    ratio = _derivative_ratio(model, fit.ev)
    if not 0.2 < ratio < 5.0:
        raise InputError(
            f"{model.study.path}: numerics.revolutions_per_update = "
            f"{model.study.revolutions_per_update:g} is too large for this joint: the "
            f"derivative of depth with respect to K_d is {ratio:.3g} times the depth "
            f"(expected about 1), so the amplified wear updates are unstable for "
            f"derivatives; halve revolutions_per_update")


def diagnose(study: Study, *, verbose: bool = False, max_refits: int = 3,
             noise_um: float | None = None) -> Diagnosis:
    """Diagnose a study (module docstring). Progress on stderr when `verbose`.

    `noise_um`: a known measurement noise level [µm]; default: estimated from the data.
    """
    t0 = time.perf_counter()
    evals0 = Model.evaluations
    _log(verbose, f"diagnose {study.path}: {len(study.experiments)} experiments")
    model = Model(study)
    if model.n < 3:
        raise InputError(f"{study.path}: diagnose needs at least 3 measured points")
    _log(verbose, f"  {model.n} data rows; candidates: {', '.join(model.candidates) or 'none'}"
                  " (the first evaluation compiles the extended model)")
    models = {None: model}

    def by_contact(contact):
        if contact not in models:
            _log(verbose, f"  compiling the model with {contact} contact")
            models[contact] = model.with_contact(contact)
            models[contact].noise_weight = model.noise_weight
        return models[contact]

    # 1. the base model, as the study states it; the prior weighted with the noise level
    u0 = np.zeros(len(model.names))
    ev0 = model.evaluate(u0)
    kd = model.index.get("K_d_per_Pa")
    if kd is not None and ev0.usable:
        d = ev0.pred
        a = float(d @ model.measured) / max(float(d @ d), 1e-300)
        if a > 0 and math.isfinite(a) and abs(math.log(a)) > 0.02:
            u0[kd] += math.log(a)  # depth is nearly proportional to K_d
            ev0 = None
    _log(verbose, f"  base fit ({int(model.base_mask.sum())} parameters)")
    base = fit_masked(model, model.base_mask, u0, label="base", ev0=ev0, verbose=verbose)
    noise, nu = _noise(model, base, noise_um)
    if model.prior_cols:
        for m_ in models.values():
            m_.noise_weight = noise
        base = fit_masked(model, model.base_mask, base.ev.u, label="base", verbose=verbose)
        noise, nu = _noise(model, base, noise_um)
    base = finish(model, base, noise)
    _check_derivatives(model, base)
    pairs = neighbour_pairs(model)
    _log(verbose, f"  base RMSE {base.rmse:.4f} µm, noise {noise:.4f} µm (ν = {nu:.4g})")

    # 2-3. is it noise? score tests of every candidate at the base fit
    scores = screen(model, base, noise, nu, verbose=verbose)
    base_tests = _tests_for(model, base, noise, nu, pairs, scores)
    _log(verbose, f"  base: chi-square ratio {base_tests.ratio:.3f} (p {base_tests.p_chi2:.1e})"
                  f", lag-1 autocorrelation {base_tests.rho:.3f} "
                  f"(p {base_tests.p_autocorr:.1e}), best score p {base_tests.p_score:.1e}")
    q_base = _objective(base.ev)
    cands = {}
    for s_ in scores:
        q_lin = max(q_base - s_.delta_rss, 1e-12 * q_base)
        cands[s_.effect] = Candidate(
            s_.effect, s_, None, evidence_from(model.n, q_base, q_lin, len(s_.start)),
            math.sqrt(max(base.rss - s_.delta_rss, 0.0) / model.n))
    status, effects, partial, alternatives = "adequate", [], [], []
    final, final_tests = base, base_tests
    promising = [c for c in cands.values() if c.evidence > STRONG_LOG_BF]
    if base_tests.systematic or promising:
        # refit the leading candidates (and the parameter-free structural ones)
        # the leader always; others only where their own score test is significant and
        # not negligible next to the leader's (a refit costs ~10 model evaluations)
        live = [s_ for s_ in scores if s_.feasible and s_.score > 0]
        todo = [(s_.effect, s_) for i, s_ in enumerate(live)
                if i == 0 or (s_.p < ALPHA and s_.score >= 0.1 * live[0].score)][:max_refits]
        if "unsymmetric" in model.candidates:
            todo.append(("unsymmetric", None))
        for name, scr in todo:
            f = _refit(by_contact, base, [name], scr, noise, verbose)
            c = cands.get(name) or Candidate(name, None, None, 0.0, math.nan)
            c.fit, c.rmse_um = f, f.rmse
            c.evidence = evidence(model, f, base)
            cands[name] = c
        refitted = sorted([c for c in cands.values() if c.refit and not c.fit.unstable],
                          key=lambda c: -c.evidence)
        best = refitted[0] if refitted else None
        systematic = base_tests.systematic or (best is not None
                                               and best.evidence > STRONG_LOG_BF)
        if systematic and best is not None and best.evidence > STRONG_LOG_BF:
            mdl = by_contact(best.fit.contact)
            rest = screen(mdl, best.fit, noise, nu)
            best.tests = _tests_for(mdl, best.fit, noise, nu, pairs, rest)
            for c in refitted[1:]:
                c.tests = _tests_for(by_contact(c.fit.contact), c.fit, noise, nu, pairs)
            if not best.tests.systematic:
                status, effects, final, final_tests = "effect_found", [best.effect], \
                    best.fit, best.tests
                alternatives = [c.effect for c in refitted[1:]
                                if not c.tests.systematic
                                and best.evidence - c.evidence < AMBIGUOUS_LOG_BF]
            else:
                explained = (q_base - _objective(best.fit.ev)) / max(
                    q_base - (model.n - base.k) * noise ** 2, 1e-300)
                status, partial, final, final_tests = "unexplained", [best.effect], \
                    best.fit, best.tests
                if explained >= EXPLAINED_FOR_SECOND_STAGE:
                    found = _second_stage(model, by_contact, best, rest, noise, nu, pairs,
                                          max_refits, verbose)
                    if found is not None:
                        pair_fit, pair_tests = found
                        status, effects, partial = "effect_found", list(pair_fit.groups), []
                        final, final_tests = pair_fit, pair_tests
                        cands[pair_fit.label] = Candidate(
                            pair_fit.label, None, pair_fit, evidence(model, pair_fit, base),
                            pair_fit.rmse, pair_tests)
        elif systematic:
            status = "unexplained"
            if best is not None:
                mdl = by_contact(best.fit.contact)
                best.tests = _tests_for(mdl, best.fit, noise, nu, pairs)
    # best first: the verdict's model, then by evidence (refits and linearised screens)
    lead_label = final.label if final is not base else None
    ordered = sorted(cands.values(), key=lambda c: (c.effect != lead_label, -c.evidence))
    diag = Diagnosis(study=study, model=model, noise_um=noise, noise_dof=nu, base=base,
                     base_tests=base_tests, screens=scores, candidates=ordered, status=status,
                     effects=effects, partial=partial, alternatives=alternatives, final=final,
                     final_tests=final_tests, loo_before=loo(model, base),
                     loo_after=loo(by_contact(final.contact), final))
    diag.summary = summarize_verdict(diag)
    diag.wall_s = time.perf_counter() - t0
    _log(verbose, f"  verdict: {status}" + (f" ({', '.join(effects)})" if effects else "")
                  + f" in {diag.wall_s:.1f} s ({Model.evaluations - evals0} model "
                    f"evaluations)")
    return diag


def _noise(model: Model, fit: Fit, known: float | None = None):
    if known is not None:
        if not known > 0:
            raise InputError(f"noise_um must be > 0, got {known}")
        return float(known), math.inf
    e, _ = neighbour_differences(model, fit.ev.r)
    if len(e) < 2:
        raise InputError(f"{model.study.path}: too few neighbouring points to estimate the "
                         f"noise level (need 3 or more points per profile or history)")
    return noise_level(e)


def _second_stage(model, by_contact, best: Candidate, rest, noise, nu, pairs, max_refits,
                  verbose):
    """With the first effect in, look for a second one that brings the misfit to noise."""
    tries = [(s_.effect, s_) for s_ in rest if s_.feasible and s_.score > 0]
    tries = tries[:max(1, max_refits - 1)]
    if "unsymmetric" in model.candidates and best.effect != "unsymmetric":
        tries.append(("unsymmetric", None))
    results = []
    for name, scr in tries:
        f = _refit(by_contact, best.fit, [best.effect, name], scr, noise, verbose)
        mdl = by_contact(f.contact)
        t = _tests_for(mdl, f, noise, nu, pairs, screen(mdl, f, noise, nu))
        results.append((evidence(model, f, best.fit), f, t))
    results = [x for x in results if not x[1].unstable]
    results.sort(key=lambda x: -x[0])
    if results and results[0][0] > STRONG_LOG_BF and not results[0][2].systematic:
        return results[0][1], results[0][2]
    return None


def _fmt_value(v, se, unit=""):
    """`v ± se unit`, rounded to the standard error's second significant digit."""
    if se is None or not math.isfinite(se) or se <= 0:
        return f"{v:.3g}{unit}"
    if se >= abs(v) or abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.3g} ± {se:.2g}{unit}"
    digits = max(0, 1 - int(math.floor(math.log10(se))))
    return f"{v:.{digits}f} ± {se:.{digits}f}{unit}"


def _strength_text(diag: Diagnosis, fit: Fit, effect: str) -> str:
    from ._calibrate import unit_of

    if effect == "unsymmetric":
        return "no extra parameter"
    m = diag.model
    parts = []
    for i in np.flatnonzero(fit.mask):
        c = m.columns[i]
        if c.group == effect:
            u = unit_of(m.names[i])
            parts.append(f"{m.names[i]} = " + _fmt_value(
                float(fit.values[i]), float(fit.stderr[i]), "" if u == "-" else f" {u}"))
    if effect == "running_in":
        for k, (v, se) in derived(m, fit).items():
            parts.append(f"identifiable product a·S_r = {_fmt_value(v, se, ' m')}")
    return ", ".join(parts)


def _signature_text(diag: Diagnosis) -> str:
    """Where the base residuals (model - measured) were largest, in words."""
    w = where_it_fails(diag.model, diag.base.ev.r)
    unit = "rev" if w["time_unit"] == "revolutions" else "h"
    bits = []
    if len(w["per_time"]) > 1:
        t = max(w["per_time"], key=lambda d: abs(d["mean_um"]))
        side = "shallower" if t["mean_um"] < 0 else "deeper"
        bits.append(f"at {t['at']:g} {unit} the base model predicts {side} wear than measured "
                    f"by {abs(t['mean_um']):.2f} µm on average")
    if len(w["per_experiment"]) > 1:
        e = max(w["per_experiment"], key=lambda d: d["rmse_um"])
        bits.append(f"the worst experiment is {e['experiment']} ({e['speed_rpm']:.0f} r/min, "
                    f"{e['clearance_mm']:.3g} mm; RMSE {e['rmse_um']:.2f} µm)")
    if w["per_angle"]:
        a = max(w["per_angle"], key=lambda d: abs(d["mean_um"]))
        bits.append(f"over angle the largest mean residual is {a['mean_um']:+.2f} µm at "
                    f"{a['from_deg']}-{a['to_deg']}°")
    return "; ".join(bits)


def _describe(effect: str) -> str:
    if effect in STRUCTURAL_CANDIDATES:
        return STRUCTURAL_CANDIDATES[effect].signature
    return get_effect(effect).signature


def summarize_verdict(diag: Diagnosis) -> str:
    t = diag.base_tests
    noise = diag.noise_um
    head = (f"The base model (as the study states it, {diag.base.k} fitted parameters) fits "
            f"{diag.model.n} measured points with RMSE {diag.base.rmse:.3f} µm against a noise "
            f"level of {noise:.3f} µm estimated from neighbouring points "
            f"(chi-square ratio {t.ratio:.2f}, p = {t.p_chi2:.1e}; lag-1 residual "
            f"autocorrelation {t.rho:.2f}, p = {t.p_autocorr:.1e}")
    if t.score_effect:
        head += f"; best single-candidate score test {t.score_effect}, p = {t.p_score:.1e}"
    head += ")."
    if diag.status == "adequate":
        return head + (" The misfit is consistent with measurement noise: no missing effect "
                       "is needed to explain these data.")
    sig = _signature_text(diag)
    if diag.status == "effect_found":
        f = diag.final
        eff = diag.effects
        names = " and ".join(eff)
        strength = "; ".join(f"{e}: {_strength_text(diag, f, e)}" for e in eff)
        lb, la = _mean_sq(diag.loo_before), _mean_sq(diag.loo_after)
        verb = "effects are" if len(eff) > 1 else "effect is"
        if not t.systematic:
            lead = next(c for c in diag.candidates if c.fit is f)
            head += (f" With so few points these tests are inconclusive, but the evidence for "
                     f"{names} over the base model is very strong (ln Bayes factor "
                     f"{lead.evidence:.1f} > ln 150, BIC with the noise level unknown).")
        text = (f"{head} The misfit is systematic, and the missing {verb} {names} "
                f"({strength}). With it the RMSE falls to {f.rmse:.3f} µm, at the noise "
                f"level (p = {diag.final_tests.p_min:.2f})"
                + (f", and the left-out-experiment prediction error from {lb:.3f} to "
                   f"{la:.3f} µm" if lb is not None and la is not None else "")
                + f". What pointed to it: {sig}"
                f" — the signature of {eff[0]} ({_describe(eff[0])}).")
        if diag.alternatives:
            text += (f" The data cannot tell it apart from {', '.join(diag.alternatives)}, "
                     f"which fits nearly as well (evidence gap < ln 20): treat the name as "
                     f"one of these, not as certain.")
        return text
    text = f"{head} The misfit is systematic ({sig})."
    if diag.partial:
        c = next(c for c in diag.candidates if c.effect == diag.partial[0])
        text += (f" The best candidate, {c.effect} ({_strength_text(diag, c.fit, c.effect)}),"
                 f" lowers the RMSE to {c.rmse_um:.3f} µm but leaves a systematic remainder "
                 f"(p = {c.tests.p_min:.1e}); no candidate or pair of candidates brings the "
                 f"misfit to noise level.")
    else:
        text += " No candidate explains it."
    return text + (" The missing physics is not among the library's candidates: look at the "
                   "residual figures for where the model fails.")
