"""Which experiment to run next: candidate experiments ranked for a goal (issue 44).

A rig test takes hours to days; the fitted model answers "which test next?" in seconds, from
the quantities every fit already has: the Jacobian of the measured rows (the Fisher
information of the study) and a batched run over conditions (the candidates' Jacobians).

**Candidates.** A crank-slider study's candidate is a new specimen run at conditions
(`speed_rpm`, `clearance_mm`, `load_scale`, ...) for `revolutions`, its profile scanned at
the interruptions `measure_at` (synth's plan: 2000, 5000, 10000 revolutions below the end,
and the end). Candidates that differ only in their length share one run (to the longest,
with a snapshot at every interruption), so a grid of S conditions x D lengths costs S runs.
A timed study's candidate (the boom: one specimen, its depth history) is the next
measurement of the maximum depth of an existing experiment at `hours`: one run of that
experiment with a snapshot at every candidate time.

**One compiled call.** The candidate runs are the experiments of one candidate study, built
as the study's own residual model (`_residual.build_model`, the fit's machinery: its
`lax.map` over experiments), started at the fitted values; `jax.jacfwd` gives every run's
snapshots and their Jacobian with respect to the fitted shared parameters and to a common
shift of the runs' clearances (the runs are independent, so the derivative of run e in that
shift is the derivative in its own clearance: one tangent for all candidates' nuisance
clearances).

**Goals** (u: the study's packed parameter vector, shared parameters only, the study's
nuisance parameters, its clearances and registrations, marginalised by Schur complements):
- `parameters`: D-optimal, log det(I_study + I_candidate) (higher is better); or with
  `for_keys`, the root mean square of the named parameters' relative standard errors after
  adding the candidate (lower is better).
- `forecast`: the half-width of the linearised forecast band (`level`, parameter part,
  z-quantile) of the maximum depth at `at`, g^T (I_study + I_candidate)^-1 g, g the
  gradient of the forecast (lower is better).
- `separate`: two rival models A and B fitted to the same data; the expected chi-square
  of the difference of their predicted rows at the candidate, d^T (σ²/n + U U^T)^-1 d with
  U U^T = J_A C_A J_A^T + J_B C_B J_B^T + τ² j j^T (each model's parameter covariance after
  the study, and the new specimen's clearance, common to both, j the difference of its
  Jacobian columns) (higher is better), with the number n of repeated scans for it to
  reach `SEPARATE_CHI2` (a likelihood ratio of 20).

A candidate's information: scan rows at the study's scan spacing, linear interpolation W
from the nodes, so a snapshot adds J^T (W^T W) J / σ²; a depth history adds the row of the
node at the maximum. Its own clearance is a nuisance with the clearance prior τ.

`--budget N`: greedy; each pick adds its information (both models' for `separate`) before
the next is chosen among the other candidates: a set of N different experiments.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from dataclasses import dataclass
from statistics import NormalDist

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._analyses.predict.forecast import training_study
from jaxwear._analyses.synth import INTERRUPTIONS
from jaxwear._core.errors import InputError
from jaxwear._core.log import log as _log
from jaxwear._core.numbers import parse_range
from jaxwear._inference.calibrate import FitResult, fit_study
from jaxwear._inference.packing import study_fit_keys
from jaxwear._inference.residual import build_model, enough_attempts
from jaxwear._physics.config import timed
from jaxwear._physics.effects import registered_effects
from jaxwear._physics.params import key_to_si
from jaxwear._study.budget import estimate_work
from jaxwear._study.plausible import check_value
from jaxwear._study.resolution import at_stable_update
from jaxwear._study.study import Experiment, History, Profile, Study

GOALS = ("separate", "parameters", "forecast")
SEPARATE_CHI2 = 2.0 * math.log(20.0)  # a likelihood ratio of 20 between the two models
MAX_SCANS = 100  # repeated scans searched for `scans_needed`
NUISANCE = ("clearance_mm", "angle_offset_deg")  # per experiment, marginalised
# keys a candidate may vary: a new specimen's conditions (crank-slider studies)
CRANK_KEYS = ("speed_rpm", "clearance_mm", "load_scale", "revolutions")
TIMED_KEYS = ("hours",)
DEFAULT_SCAN_STEP_DEG = 2.0
# compilation of the candidates' batched Jacobian, added to the work estimate (measured on
# 2 shared cores: 1-3 s for the rig at 64-90 nodes, one or two tangents)
COMPILE_ALLOWANCE_S = 5.0


# ------------------------------------------------------------------ the candidates


@dataclass(frozen=True)
class Plan:
    """The candidate set: `conditions[i]` (key → value in its unit) of candidate i, its
    measurement points `measure_at[i]` (revolutions or hours), the run `run[i]` it reads and
    the snapshot indices `snaps[i]` of that run it measures. `runs`: the runs' experiments
    (conditions without data), `points[r]` each run's snapshot points (sorted)."""

    keys: tuple
    conditions: list
    measure_at: list
    run: np.ndarray
    snaps: list
    runs: list
    points: list
    unit: str  # "revolutions" or "hours"
    continuation: str | None = None  # timed: the experiment measured again

    @property
    def size(self) -> int:
        return len(self.conditions)


