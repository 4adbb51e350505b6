"""Calibration: least squares of measured minus predicted depth over a whole study (§6-7).

All experiments of a study run as one `vmap`-ed wear loop (schedules padded to a common
length), so one compilation serves every evaluation of the fit. The fit uses optimistix's
Levenberg-Marquardt with the exact forward-mode Jacobian through the whole wear loop.

Parameterisation: positive parameters (K_d, clearances, S_r) are fitted as log-multipliers
of their start, nested effect strengths linearly around their "off" value in units of a
typical scale. The clearance-tolerance prior of DESIGN §6 adds one residual per fitted
clearance, (c - c_nominal)/τ, in units of the noise level (estimated from a first pass).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._config import ModelConfig
from ._errors import InputError
from ._params import PARAMETER_KEYS, Params, key_to_si
from ._schedule import Schedule
from ._study import Study
from ._wear import build_schedule, wear_loop
from .effects import effect_parameter_specs, get_effect


@dataclass(frozen=True)
class FitParameter:
    """One fitted quantity. `name` is its output name (DESIGN §7), `key` its study key,
    `experiment` the index it belongs to (None: shared by all experiments)."""

    name: str
    key: str
    experiment: int | None
    log: bool
    scale: float  # user units per unit of u (linear parameters)


def parse_fit(study: Study, fit: str | list[str] | None) -> list[str]:
    """Study keys to fit from `--fit` (aliases K_d, clearance) plus enabled effects' strengths."""
    items = fit.split(",") if isinstance(fit, str) else list(fit or [])
    items = [s.strip() for s in items if s.strip()] or ["K_d", "clearance"]
    alias = {"K_d": "K_d_per_Pa", "clearance": "clearance_mm"}
    specs = effect_parameter_specs()
    keys = []
    for it in items:
        key = alias.get(it, it)
        if key not in PARAMETER_KEYS and key not in specs:
            raise InputError(f"--fit: unknown parameter {it!r}; expected K_d, clearance or a "
                             f"study key such as spring_N_per_m")
        keys.append(key)
    for eff in study.config.effects:
        for k in get_effect(eff).parameters:
            if k not in keys:
                keys.append(k)
    return list(dict.fromkeys(keys))


def fit_parameters(study: Study, keys: list[str]) -> list[FitParameter]:
    specs = effect_parameter_specs()
    out = []
    for key in keys:
        if key == "clearance_mm":
            if study.clearance_tolerance_um == 0:
                continue  # fixed at nominal by the prior's zero width
            for i, e in enumerate(study.experiments):
                out.append(FitParameter(f"clearance_mm/{e.name}", key, i, True, 1.0))
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


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def _schedules(study: Study, plist: list[Params]) -> Schedule:
    scheds = [build_schedule(p, study.config, revolutions=e.revolutions, hours=e.hours,
                             snapshots=e.snapshot_points or [e.hours or e.revolutions],
                             M=study.revolutions_per_update, pad=False)
              for p, e in zip(plist, study.experiments)]
    U = max(s.updates for s in scheds)
    S = max(s.n_snapshots for s in scheds)
    padded = []
    for s in scheds:
        extra = U - s.updates
        snap = jnp.where(s.snapshot >= s.n_snapshots, S, s.snapshot)
        padded.append(Schedule(
            cycles=jnp.concatenate([s.cycles, jnp.zeros(extra)]),
            regime=jnp.concatenate([s.regime, jnp.zeros(extra, jnp.int32)]),
            snapshot=jnp.concatenate([snap, jnp.full(extra, S, jnp.int32)]),
            cycle_end=jnp.concatenate([s.cycle_end, jnp.full(extra, s.cycle_end[-1])]),
            n_snapshots=S))
    return _stack(padded)


