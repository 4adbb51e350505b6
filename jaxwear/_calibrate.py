"""Calibration: least squares of measured minus predicted depth over a whole study (§6-7).

All experiments of a study run in one compiled function (schedules padded to a common
length), and that one function returns the residuals, the exact forward-mode Jacobian
through the whole wear loop (`jax.jacfwd`), and the model's snapshots. Everything the fit
needs (the robust start, every trial, the standard errors) is an evaluation of it, so a
problem compiles once. The iteration itself is the one least-squares core, `jaxwear.lsq`
(optimistix's Levenberg-Marquardt pieces, the statistical stop, the noise re-estimated
inside the loop, the covariance); this module only states the problem.

Parameterisation: positive parameters (K_d, clearances, S_r) are fitted as log-multipliers
of their start, nested effect strengths linearly around their "off" value in units of a
typical scale, within the effects' bounds. The clearance-tolerance prior of DESIGN §6 adds
one row per fitted clearance, (c - c_nominal)/τ in units of its standard deviation (the
core weights the data rows by 1/σ); τ = inf gives zero rows (free clearances), τ = 0
removes the clearances from the fit. With `[fit] angle_tolerance_deg` > 0 each profile's
angular registration is fitted too (`angle_offset_deg/EXP`, linear, started at the given
offset, the same kind of prior row): the model is read at the shifted angles by a periodic
interpolation differentiable in the offset (docs/measurements.md).

Outcome semantics: a fit that stops without meeting its convergence test still returns its
result, with `converged = False`, `status` ("stalled" or "budget") and a `message` saying
why; only a start that cannot be evaluated at all (worn through whatever K_d, or
non-finite) raises `FitError`, and a noise level the data cannot determine raises
`InputError` before any evaluation.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import lsq
from ._config import ModelConfig
from ._errors import InputError
from ._params import PARAMETER_KEYS, Params, key_to_si
from ._schedule import Schedule, pad_schedule
from ._study import Study
from ._wear import adaptive_attempts, build_schedule, schedule_numerics, wear_loop
from .effects import effect_parameter_specs, get_effect, product_pairs, project_products


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


def registered(study: Study, result) -> Study:
    """`study` with every scan rotated by its fitted registration (`angle_offset_deg/EXP`
    of `result`, a `FitResult`) and the registration then held (`angle_tolerance_deg` 0):
    what diagnose compares its candidates at, after the base fit found the offsets."""
    from dataclasses import replace

    fitted = dict(zip(result.names, map(float, result.values)))
    exps = []
    for e in study.experiments:
        name = f"angle_offset_deg/{e.name}"
        if e.profile is not None and name in fitted:
            shift = fitted[name] - e.profile.angle_offset_deg
            prof = replace(e.profile, angle=np.mod(e.profile.angle + np.deg2rad(shift),
                                                   2 * np.pi),
                           angle_offset_deg=fitted[name])
            e = replace(e, profile=prof)
        exps.append(e)
    return replace(study.with_experiments(exps), angle_tolerance_deg=0.0)


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
    noise_um: float | None = eqx.field(static=True, default=None)  # [fit] noise_um, if given

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
        """Fitted parameters in user units from u (p,). A strength fitted with its `per`
        parameter (`EffectParameter.per`) is the linear coordinate times exp(-u_per): u
        then measures the product the data identify (running-in: a·S_r)."""
        out = []
        for i, f in enumerate(self.fits):
            if f.log:
                out.append(self.start[i] * jnp.exp(u[i]))
            else:
                out.append(self.start[i] + f.scale * u[i])
        for i, j in product_pairs([f.key for f in self.fits]):
            out[i] = out[i] * jnp.exp(-u[j])
        return jnp.stack(out) if out else jnp.zeros(0)

    def value_jacobian(self, u) -> np.ndarray:
        """d values / d u (p, p) at u: diagonal but for the product pairs."""
        if not self.fits:
            return np.zeros((0, 0))
        return np.asarray(jax.jacfwd(self.values)(jnp.asarray(u, jnp.float64)))

    def bounds_u(self):
        """Bounds on u (p,) from the effects' parameter bounds (others unbounded)."""
        specs = effect_parameter_specs()
        s = np.asarray(self.start)
        lo, hi = np.full(len(self.fits), -np.inf), np.full(len(self.fits), np.inf)
        for i, f in enumerate(self.fits):
            if f.key not in specs:
                continue
            sp = specs[f.key]
            if f.log:
                lo[i] = math.log(sp.lower / s[i]) if sp.lower > 0 else -np.inf
                hi[i] = math.log(sp.upper / s[i]) if math.isfinite(sp.upper) else np.inf
            else:
                lo[i], hi[i] = (sp.lower - s[i]) / f.scale, (sp.upper - s[i]) / f.scale
        return lo, hi

    def project(self, u) -> np.ndarray:
        """u with every product strength (`EffectParameter.per`) inside its value bounds,
        by moving its linear coordinate: the box on u cannot state a bound on
        linear·exp(-u_per), and an unbounded running-in amplitude (S_r to 0 along the
        valley of equal a·S_r) makes the wear loop arbitrarily stiff."""
        return project_products([f.key for f in self.fits], np.asarray(self.start),
                                [f.scale for f in self.fits], u)

    def u_of(self, values):
        """Inverse of `values` (numpy in, numpy out)."""
        v = np.asarray(values, float)
        s = np.asarray(self.start)
        lin = v.copy()
        for i, j in product_pairs([f.key for f in self.fits]):
            lin[i] = v[i] * v[j] / s[j]  # the linear coordinate of the product
        out = []
        for i, f in enumerate(self.fits):
            out.append(np.log(v[i] / s[i]) if f.log else (lin[i] - s[i]) / f.scale)
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
                                                   jnp.float64),
                   noise_um=study.noise_um)


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
    return evaluate_with(problem, u, noise_um)[0]