def parse_vary(text: str | None, study: Study) -> dict:
    """`KEY=LO:HI[:N],KEY=...` → {key: values}; LO:HI without N: 5 values. `InputError`
    (exit 2) naming `--vary` for bad syntax, unknown keys and implausible values."""
    if text is None or not str(text).strip():
        return {}
    allowed = TIMED_KEYS if timed(study.config) else CRANK_KEYS
    out: dict = {}
    # split on commas that start a new KEY= (a value list A,B,C stays whole)
    items, cur = [], ""
    for part in str(text).split(","):
        if "=" in part or not cur:
            if cur:
                items.append(cur)
            cur = part
        else:
            cur += "," + part
    if cur:
        items.append(cur)
    for item in items:
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq or not key or not val.strip():
            raise InputError(f"--vary {item!r}: expected KEY=LO:HI[:N] (e.g. "
                             f"speed_rpm=100:300:5)")
        if key not in allowed:
            raise InputError(f"--vary: unknown key {key!r} for this study; expected one of "
                             f"{', '.join(allowed)}")
        v = val.strip()
        if v.count(":") == 1:
            v += ":5"
        vals = parse_range(f"--vary {key}", v)
        if key in out:
            raise InputError(f"--vary: {key} given twice")
        where = f"--vary {key}"
        rng_key = ("experiment." + key) if key in ("revolutions", "hours") else key
        for x in (float(np.min(vals)), float(np.max(vals))):
            check_value(where, rng_key, x, preset=study.preset, name=where)
        if key == "clearance_mm":
            radius_mm = float(study.params().bore_radius) * 1e3
            if np.max(vals) >= radius_mm:
                raise InputError(f"--vary clearance_mm: values must be below the bore radius "
                                 f"{radius_mm:g} mm")
        if key in ("revolutions", "hours", "speed_rpm", "load_scale") and np.min(vals) <= 0:
            raise InputError(f"--vary {key}: values must be > 0")
        out[key] = np.unique(vals)
    return out


def default_vary(study: Study, after: float | None = None) -> dict:
    """The default candidate ranges: around the study's own conditions, inside the
    plausibility table. Crank-slider: speed 0.5-1.5x the studied speeds (5 values),
    clearance 0.5-1.5x the studied clearances (5), revolutions 0.25-2x the longest run (8):
    200 candidates in 25 runs. Timed: hours from the last measurement (`after`) to twice it,
    20 values."""
    if timed(study.config):
        last = after if after is not None else max(
            max(e.snapshot_points or [e.hours or 0.0]) for e in study.experiments)
        last = max(float(last), 1e-3)
        return {"hours": np.linspace(last * 1.05, 2.0 * last, 20)}
    plist = [study.params(e) for e in study.experiments]
    speeds = [float(p.get("speed_rpm")) / key_to_si("speed_rpm") for p in plist]
    clear = [float(p.clearance) * 1e3 for p in plist]
    revs = max(float(e.revolutions or 1.0) for e in study.experiments)
    return {"speed_rpm": np.linspace(0.5 * min(speeds), 1.5 * max(speeds), 5),
            "clearance_mm": np.linspace(0.5 * min(clear), 1.5 * max(clear), 5),
            "revolutions": np.round(np.linspace(0.25 * revs, 2.0 * revs, 8))}


def measure_points(revolutions: float) -> list[float]:
    """Where a new crank-slider specimen is scanned: synth's interruptions below its end,
    and the end (so that `jaxwear synth --conditions` makes the same measurements)."""
    pts = [r for r in INTERRUPTIONS if r < revolutions - 1e-9]
    if not pts:  # short tests: interrupt at 20 % and 50 % of the run
        pts = [round(0.2 * revolutions), round(0.5 * revolutions)]
    return sorted(set(pts + [float(revolutions)]))


def plan_candidates(study: Study, vary: dict, *, experiment: int = 0) -> Plan:
    """The candidate set of `vary` (`parse_vary`/`default_vary`) for `study`."""
    if timed(study.config):
        hours = np.asarray(vary.get("hours", default_vary(study)["hours"]), float)
        e = study.experiments[experiment]
        pts = sorted(set(hours.tolist()))
        conds = [{"hours": float(h)} for h in hours]
        return Plan(keys=("hours",), conditions=conds, measure_at=[[float(h)] for h in hours],
                    run=np.zeros(len(hours), int), snaps=[[pts.index(float(h))] for h in hours],
                    runs=[e], points=[pts], unit="hours", continuation=e.name)
    vary = dict(vary)
    base = dict(default_vary(study)) if not vary else {}
    grid = {**base, **vary}
    if "revolutions" not in grid:
        grid["revolutions"] = np.array([max(float(e.revolutions or 1.0)
                                            for e in study.experiments)])
    cond_keys = [k for k in grid if k != "revolutions"]
    template = study.experiments[experiment]
    runs, points, conds, measure, run_idx, snaps = [], [], [], [], [], []
    durations = sorted(float(r) for r in grid["revolutions"])
    for combo in itertools.product(*(grid[k] for k in cond_keys)):
        over = dict(template.overrides)
        over.update({k: float(v) for k, v in zip(cond_keys, combo)})
        pts = sorted(set(itertools.chain.from_iterable(measure_points(r) for r in durations)))
        name = "cand-" + "-".join(f"{k}{float(v):g}" for k, v in zip(cond_keys, combo))
        runs.append(Experiment(name, over, revolutions=max(durations)))
        points.append(pts)
        for r in durations:
            m = measure_points(r)
            conds.append({**{k: float(v) for k, v in zip(cond_keys, combo)},
                          "revolutions": float(r)})
            measure.append(m)
            run_idx.append(len(runs) - 1)
            snaps.append([pts.index(x) for x in m])
    return Plan(keys=tuple(cond_keys) + ("revolutions",), conditions=conds,
                measure_at=measure, run=np.asarray(run_idx), snaps=snaps, runs=runs,
                points=points, unit="revolutions")