def _data(study: Study) -> Data:
    n = study.config.nodes
    rows = {k: [] for k in ("exp", "snap", "i0", "i1", "w", "is_max", "depth_um")}
    for ei, e in enumerate(study.experiments):
        points = e.snapshot_points
        if e.profile is not None:
            x = np.mod(e.profile.angle / (2 * np.pi) * n, n)
            i0 = np.floor(x).astype(int) % n
            for j in range(len(x)):
                rows["exp"].append(ei)
                rows["snap"].append(points.index(float(e.profile.revolutions[j])))
                rows["i0"].append(i0[j]), rows["i1"].append((i0[j] + 1) % n)
                rows["w"].append(x[j] - np.floor(x[j])), rows["is_max"].append(False)
                rows["depth_um"].append(e.profile.depth[j] * 1e6)
        if e.history is not None:
            for t, d in zip(e.history.hours, e.history.depth):
                rows["exp"].append(ei), rows["snap"].append(points.index(float(t)))
                rows["i0"].append(0), rows["i1"].append(0), rows["w"].append(0.0)
                rows["is_max"].append(True), rows["depth_um"].append(d * 1e6)
    if not rows["exp"]:
        raise InputError(f"{study.path}: no measured data (profile or history) to fit")
    return Data(exp=jnp.asarray(rows["exp"]), snap=jnp.asarray(rows["snap"]),
                i0=jnp.asarray(rows["i0"]), i1=jnp.asarray(rows["i1"]),
                w=jnp.asarray(rows["w"], jnp.float64), is_max=jnp.asarray(rows["is_max"]),
                depth_um=jnp.asarray(rows["depth_um"], jnp.float64))


class Problem(eqx.Module):
    """A study's least-squares problem: parameters u ↦ residuals [µm]."""

    cfg: ModelConfig = eqx.field(static=True)
    fits: tuple = eqx.field(static=True)
    names: tuple = eqx.field(static=True)
    exp_names: tuple = eqx.field(static=True)
    params: Params  # batched over experiments (leading axis)
    schedule: Schedule  # batched
    data: Data
    start: jax.Array  # start values of the fitted parameters, user units (p,)
    nominal_clearance_mm: jax.Array  # (experiments,)
    tolerance_um: float = eqx.field(static=True)

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
            si = vals[i] * key_to_si(f.key)
            cur = updates.get(f.key, p.get(f.key))
            if f.experiment is None:
                updates[f.key] = jnp.broadcast_to(si, (n_exp,))
            else:
                updates[f.key] = jnp.asarray(cur).at[f.experiment].set(si)
        return p.with_values(updates) if updates else p

    def snapshots(self, u):
        """Model snapshots (experiments, snapshots, nodes) [µm] and max contact residual."""
        # lax.map, not vmap: on CPU the experiments gain nothing from batching, and mapping
        # keeps the contact solver's data-dependent branches and loop counts per experiment.
        res = jax.lax.map(lambda ps: wear_loop(ps[0], self.cfg, ps[1]),
                          (self.batched_params(u), self.schedule))
        return res.snapshots * 1e6, res

    def predict(self, u):
        """Model depth at every measured row [µm]."""
        snaps, _ = self.snapshots(u)
        d = self.data
        prof = snaps[d.exp, d.snap]  # (rows, nodes)
        at = jnp.take_along_axis(prof, d.i0[:, None], 1)[:, 0] * (1 - d.w) + \
            jnp.take_along_axis(prof, d.i1[:, None], 1)[:, 0] * d.w
        return jnp.where(d.is_max, jnp.max(prof, axis=1), at)

    def data_residuals(self, u):
        return self.predict(u) - self.data.depth_um

    def prior_residuals(self, u, noise_um):
        """(c - c_nominal)/τ per fitted clearance, scaled to µm of depth by the noise level."""
        if not math.isfinite(self.tolerance_um):
            return jnp.zeros(0)
        vals = self.values(u)
        out = [(vals[i] - self.nominal_clearance_mm[f.experiment]) * 1e3 / self.tolerance_um
               for i, f in enumerate(self.fits) if f.key == "clearance_mm"]
        return noise_um * jnp.stack(out) if out else jnp.zeros(0)

    def residuals(self, u, noise_um):
        return jnp.concatenate([self.data_residuals(u), self.prior_residuals(u, noise_um)])