def evaluate_with(problem: Problem, u, noise_um: float = 1.0, *, doublings: int = 3
                  ) -> tuple[Evaluation, Problem]:
    """`evaluate`, and the problem it ran (its attempt count raised where u needed more): a
    fit keeps that problem, so later trials neither repeat the short run nor recompile."""
    problem = _enough_attempts(problem, u)
    u, noise_um = jnp.asarray(u, jnp.float64), jnp.asarray(noise_um, jnp.float64)
    ev = _evaluate_jit(problem, u, noise_um)
    # The attempt count is an estimate: where the loop did not reach the end (a stiff
    # layer's rejections), double it (a recompilation) rather than hand LM a NaN.
    for _ in range(doublings):
        if not (problem.schedule.adaptive and not np.isfinite(float(ev.error_estimate))):
            break
        sched = problem.schedule
        problem = dataclasses.replace(
            problem, schedule=sched.more_attempts())
        ev = _evaluate_jit(problem, u, noise_um)
    return jax.tree.map(np.asarray, ev), problem


def _usable(ev: Evaluation) -> bool:
    return bool(np.all(np.isfinite(ev.residuals)) and np.all(np.isfinite(ev.jacobian))
                and float(ev.worn) < 0)


def _log(verbose, msg):
    if verbose:
        print(msg, file=sys.stderr, flush=True)


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
    status: str = "converged"  # the core's: converged, stalled, budget
    noise_used_um: float = 0.0  # σ the data rows were weighted with at the answer
    noise_given: bool = False
    step_se: float = 0.0  # the next Gauss-Newton step at the answer, in standard errors
    resolution: dict | None = None  # the spatial resolution and its check (`calibrate`)

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
            "status": self.status,
            "iterations": int(self.iterations),
            "model_evaluations": int(self.iterations),
            "next_step_standard_errors": (float(self.step_se)
                                          if math.isfinite(self.step_se) else None),
            "noise_weight_um": float(self.noise_used_um),
            "noise": "given" if self.noise_given else "estimated from the residuals",
            "message": self.message,
            "flags": list(self.flags),
            "n_data": int(self.n_data),
            "clearance_tolerance_um": tol if math.isfinite(tol) else "inf",
            "max_contact_residual": float(self.max_contact_residual),
            "integration": self.integration,
            "resolution": self.resolution,
        }

    @property
    def n_data(self) -> int:
        return len(self.residuals_um)

    @property
    def rss(self) -> float:
        return float(np.sum(self.residuals_um ** 2))