def _placeholder(e: Experiment, pts: list[float], is_timed: bool) -> Experiment:
    """`e` with zero data at `pts`: its run's snapshots (the rows are never compared)."""
    pts = [float(x) for x in pts]
    if is_timed:
        return dataclasses.replace(e, profile=None, hours=max(pts),
                                   history=History(np.array(pts), np.zeros(len(pts)), ""))
    return dataclasses.replace(e, history=None, revolutions=max(pts), profile=Profile(
        np.zeros(len(pts)), np.zeros(len(pts)), np.array(pts), ""))


# ------------------------------------------------------------------ the batched Jacobian


@eqx.filter_jit
def _candidate_jit(model, v):
    """Snapshots (runs, S, N) [µm] and their Jacobian (runs, S, N, P + 1) in (u, δ): δ [mm]
    a shift of every run's clearance; the integration's worst error estimate [µm] and the
    worn-through flag. One compiled call: `model.snapshots` maps over the runs."""

    def g(w):
        p = model.params
        m = dataclasses.replace(model, params=p.replace(clearance=p.clearance + w[-1] * 1e-3))
        snaps, res = m.snapshots(w[:-1])
        return snaps, (snaps, jnp.max(res.error_estimate) * 1e6,
                       jnp.max(res.worn_through_cycle))

    return jax.jacfwd(g, has_aux=True)(v)


@dataclass(frozen=True)
class Runs:
    """The candidate runs of one model at its fitted values: `snaps` (R, S, N) [µm],
    `J` (R, S, N, P) with respect to the study's packed shared parameters (u of the fit),
    `J_clear` (R, S, N) [µm/mm] to the run's own clearance; `names` the P parameters;
    `seconds` the wall time of the batched call (compilation included)."""

    snaps: np.ndarray
    J: np.ndarray
    J_clear: np.ndarray
    names: tuple
    seconds: float
    error_um: float


def shared_keys(keys: list[str]) -> list[str]:
    return [k for k in keys if k not in NUISANCE]


def run_candidates(study: Study, result: FitResult, keys: list[str], runs: list,
                   points: list, *, is_timed: bool) -> Runs:
    """Every candidate run of `runs` (experiments, measured at `points`) in the fitted
    model of `result`, as one batched Jacobian (`_candidate_jit`)."""
    skeys = shared_keys(keys)
    fitted = dict(zip(result.names, map(float, result.values)))
    cfg = result.problem.cfg
    cand = dataclasses.replace(
        study.with_experiments([_placeholder(e, p, is_timed) for e, p in zip(runs, points)]),
        auto_resolution=False)
    cand = cand.with_config(nodes=cfg.nodes, steps_per_rev=cfg.steps_per_rev)
    start = {k: fitted[k] for k in skeys if k in fitted}
    model = build_model(cand, skeys, start)
    u0 = np.zeros(model.packing.size)
    model = enough_attempts(model, u0)
    t0 = time.perf_counter()
    v = jnp.zeros(model.packing.size + 1)
    for _ in range(4):  # the attempt count is an estimate: double it where it ran short
        (Js, (snaps, err, worn)) = _candidate_jit(
            model.with_schedule(model.schedule.with_dynamic_attempts()), v)
        if not (model.schedule.adaptive and not np.isfinite(float(err))):
            break
        model = model.with_schedule(model.schedule.more_attempts())
    Js, snaps = np.asarray(Js), np.asarray(snaps)
    seconds = time.perf_counter() - t0
    if not np.isfinite(float(err)) or not np.all(np.isfinite(Js)):
        raise InputError("design: a candidate run did not complete (integration or contact "
                         "failed); narrow --vary")
    if float(worn) >= 0:
        raise InputError("design: a candidate wears through the layer; narrow --vary "
                         "(shorter runs or lower speeds)")
    # candidate u (start = fitted values, u = 0) → the fit's u of the same parameters
    names = tuple(model.packing.names)
    idx = [result.names.index(n) for n in names]
    Gc = model.packing.value_jacobian(u0)
    Gs = result.problem.packing.value_jacobian(result.u)[np.ix_(idx, idx)]
    T = np.linalg.solve(Gc, Gs)  # dv/du_c^-1 dv/du_s
    J = np.einsum("rsnp,pq->rsnq", Js[..., :-1], T)
    return Runs(snaps=snaps, J=J, J_clear=Js[..., -1], names=names, seconds=seconds,
                error_um=float(err))