def build_problem(study: Study, keys: list[str], start: dict | None = None) -> Problem:
    """The least-squares problem for fitting study keys `keys` (see `parse_fit`).

    `start`: optional start values by output name (user units), else the study's values.
    """
    fits = fit_parameters(study, keys)
    plist = [study.params(e) for e in study.experiments]
    nominal = [float(p.clearance) * 1e3 for p in plist]
    start = dict(start or {})
    s0 = []
    specs = effect_parameter_specs()
    for f in fits:
        if f.name in start:
            s0.append(float(start[f.name]))
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
                   params=_stack(plist), schedule=_schedules(study, plist), data=_data(study),
                   start=jnp.asarray(s0, jnp.float64),
                   nominal_clearance_mm=jnp.asarray(nominal),
                   tolerance_um=study.clearance_tolerance_um)


@eqx.filter_jit
def _residuals(problem: Problem, u, noise_um):
    return problem.residuals(u, noise_um)


@eqx.filter_jit
def _jacobian(problem: Problem, u, noise_um):
    return jax.jacfwd(lambda v: problem.residuals(v, noise_um))(u)


@eqx.filter_jit
def _predict(problem: Problem, u):
    snaps, res = problem.snapshots(u)
    return problem.predict(u), snaps, jnp.max(res.max_residual), jnp.max(res.worn_through_cycle)


@eqx.filter_jit
def _lm(problem: Problem, u0, noise_um, max_steps: int, rtol: float, verbose: bool):
    def fn(u, args):
        return problem.residuals(u, noise_um)

    def show(**kw):
        if verbose:
            n = problem.data.depth_um.shape[0]
            step = kw["num_steps"][1]
            loss = kw["loss_last_accepted_step"][1]
            jax.debug.callback(lambda s, lo: print(
                f"    LM step {int(s):3d}: rms residual {math.sqrt(2 * float(lo) / n):.4f} µm",
                file=sys.stderr, flush=True), step, loss)

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=1e-12, verbose=show)
    sol = optx.least_squares(fn, solver, u0, max_steps=max_steps, throw=False)
    return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


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
    jacobian: np.ndarray  # of the normalised residuals w.r.t. u (rows incl. prior)
    problem: Problem
    snapshots_um: np.ndarray  # (experiments, snapshots, nodes)
    max_contact_residual: float

    def parameters_json(self) -> dict:
        return {n: {"value": float(v), "stderr": (float(s) if np.isfinite(s) else None)}
                for n, v, s in zip(self.names, self.values, self.stderr)}

    @property
    def n_data(self) -> int:
        return len(self.residuals_um)

    @property
    def rss(self) -> float:
        return float(np.sum(self.residuals_um ** 2))


def fit(problem: Problem, u0=None, *, max_steps: int = 60, rtol: float = 1e-7,
        verbose: bool = False) -> FitResult:
    """Levenberg-Marquardt fit, then Gauss-Newton standard errors and correlations.

    Two passes: the first weights the clearance prior with a 1 µm noise guess, the second
    with the noise level estimated from the first pass's residuals.
    """
    p = len(problem.fits)
    u = jnp.zeros(p) if u0 is None else jnp.asarray(u0, jnp.float64)
    n = int(problem.data.depth_um.shape[0])
    noise = 1.0
    converged, steps = True, 0
    if p:
        for stage in range(2):
            if verbose:
                print(f"  fit pass {stage + 1}/2 ({p} parameters, {n} data rows)",
                      file=sys.stderr, flush=True)
            u, ok, k = _lm(problem, u, jnp.asarray(noise), max_steps, rtol, verbose)
            converged, steps = bool(ok), steps + int(k)
            r = np.asarray(_residuals(problem, u, jnp.asarray(noise)))[:n]
            dof = max(n - p, 1)
            noise = max(float(np.sqrt(np.sum(r ** 2) / dof)), 1e-6)
            if not math.isfinite(problem.tolerance_um) or not any(
                    f.key == "clearance_mm" for f in problem.fits):
                break
    return summarize(problem, u, noise, converged, steps)