def point(problem: Problem, u) -> lsq.Point:
    """The problem at u as the least-squares core sees it: data rows, prior rows in units of
    their standard deviation (the evaluation's noise weight 1), usability and the adaptive
    integrator's error estimate: its step choice makes the model's error jump between
    nearby parameters, which sets the floor of a meaningful decrease. The paper
    integrator's fixed steps give a smooth bias instead, no floor (0)."""
    ev = evaluate(problem, u, 1.0)
    return _as_point(problem, u, ev)


def _as_point(problem: Problem, u, ev: Evaluation) -> lsq.Point:
    n = problem.n_data
    err = ev.error_estimate
    err = (float(err) if problem.schedule.adaptive and err is not None and np.isfinite(err)
           else 0.0)
    return lsq.Point(u=np.asarray(u, np.float64), r=ev.residuals[:n], predicted=ev.predicted,
                     J=ev.jacobian[:n], r_prior=ev.residuals[n:], J_prior=ev.jacobian[n:],
                     usable=_usable(ev), error_um=err, extra=ev)


def _unusable_point(problem: Problem, u) -> lsq.Point:
    """A trial the fit declines to evaluate (see `fit`): rejected as unusable."""
    n, p = problem.n_data, len(problem.fits)
    m = _n_prior_rows(problem)
    return lsq.Point(u=np.asarray(u, np.float64), r=np.full(n, np.inf),
                     predicted=np.full(n, np.nan), J=np.zeros((n, p)),
                     r_prior=np.zeros(m), J_prior=np.zeros((m, p)), usable=False)


def _n_prior_rows(problem: Problem) -> int:
    return sum(f.key in ("clearance_mm", "angle_offset_deg") for f in problem.fits)


def check_noise_determined(problem: Problem, noise_um: float | None, *, hint: str) -> None:
    """Refuse, before any evaluation, what is known then: a noise level the data cannot
    determine (σ̂ needs more data rows than fitted parameters; `hint` names how to give σ),
    and a per-experiment parameter that no measured row can see (an experiment without
    data, its clearance free of any prior)."""
    n, p = problem.n_data, len(problem.fits)
    noise_um = problem.noise_um if noise_um is None else noise_um
    if noise_um is None and p and n <= p:
        raise InputError(f"the {n} data rows do not determine the noise level with {p} fitted "
                         f"parameters ({', '.join(problem.names)}); give the measurement "
                         f"noise with {hint} (or fit fewer parameters, or add data)")
    seen = set(np.asarray(problem.data.exp).tolist())
    free_prior = not math.isfinite(float(problem.tolerance_um))
    blind = [f.name for f in problem.fits if f.experiment is not None
             and f.experiment not in seen and (f.key != "clearance_mm" or free_prior)]
    if blind:
        raise InputError(f"no measured row can see {', '.join(blind)}: the experiment has no "
                         f"profile or history; give its data, a finite [fit] "
                         f"clearance_tolerance_um, or leave it out of the fit")