# ------------------------------------------------------------------ information


def scan_metric(nodes: int, step_deg: float) -> np.ndarray:
    """W^T W (N, N): the rows of one scan every `step_deg` degrees, read from the nodes by
    periodic linear interpolation (as the residual model reads a profile)."""
    ang = np.arange(0.0, 360.0, step_deg)
    x = np.mod(ang / 360.0 * nodes, nodes)
    i0 = np.floor(x).astype(int) % nodes
    w = x - np.floor(x)
    W = np.zeros((len(ang), nodes))
    np.add.at(W, (np.arange(len(ang)), i0), 1 - w)
    np.add.at(W, (np.arange(len(ang)), (i0 + 1) % nodes), w)
    return W.T @ W


def scan_step_deg(study: Study) -> float:
    """The study's scan spacing (median of its first profile's angle steps), else 2°."""
    for e in study.experiments:
        if e.profile is not None and len(e.profile.angle) > 2:
            a = np.unique(np.round(np.degrees(np.asarray(e.profile.angle)), 9))
            d = np.diff(a)
            if d.size and np.median(d) > 0:
                return float(np.median(d))
    return DEFAULT_SCAN_STEP_DEG


def row_blocks(runs: Runs, metric: np.ndarray | None) -> np.ndarray:
    """Per (run, snapshot), the rows' information blocks Z^T M Z (R, S, q, q), Z = [J,
    J_clear]: profile scans with `metric` M = W^T W; depth histories (None) the row of
    the node at the maximum."""
    Z = np.concatenate([runs.J, runs.J_clear[..., None]], axis=-1)
    if metric is None:  # a history row: the maximum over the nodes
        k = np.argmax(runs.snaps, axis=-1)  # (R, S)
        z = np.take_along_axis(Z, k[..., None, None], axis=2)[:, :, 0]  # (R, S, q)
        return np.einsum("rsp,rsq->rspq", z, z)
    return np.einsum("rsnp,nm,rsmq->rspq", Z, metric, Z)


def _marginal(Iq: np.ndarray, P: int, clear_prec: float | None) -> np.ndarray:
    """Information (..., q, q) over [θ (P), δ] → over θ: the candidate's own clearance δ a
    nuisance with prior precision `clear_prec` (None: held at nominal)."""
    A = Iq[..., :P, :P]
    if clear_prec is None:
        return A
    b = Iq[..., :P, P]
    d = Iq[..., P, P] + clear_prec
    return A - b[..., :, None] * b[..., None, :] / d[..., None, None]


def _clear_prec(study: Study) -> float | None:
    tol = float(study.clearance_tolerance_um)
    if tol == 0:
        return None  # clearances held at nominal
    return 0.0 if math.isinf(tol) else 1.0 / (tol * 1e-3) ** 2


def _logdet(M) -> np.ndarray:
    sign, ld = np.linalg.slogdet(M)
    return np.where(sign > 0, ld, -np.inf)


# ------------------------------------------------------------------ results


@dataclass(frozen=True)
class DesignResult:
    """Candidates ranked for a goal. `order`: candidate indices best first; `values` (C,)
    the goal's value (`better`: "higher" or "lower"); `recommended`: the greedy set of
    `budget` (indices) with the cumulative value after each pick (`recommended_values`);
    `baseline`: the value of the study as it is (no candidate; None for `separate`);
    `details`: per candidate extra numbers (dicts); `timing`: seconds by phase."""

    goal: str
    between: list
    plan: Plan
    values: np.ndarray
    better: str
    order: np.ndarray
    recommended: list
    recommended_values: list
    baseline: float | None
    details: list
    timing: dict
    info: dict

    def conditions(self, i: int) -> dict:
        return dict(self.plan.conditions[i])


def _rank(values: np.ndarray, better: str) -> np.ndarray:
    v = np.where(np.isfinite(values), values, -np.inf if better == "higher" else np.inf)
    return np.argsort(-v if better == "higher" else v, kind="stable")


def _fit(study, keys, verbose, what, flags):
    """The fit of `study` (the fit driver) and the study it was fitted as: with the paper
    integrator (eq 23) above its stable amplification at the fitted K_d, refitted at a
    stable M as `predict` does (the Jacobian, hence every candidate's information, blows up
    there: measured on the boom at M = 10, derivatives of 1e9 µm per unit)."""
    _log(verbose, f"design: fitting {what} ({', '.join(keys)})")
    try:
        result = fit_study(study, keys, verbose=False)
        stable, flag = at_stable_update(
            study, dict(zip(result.names, map(float, result.values))),
            done="fitted and designed", at=f"the fitted K_d of {what}")
        if flag is not None:
            flags.append(flag)
            _log(verbose, f"design: {flags[-1]}")
        if stable is not study:
            study = stable
            result = fit_study(study, keys, verbose=False)
    except InputError:
        raise
    except Exception as e:  # the fit itself failed: nothing to rank from
        raise RuntimeError(f"design: the fit of {what} failed: {e}") from e
    return study, result