def summarize(problem: Problem, u, noise_guess, converged=True, steps=0) -> FitResult:
    u = jnp.asarray(u, jnp.float64)
    n = int(problem.data.depth_um.shape[0])
    p = len(problem.fits)
    pred, snaps, max_res, worn = _predict(problem, u)
    pred = np.asarray(pred)
    meas = np.asarray(problem.data.depth_um)
    r = pred - meas
    dof = max(n - p, 1)
    noise = float(np.sqrt(np.sum(r ** 2) / dof))
    flags = []
    if p:
        J = np.asarray(_jacobian(problem, u, jnp.asarray(noise_guess)))
        Jn = J / max(noise, 1e-12)  # residuals in units of the noise (prior rows already are)
        Jn[n:] = J[n:] / max(noise_guess, 1e-12)
        JtJ = Jn.T @ Jn
        try:
            cov_u = np.linalg.pinv(JtJ, rcond=1e-13, hermitian=True)
        except np.linalg.LinAlgError:
            cov_u = np.full((p, p), np.nan)
        vals = np.asarray(problem.values(u))
        deriv = np.array([vals[i] if f.log else f.scale for i, f in enumerate(problem.fits)])
        se = np.sqrt(np.clip(np.diag(cov_u), 0, None)) * np.abs(deriv)
        d = np.sqrt(np.clip(np.diag(cov_u), 1e-300, None))
        corr = cov_u / np.outer(d, d)
        rank = np.linalg.matrix_rank(JtJ, tol=1e-10 * np.max(np.abs(JtJ)))
        if rank < p:
            flags.append(f"Jacobian rank {rank} < {p} parameters: some are not identifiable")
        for i, name in enumerate(problem.names):
            rel = se[i] / max(abs(vals[i]), 1e-300)
            f = problem.fits[i]
            if f.log and rel > 1.0:
                flags.append(f"{name}: standard error {rel:.0%} of the value (not identifiable)")
            for j in range(i + 1, p):
                if abs(corr[i, j]) > 0.99:
                    flags.append(f"{name} and {problem.names[j]}: correlation "
                                 f"{corr[i, j]:+.3f} (|r| > 0.99, not separately identifiable)")
    else:
        J = np.zeros((n, 0))
        vals, se, corr = np.zeros(0), np.zeros(0), np.zeros((0, 0))
    exp_idx = np.asarray(problem.data.exp)
    per = {}
    for i, name in enumerate(problem.exp_names):
        m = exp_idx == i
        if m.any():
            per[name] = float(np.sqrt(np.mean(r[m] ** 2)))
    msg = "converged" if converged else "did not converge within the step limit"
    if float(worn) >= 0:
        msg += "; the layer wore through during the fit's last evaluation"
        converged = False
    if not float(max_res) < 1e-9:
        msg += f"; contact residual {float(max_res):.1e} ≥ 1e-9"
        converged = False
    return FitResult(names=list(problem.names), values=np.asarray(vals), stderr=np.asarray(se),
                     correlation=np.asarray(corr), u=np.asarray(u),
                     rmse_um=float(np.sqrt(np.mean(r ** 2))), rmse_per_experiment=per,
                     noise_um=noise, residuals_um=r, predicted_um=pred, measured_um=meas,
                     row_experiment=exp_idx, converged=converged, iterations=int(steps),
                     message=msg, flags=flags, jacobian=J, problem=problem,
                     snapshots_um=np.asarray(snaps), max_contact_residual=float(max_res))


def calibrate(study: Study, fit_spec="K_d,clearance", *, start=None, verbose=False,
              max_steps: int = 60) -> FitResult:
    """Fit a study's parameters to its data (DESIGN §7 `calibrate`)."""
    keys = parse_fit(study, fit_spec)
    problem = build_problem(study, keys, start)
    return fit(problem, max_steps=max_steps, verbose=verbose)