def fit(problem: Problem, u0=None, *, noise_um: float | None = None,
        max_evaluations: int = 30, verbose: bool = False, robust: bool = True,
        label: str = "fit", se_tol: float = lsq.SE_TOL) -> FitResult:
    """Least-squares fit through the one core (`jaxwear.lsq.solve`), then standard errors,
    correlations and flags.

    **Arguments:**
    - `u0`: start in the problem's parameterisation (default: the problem's start values).
    - `noise_um`: measurement noise σ [µm] if known (weights the data rows against the
      priors); default: the study's `[fit] noise_um`, else re-estimated from the residuals
      inside the loop (one pass).
    - `max_evaluations`: budget of the iteration (the robust start's evaluations come on
      top; all are counted in `iterations`).
    - `verbose`: one line per evaluation on stderr. `robust`: rescale K_d first.
    - `se_tol`: the stop, as a fraction of a standard error (`lsq.solve`).

    Raises `InputError` before any evaluation when σ is not given and the data rows do not
    outnumber the fitted parameters; `FitError` when no start can be evaluated.
    """
    noise_um = problem.noise_um if noise_um is None else noise_um
    check_noise_determined(problem, noise_um, hint="[fit] noise_um")
    p = len(problem.fits)
    u = np.zeros(p) if u0 is None else np.asarray(u0, np.float64)
    log = (lambda m: _log(True, m)) if verbose else None
    held = [problem]

    def start_model(v):
        # the largest attempt count any evaluation needed is kept for the next ones
        ev, used = evaluate_with(held[0], v, 1.0)
        if used.schedule.attempts > held[0].schedule.attempts:
            held[0] = used
        return _as_point(used, v, ev)

    def model(v):
        # A trial that needs far more integration steps than the fit's current point (a
        # stiff corner: running-in over a millimetre, K_d 100x) is rejected unevaluated:
        # the trust region then shrinks towards where the model is affordable, and a fit
        # that truly goes there gets there in steps (at most 4x the cost each). A trial
        # doubles the attempt count once at most (the start three times).
        if (held[0].schedule.adaptive and _enough_attempts(held[0], v).schedule.attempts
                > 4 * held[0].schedule.attempts):
            return _unusable_point(held[0], v)
        ev, used = evaluate_with(held[0], v, 1.0, doublings=1)
        if used.schedule.attempts > held[0].schedule.attempts:
            held[0] = used
        return _as_point(used, v, ev)

    k = next((i for i, f in enumerate(problem.fits) if f.key == "K_d_per_Pa"), None)
    if robust and p:
        u, pt, evals0, why = lsq.robust_start(start_model, u, k, measured=np.asarray(
            problem.data.depth_um), log=log)
        if why:
            raise FitError(f"cannot start the fit: {why} "
                           f"{dict(zip(problem.names, np.asarray(problem.values(u))))}")
    else:
        pt, evals0 = start_model(u), 1
    lo, hi = problem.bounds_u()
    _log(verbose, f"  fit: {p} parameters, {problem.n_data} data rows")
    out = lsq.solve(model, u, point0=pt, lower=lo, upper=hi, noise_um=noise_um,
                    max_evaluations=max_evaluations, label=label, log=log,
                    project=problem.project, se_tol=se_tol)
    return summarize(problem, out, evals0 + out.evaluations)


def _product_flag(names, vals, cov, unidentified) -> list[str]:
    """With K_d and load_scale both fitted: only their product is identifiable from depths
    (the wear rate is K_d p dS and the pressure scales with the load; the load's size moves
    the contact arc only a little), so say so, with the product and its standard error."""
    if not ("K_d_per_Pa" in names and "load_scale" in names):
        return []
    i, j = names.index("K_d_per_Pa"), names.index("load_scale")
    prod = vals[i] * vals[j]
    rel2 = (cov[i, i] / vals[i] ** 2 + cov[j, j] / vals[j] ** 2
            + 2 * cov[i, j] / (vals[i] * vals[j]))
    se = "undetermined" if unidentified[i] or unidentified[j] or not rel2 >= 0 else \
        f"{abs(prod) * np.sqrt(rel2):.3g}"
    r = cov[i, j] / np.sqrt(max(cov[i, i] * cov[j, j], 1e-300))
    return [f"K_d_per_Pa and load_scale: only their product K_d x load_scale = {prod:.4g} "
            f"(standard error {se}) 1/Pa is identifiable from depth data (wear is K_d p dS and "
            f"p scales with the load); each alone (correlation {r:+.3f}) rests on how the "
            f"load's size shapes the contact arc: fix one of them (the load from the "
            f"multibody model, or K_d from a wear test)"]