def _forecast_runs(study: Study, result: FitResult, at: float, plan: Plan):
    """The forecast target as an extra run (crank: the first experiment at its fitted
    clearance, to `at`) or an extra snapshot of the continued run (timed)."""
    e = study.experiments[0]
    if plan.continuation is not None:
        pts = sorted(set(plan.points[0] + [float(at)]))
        snaps = [[pts.index(x) for x in (plan.measure_at[i])] for i in range(plan.size)]
        plan = dataclasses.replace(plan, points=[pts], snaps=snaps)
        return plan, (0, pts.index(float(at)))
    fitted = dict(zip(result.names, map(float, result.values)))
    over = dict(e.overrides)
    c = fitted.get(f"clearance_mm/{e.name}")
    if c is not None:
        over["clearance_mm"] = c
    target = Experiment(e.name + "-forecast", over, revolutions=float(at))
    plan = dataclasses.replace(plan, runs=plan.runs + [target],
                               points=plan.points + [[float(at)]])
    return plan, (len(plan.runs) - 1, 0)


def design(study: Study, *, goal: str = "parameters", between=None, vary=None,
           budget: int = 1, for_keys=None, at: float | None = None,
           train_until: float | None = None, level: float = 0.9,
           verbose: bool = False) -> DesignResult:
    """Rank candidate next experiments of `study` for `goal` (module docstring).

    **Arguments:**
    - `goal`: "parameters", "forecast" or "separate".
    - `between`: for "separate", two explanations: effect names (registered effects) or
      "base" (the study's model as written).
    - `vary`: {key: values} (`parse_vary`), None or {}: `default_vary`.
    - `budget`: experiments in the recommended set (greedy).
    - `for_keys`: for "parameters", the parameters whose standard errors count (study keys,
      e.g. ["K_d_per_Pa"]); None: D-optimal.
    - `at`: for "forecast", the point (revolutions or hours) of the forecast maximum depth
      (default: twice the last measured point of the first experiment; with `train_until`,
      that experiment's own length).
    - `train_until`: use only the measurements at or before it (as `predict`).
    - `level`: the forecast band's level.

    **Returns:** a `DesignResult`.
    """
    t_start = time.perf_counter()
    if goal not in GOALS:
        raise InputError(f"--goal: expected one of {', '.join(GOALS)}, got {goal!r}")
    if int(budget) < 1:
        raise InputError(f"--budget: expected a whole number >= 1, got {budget}")
    study = training_study(study, train_until)
    is_timed = timed(study.config)
    plan = plan_candidates(study, vary or {})
    if budget > plan.size:
        raise InputError(f"--budget {budget}: only {plan.size} candidates; vary more values")
    keys = study_fit_keys(study)
    between = list(between or [])
    if goal == "separate":
        between = check_between(study, between)
    elif between:
        raise InputError("--between: only with --goal separate")
    if goal == "forecast" and at is None:
        e0 = study.experiments[0]
        last = max(e0.snapshot_points or [e0.hours or e0.revolutions or 1.0])
        at = float((e0.hours or e0.revolutions) if train_until is not None else 2.0 * last)
    tangents = len(shared_keys(keys)) + 1
    cand_study = study.with_experiments(
        [_placeholder(e, p, is_timed) for e, p in zip(plan.runs, plan.points)])
    est = estimate_work(cand_study, tangents=tangents).seconds + COMPILE_ALLOWANCE_S
    n_models = 2 if goal == "separate" else 1
    _log(verbose, f"design: {plan.size} candidates in {len(plan.runs)} batched run(s) "
                  f"(varying {', '.join(plan.keys)}); estimated {n_models * est:.0f} s for "
                  f"the candidates after {n_models} fit(s) of the study")
    timing = {}
    if goal == "separate":
        res = _separate(study, plan, between, budget, verbose, timing)
    else:
        t0 = time.perf_counter()
        flags: list = []
        study, result = _fit(study, keys, verbose, "the study", flags)
        timing["fit_s"] = time.perf_counter() - t0
        target = None
        if goal == "forecast":
            plan, target = _forecast_runs(study, result, at, plan)
        res = _one_model(study, result, keys, plan, goal, budget, for_keys, target, level,
                         verbose, timing)
        res.info["flags"] = flags
    timing["total_s"] = time.perf_counter() - t_start
    timing["estimate_s"] = n_models * est
    return dataclasses.replace(res, timing=timing)


# ------------------------------------------------------------------ one fitted model


def _full_information(result: FitResult) -> tuple[np.ndarray, float]:
    """The study's information over every fitted u (data rows at the fit's error scale,
    prior rows) and that scale [µm]."""
    ev = result.evaluation
    s = float(result.error_scale_um) if math.isfinite(result.error_scale_um) else float(
        result.noise_um)
    return ev.J.T @ ev.J / s ** 2 + ev.J_prior.T @ ev.J_prior, s