def summarize(problem: Problem, out: lsq.Outcome, evaluations: int) -> FitResult:
    """FitResult at the core's answer: values, standard errors (the core's covariance at the
    answer), correlations, RMSE, flags."""
    u, ev = out.u, out.point.extra
    n = problem.n_data
    p = len(problem.fits)
    pred = np.asarray(ev.predicted)
    meas = np.asarray(problem.data.depth_um)
    r = pred - meas
    noise = float(np.sqrt(np.sum(r ** 2) / max(n - p, 1)))
    flags = []
    J = np.asarray(ev.jacobian)
    if p:
        vals = np.asarray(problem.values(u))
        # covariance of the values (delta method through the parameterisation, exact for
        # its diagonal part); a value that depends on an undetermined u is undetermined
        G = problem.value_jacobian(u)
        cov_u = G @ out.cov.cov @ G.T
        unidentified = np.any((np.abs(G) > 0) & out.cov.undetermined[None, :], axis=1)
        se = np.sqrt(np.clip(np.diag(cov_u), 0, None))
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
        flags += _product_flag(problem.names, vals, cov_u, unidentified)
    else:
        vals, se, corr = np.zeros(0), np.zeros(0), np.zeros((0, 0))
    if out.status != "converged":
        flags.append(f"the fit did not converge ({out.status}): {out.message}")
    exp_idx = np.asarray(problem.data.exp)
    per = {}
    for i, name in enumerate(problem.exp_names):
        m = exp_idx == i
        if m.any():
            per[name] = float(np.sqrt(np.mean(r[m] ** 2)))
    msg, converged = out.message, out.converged
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
                     row_experiment=exp_idx, converged=converged, iterations=int(evaluations),
                     message=msg, flags=flags, jacobian=J, problem=problem,
                     snapshots_um=np.asarray(ev.snapshots),
                     max_contact_residual=float(ev.max_residual),
                     integration=_integration(problem, ev), status=out.status,
                     noise_used_um=float(out.noise_um), noise_given=out.noise_given,
                     step_se=float(out.step_se))


def calibrate(study: Study, fit_spec="K_d,clearance", *, start=None, verbose=False,
              max_evaluations: int = 30, noise_um: float | None = None) -> FitResult:
    """Fit a study's parameters to its data (DESIGN §7 `calibrate`).

    **Arguments:**
    - `study`: a loaded study with profile and/or history data.
    - `fit_spec`: "K_d,clearance" (default) or any comma-separated study keys; strengths of
      the effects the study switches on are always added.
    - `start`: optional start values by output name (user units), e.g.
      `{"K_d_per_Pa": 1e-12, "clearance_mm/n276": 0.06}`.
    - `noise_um`: measurement noise σ [µm] if known (default: the study's `[fit] noise_um`,
      else estimated inside the fit).
    - `max_evaluations`: the fit's budget of model evaluations.

    **Returns:** a `FitResult` (`.to_json()` gives the DESIGN §7 document).
    """
    keys = with_registration(study, parse_fit(study, fit_spec))
    return fit_study(study, keys, start=start, noise_um=noise_um,
                     max_evaluations=max_evaluations, verbose=verbose)


def fit_study(study: Study, keys: list[str], *, start=None, noise_um: float | None = None,
              max_evaluations: int = 30, verbose: bool = False,
              se_tol: float = lsq.SE_TOL) -> FitResult:
    """The whole fit of a study: build the problem, refuse what is known before any
    evaluation, fit, re-check the integration error at the answer and, where the study
    leaves the resolution to the error (DESIGN §6), fit at the coarsest level of
    `_resolution.LEVELS` and check the answer against the next finer level (one
    Gauss-Newton step there must move no parameter by more than 0.1 standard error; else
    refit at the finer level from the answer). `result.resolution` reports it, and
    `result.iterations` counts every model evaluation of all levels (checks included)."""
    from . import _resolution as res

    noise_um = study.noise_um if noise_um is None else noise_um
    kw = dict(noise_um=noise_um, max_evaluations=max_evaluations, verbose=verbose,
              se_tol=se_tol)
    if not study.auto_resolution:
        result = _fit_at(study, keys, start, **kw)
        result.resolution = res.given(study)
        return result
    levels = res.LEVELS
    result = _fit_at(res.at_level(study, levels[0]), keys, start, **kw)
    spent = 0  # evaluations of the coarser levels' fits and of the checks
    for i, level in enumerate(levels):
        if i + 1 == len(levels):
            result.resolution = res.report(level, None, kind="fit", value=None, ok=False)
            result.flags.append(f"resolution: the fit needed the finest level {level[0]} x "
                                f"{level[1]}, which is not checked against a finer one")
            break
        finer = levels[i + 1]
        ratio = refinement_step(res.at_level(study, finer), keys, result)
        spent += 1
        ok = ratio <= res.FIT_SE_TOL
        _log(verbose, f"  resolution {level[0]} x {level[1]}: a Gauss-Newton step at "
                      f"{finer[0]} x {finer[1]} moves the answer by {ratio:.2g} standard "
                      f"errors" + ("" if ok else f" (> {res.FIT_SE_TOL:g}): refit there"))
        if ok:
            result.resolution = res.report(level, finer, kind="fit", value=ratio, ok=True)
            break
        spent += result.iterations
        result = _fit_at(res.at_level(study, finer), keys,
                         dict(zip(result.names, map(float, result.values))), **kw)
    # every model evaluation of the answer: all levels' fits and the forward checks
    result.iterations += spent
    return result