def _embed(result: FitResult, runs: Runs, plan: Plan, A: np.ndarray, sigma: float,
           clear_prec) -> np.ndarray:
    """(C, P_full, P_full): each candidate's information in the study's full u. A new
    specimen's own clearance is marginalised (prior precision `clear_prec`); the next
    measurement of an existing experiment (timed) shares that experiment's fitted
    clearance column."""
    names = list(result.names)
    P_full = len(names)
    P = len(runs.names)
    idx = [names.index(n) for n in runs.names]
    G = result.problem.packing.value_jacobian(result.u)
    out = np.zeros((plan.size, P_full, P_full))
    col = None
    if plan.continuation is not None:
        col = names.index(f"clearance_mm/{plan.continuation}") if (
            f"clearance_mm/{plan.continuation}" in names) else None
    for i in range(plan.size):
        Iq = A[plan.run[i], plan.snaps[i]].sum(axis=0)[:P + 1, :P + 1] / sigma ** 2
        if plan.continuation is None:
            out[i][np.ix_(idx, idx)] = _marginal(Iq, P, clear_prec)
        elif col is None:
            out[i][np.ix_(idx, idx)] = Iq[:P, :P]
        else:
            g = G[col, col]  # d clearance [mm] / d u of its column
            T = np.zeros((P + 1, P_full))
            T[np.arange(P), idx] = 1.0
            T[P, col] = g
            out[i] = T.T @ Iq @ T
    return out


def _forecast_gradient(result: FitResult, runs: Runs, target, plan: Plan,
                       study: Study) -> np.ndarray:
    """d (forecast maximum depth) / d u (P_full,) [µm]: the shared parameters, and the
    target experiment's own fitted clearance."""
    names = list(result.names)
    r, s = target
    k = int(np.argmax(runs.snaps[r, s]))
    g = np.zeros(len(names))
    g[[names.index(n) for n in runs.names]] = runs.J[r, s, k]
    exp = plan.continuation or study.experiments[0].name
    col = f"clearance_mm/{exp}"
    if col in names:
        i = names.index(col)
        g[i] = runs.J_clear[r, s, k] * result.problem.packing.value_jacobian(result.u)[i, i]
    return g


def _goal_value(goal, info, shared_idx, for_idx, G, values, g, z):
    """The goal's value of information matrices I (..., P_full, P_full) (module
    docstring); and per-parameter standard errors (..., len(shared)) in value units."""
    cov = np.linalg.inv(info)
    Gs = G[np.ix_(shared_idx, shared_idx)]
    cs = cov[..., shared_idx, :][..., :, shared_idx]
    cov_v = Gs @ cs @ Gs.T
    se = np.sqrt(np.clip(np.diagonal(cov_v, axis1=-2, axis2=-1), 0, None))
    if goal == "forecast":
        return z * np.sqrt(np.clip(np.einsum("p,...pq,q->...", g, cov, g), 0, None)), se
    if for_idx:
        rel = se[..., for_idx] / np.abs(values[for_idx])
        return 100.0 * np.sqrt(np.mean(rel ** 2, axis=-1)), se
    return -_logdet(cs), se


def _greedy(value_of, I0, Ic, better, budget):
    """Greedy best set: each pick's information added before the next; returns the picks
    and the value after each."""
    picks, vals, cur = [], [], I0.copy()
    for _ in range(budget):
        v = value_of(cur[None] + Ic)
        if picks:
            v = np.asarray(v, float).copy()
            v[picks] = -np.inf if better == "higher" else np.inf
        best = int(_rank(v, better)[0])
        picks.append(best)
        vals.append(float(v[best]))
        cur = cur + Ic[best]
    return picks, vals


def _one_model(study, result, keys, plan, goal, budget, for_keys, target, level, verbose,
               timing) -> DesignResult:
    is_timed = plan.unit == "hours"
    _log(verbose, f"design: fit done ({timing['fit_s']:.1f} s, RMSE {result.rmse_um:.3g} µm); "
                  f"running {len(plan.runs)} candidate run(s) with their Jacobian")
    runs = run_candidates(study, result, keys, plan.runs, plan.points, is_timed=is_timed)
    timing["candidates_s"] = runs.seconds
    metric = None if is_timed else scan_metric(result.problem.cfg.nodes, scan_step_deg(study))
    A = row_blocks(runs, metric)
    I_full, sigma = _full_information(result)
    Ic = _embed(result, runs, plan, A, sigma, None if is_timed else _clear_prec(study))
    names = list(result.names)
    shared_idx = [names.index(n) for n in runs.names]
    values = np.asarray(result.values, float)[shared_idx]
    for_idx = []
    if for_keys:
        for k in for_keys:
            if k not in runs.names:
                raise InputError(f"--for: {k!r} is not a fitted shared parameter of the study; "
                                 f"expected one of {', '.join(runs.names)}")
            for_idx.append(list(runs.names).index(k))
    G = result.problem.packing.value_jacobian(result.u)
    g = _forecast_gradient(result, runs, target, plan, study) if goal == "forecast" else None
    z = NormalDist().inv_cdf(0.5 + level / 2)
    better = "higher" if goal == "parameters" and not for_idx else "lower"

    def value_of(info):
        return _goal_value(goal, info, shared_idx, for_idx, G, values, g, z)[0]

    vals, se = _goal_value(goal, I_full[None] + Ic, shared_idx, for_idx, G, values, g, z)
    base = float(value_of(I_full[None])[0])
    picks, pick_vals = _greedy(value_of, I_full, Ic, better, budget)
    details = []
    for i in range(plan.size):
        r, s_last = plan.run[i], plan.snaps[i][-1]
        d = {"peak_depth_um": float(np.max(runs.snaps[r, s_last])),
             "stderr": {n: float(x) for n, x in zip(runs.names, se[i])}}
        if goal == "forecast":
            d["half_width_um"] = float(vals[i])
        details.append(d)
    info = {"fit": {"rmse_um": float(result.rmse_um), "noise_um": float(result.noise_um),
                    "error_scale_um": sigma,
                    "parameters": {n: {"value": float(v), "stderr": float(s)}
                                   for n, v, s in zip(result.names, result.values,
                                                      result.stderr)}},
            "resolution": {"nodes": result.problem.cfg.nodes,
                           "steps_per_rev": result.problem.cfg.steps_per_rev},
            "criterion": ("log det of the shared parameters' information" if goal ==
                          "parameters" and not for_idx else
                          f"rms relative standard error [%] of {', '.join(for_keys)}"
                          if for_idx else
                          f"half-width [µm] of the {level:g} band (parameter part) of the "
                          f"maximum depth at {target_label(plan, target, study)}"),
            "for": list(for_keys or [])}
    if goal == "forecast":
        info["at"] = target_label(plan, target, study)
    return DesignResult(goal=goal, between=[], plan=plan, values=np.asarray(vals, float),
                        better=better, order=_rank(np.asarray(vals, float), better),
                        recommended=picks, recommended_values=pick_vals, baseline=base,
                        details=details, timing=timing, info=info)


def target_label(plan: Plan, target, study: Study) -> str:
    r, s = target
    at = plan.points[r][s]
    exp = plan.continuation or study.experiments[0].name
    return f"{at:g} {plan.unit} of {exp}"


# ------------------------------------------------------------------ two rival models


def check_between(study: Study, between: list) -> list:
    """Two distinct explanations: "base" (the study as written) or registered effects not
    yet switched on. `InputError` naming --between otherwise."""
    known = list(registered_effects())
    if len(between) != 2 or between[0] == between[1]:
        raise InputError(f"--between: expected two different explanations A,B (effects such "
                         f"as {', '.join(known[:3])}, or base), got {','.join(between) or '-'}")
    for b in between:
        if b != "base" and b not in known:
            raise InputError(f"--between: unknown explanation {b!r}; expected base or one of "
                             f"{', '.join(known)}")
        if b in study.config.effects:
            raise InputError(f"--between: {b} is already switched on in the study; name "
                             f"effects it lacks (or base)")
    return list(between)


def model_study(study: Study, name: str) -> Study:
    """The study with the explanation `name` switched on ("base": as written)."""
    if name == "base":
        return study
    return study.with_config(effects=tuple(study.config.effects) + (name,))


def _chi2(dd, b, UtU, a):
    """d^T (a I + U U^T)^-1 d by Woodbury, from d·d, U^T d, U^T U (batched)."""
    q = UtU.shape[-1]
    x = np.linalg.solve(a[..., None, None] * np.eye(q) + UtU, b[..., None])[..., 0]
    return (dd - np.einsum("...q,...q->...", b, x)) / a