def _fit_at(study: Study, keys, start, *, noise_um, max_evaluations, verbose,
            se_tol) -> FitResult:
    problem = build_problem(study, keys, start)
    check_noise_determined(problem, noise_um, hint="[fit] noise_um")
    result = fit(problem, noise_um=noise_um, max_evaluations=max_evaluations, verbose=verbose,
                 se_tol=se_tol)
    return recheck_integration(study, result, noise_um=noise_um,
                               max_evaluations=max_evaluations, verbose=verbose,
                               se_tol=se_tol)


@eqx.filter_jit
def _predict_jit(problem: Problem, u):
    """Model depth at every row [µm] and whether the model is usable there (forward only: a
    resolution check needs no Jacobian at the finer level, see `refinement_step`)."""
    snaps, res = problem.snapshots(u)
    ok = (jnp.max(res.worn_through_cycle) < 0) & jnp.isfinite(jnp.max(res.error_estimate))
    return problem.predict_from(snaps, u), ok


def refinement_step(finer: Study, keys, result: FitResult) -> float:
    """The largest move, in standard errors, of one Gauss-Newton step of the `finer`
    study's problem from the fitted values of `result`.

    The step takes the finer level's residuals (one forward run there) and the fit's own
    Jacobian: what a finer grid changes is the residual, by the discretisation error; its
    effect on the Jacobian changes the step only at second order. This keeps the check to
    one forward compilation and run at the finer level (the Jacobian there would cost ~3x
    the compilation and ~7x the run, measured on the rig at 180 x 144)."""
    prob = build_problem(finer, keys, dict(zip(result.names, map(float, result.values))))
    p = len(prob.fits)
    if not p:
        return 0.0
    u0 = jnp.zeros(p)
    prob = _enough_attempts(prob, u0)
    pred, ok = _predict_jit(prob, u0)
    for _ in range(3):  # the attempt count is an estimate (as in `evaluate_with`)
        if bool(ok) or not prob.schedule.adaptive:
            break
        prob = dataclasses.replace(prob, schedule=prob.schedule.more_attempts())
        pred, ok = _predict_jit(prob, u0)
    pred = np.asarray(pred)
    n = prob.n_data
    J = np.asarray(result.jacobian)
    prior = np.asarray(prob.prior_residuals(u0, 1.0))
    pt = lsq.Point(u=np.zeros(p), r=pred - np.asarray(prob.data.depth_um), predicted=pred,
                   J=J[:n], r_prior=prior, J_prior=J[n:], usable=bool(ok))
    lo, hi = prob.bounds_u()
    return lsq.step_in_standard_errors(pt, result.noise_used_um, lo, hi)[0]


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
    checks = 0  # evaluations of the check itself (counted with the fit's)
    for k in range(refits + 1):
        # schedules (and attempt counts) at the fitted values
        fitted = dataclasses.replace(problem, schedule=_schedules(
            dataclasses.replace(study, wear_tolerance_um=tol), per_exp(result.u)))
        ev = evaluate(fitted, result.u)
        checks += 1
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
    result.iterations += checks
    if err <= study.wear_tolerance_um:
        return result
    note = (f"integration error estimate {err:.3g} µm at the fitted values exceeds the "
            f"tolerance {study.wear_tolerance_um:g} µm (after {refits} refits); lower "
            f"[numerics] wear_tolerance_um")
    result.flags.append(note)
    result.message += "; " + note
    return result