def _separate(study, plan, between, budget, verbose, timing) -> DesignResult:
    is_timed = plan.unit == "hours"
    fits, runs, keys_of, studies, flags = [], [], [], [], []
    t0 = time.perf_counter()
    for name in between:
        st = model_study(study, name)
        keys = study_fit_keys(st)
        st, f = _fit(st, keys, verbose, f"explanation {name}", flags)
        fits.append(f)
        studies.append(st)
        keys_of.append(keys)
    timing["fit_s"] = time.perf_counter() - t0
    _log(verbose, f"design: fits done ({timing['fit_s']:.1f} s; RMSE "
                  + ", ".join(f"{n} {f.rmse_um:.3g} µm" for n, f in zip(between, fits))
                  + f"); running {len(plan.runs)} candidate run(s) per explanation")
    timing["candidates_s"] = 0.0
    for st, f, keys in zip(studies, fits, keys_of):
        r = run_candidates(st, f, keys, plan.runs, plan.points, is_timed=is_timed)
        timing["candidates_s"] += r.seconds
        runs.append(r)
    sigma = min(float(f.noise_um) for f in fits)
    metric = None if is_timed else scan_metric(fits[0].problem.cfg.nodes, scan_step_deg(study))
    ra, rb = runs
    PA, PB = len(ra.names), len(rb.names)
    # columns: J_A (PA), J_B (PB), the common clearance's difference, the difference d
    Z = np.concatenate([ra.J, rb.J, (ra.J_clear - rb.J_clear)[..., None],
                        (ra.snaps - rb.snaps)[..., None]], axis=-1)
    if metric is None:
        k = np.argmax(ra.snaps, axis=-1)
        z = np.take_along_axis(Z, k[..., None, None], axis=2)[:, :, 0]
        z[..., -1] = ra.snaps.max(-1) - rb.snaps.max(-1)
        K = np.einsum("rsp,rsq->rspq", z, z)
    else:
        K = np.einsum("rsnp,nm,rsmq->rspq", Z, metric, Z)
    Kc = np.stack([K[plan.run[i], plan.snaps[i]].sum(axis=0) for i in range(plan.size)])
    tau2 = 0.0
    if not is_timed and _clear_prec(study):
        tau2 = 1.0 / _clear_prec(study)
    # each model's own information of a candidate (for the greedy update): its J and δ
    infos = []
    for m, (f, r) in enumerate(zip(fits, runs)):
        A = row_blocks(r, metric)
        infos.append(_embed(f, r, plan, A, sigma, None if is_timed else _clear_prec(study)))
    I_cur = [_full_information(f)[0] for f in fits]

    def shared_chol(f, r, info):
        names = list(f.names)
        idx = [names.index(n) for n in r.names]
        cov = np.linalg.inv(info)[np.ix_(idx, idx)]
        w, V = np.linalg.eigh(0.5 * (cov + cov.T))
        return V * np.sqrt(np.clip(w, 0, None))  # L with L L^T = cov

    def chi2_all(n_scans=1.0):
        LA = shared_chol(fits[0], ra, I_cur[0])
        LB = shared_chol(fits[1], rb, I_cur[1])
        q = PA + PB + 1
        Bm = np.zeros((q, q))
        Bm[:PA, :PA] = LA
        Bm[PA:PA + PB, PA:PA + PB] = LB
        Bm[-1, -1] = math.sqrt(tau2)
        UtU = np.einsum("pi,cpq,qj->cij", Bm, Kc[:, :q, :q], Bm)
        b = np.einsum("pi,cp->ci", Bm, Kc[:, :q, q])
        dd = Kc[:, q, q]
        a = np.full(plan.size, sigma ** 2 / n_scans)
        return _chi2(dd, b, UtU, a), (dd, b, UtU)

    values, parts = chi2_all()
    order = _rank(values, "higher")
    scans = _scans_needed(parts, sigma)
    picks, pick_vals, total = [], [], 0.0
    for _ in range(budget):
        v, _p = chi2_all()
        v = v.copy()
        v[picks] = -np.inf
        best = int(_rank(v, "higher")[0])
        picks.append(best)
        total += float(v[best])
        pick_vals.append(total)
        I_cur = [I_cur[m] + infos[m][best] for m in range(2)]
    details = []
    for i in range(plan.size):
        r, s_last = plan.run[i], plan.snaps[i][-1]
        diff = ra.snaps[r, s_last] - rb.snaps[r, s_last]
        details.append({"max_difference_um": float(np.max(np.abs(diff))),
                        "peak_depth_um": {between[0]: float(ra.snaps[r, s_last].max()),
                                          between[1]: float(rb.snaps[r, s_last].max())},
                        "scans_needed": scans[i]})
    now = (fits[1].rss - fits[0].rss) / sigma ** 2
    info = {"fits": {n: {"rmse_um": float(f.rmse_um), "noise_um": float(f.noise_um),
                         "parameters": f.parameters_json()} for n, f in zip(between, fits)},
            "noise_um": sigma, "chi2_between_now": float(now),
            "criterion": "expected chi-square of the difference of the two explanations' "
                         "predicted rows, against the noise and both models' parameter "
                         "uncertainty (one scan set)",
            "separate_chi2": SEPARATE_CHI2, "flags": flags,
            "resolution": {"nodes": fits[0].problem.cfg.nodes,
                           "steps_per_rev": fits[0].problem.cfg.steps_per_rev}}
    return DesignResult(goal="separate", between=list(between), plan=plan,
                        values=np.asarray(values, float), better="higher", order=order,
                        recommended=picks, recommended_values=pick_vals, baseline=None,
                        details=details, timing=timing, info=info)


def _scans_needed(parts, sigma) -> list:
    """Per candidate, the fewest repeated scan sets n (noise σ²/n, the parameters'
    uncertainty unchanged) whose expected chi-square reaches `SEPARATE_CHI2`; None where
    even `MAX_SCANS` do not (the models' parameter uncertainty covers the difference)."""
    dd, b, UtU = parts
    out = [None] * len(dd)
    need = np.full(len(dd), -1)
    for n in range(1, MAX_SCANS + 1):
        c = _chi2(dd, b, UtU, np.full(len(dd), sigma ** 2 / n))
        hit = (need < 0) & (c >= SEPARATE_CHI2)
        need[hit] = n
        if (need > 0).all():
            break
    for i, n in enumerate(need):
        out[i] = int(n) if n > 0 else None
    return out
