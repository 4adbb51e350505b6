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
import math
import time
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from jaxwear._analyses.design.information import (
    SEPARATE_CHI2,
    _chi2,
    _clear_prec,
    _embed,
    _forecast_gradient,
    _full_information,
    _goal_value,
    _greedy,
    _rank,
    _scans_needed,
)
from jaxwear._analyses.design.plan import (
    COMPILE_ALLOWANCE_S,
    GOALS,
    Plan,
    _placeholder,
    plan_candidates,
)
from jaxwear._analyses.design.runs import (
    row_blocks,
    run_candidates,
    scan_metric,
    scan_step_deg,
    shared_keys,
)
from jaxwear._analyses.design.shape_rival import (
    beyond_flag,
    beyond_speeds,
    fit_shape,
    information_of,
    is_shape,
    parse_shape,
    shape_start,
)
from jaxwear._analyses.predict.grid import training_study
from jaxwear._core.errors import InputError, ModelFailure
from jaxwear._core.log import log as _log
from jaxwear._inference.calibrate import fit_study
from jaxwear._inference.packing import study_fit_keys
from jaxwear._inference.result import FitResult
from jaxwear._physics.config import timed
from jaxwear._physics.effects import registered_effects
from jaxwear._study.budget import estimate_work
from jaxwear._study.resolution import at_stable_update
from jaxwear._study.study import Experiment, Study

# ------------------------------------------------------------------ the candidates


# ------------------------------------------------------------------ the batched Jacobian


# ------------------------------------------------------------------ information


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
        raise ModelFailure(f"design: the fit of {what} failed: {e}") from e
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
        raise InputError(f"<<goal>>: expected one of {', '.join(GOALS)}, got {goal!r}")
    if int(budget) < 1:
        raise InputError(f"<<budget>>: expected a whole number >= 1, got {budget}")
    study = training_study(study, train_until)
    is_timed = timed(study.config)
    plan = plan_candidates(study, vary or {})
    if budget > plan.size:
        raise InputError(f"<<budget>> {budget}: only {plan.size} candidates; vary more values")
    keys = study_fit_keys(study)
    between = list(between or [])
    if goal == "separate":
        between = check_between(study, between)
    elif between:
        raise InputError("<<between>>: only with <<goal>> separate")
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
                raise InputError(f"<<for_keys>>: {k!r} is not a fitted shared parameter of the "
                                 f"study; "
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
    """Two distinct explanations: "base" (the study as written), registered effects not
    yet switched on, or variables of the shape (`shape:VARIABLE`, `shape:deposit:VARIABLE`:
    `shape_rival`). `InputError` naming --between otherwise."""
    known = list(registered_effects())
    if len(between) != 2 or between[0] == between[1]:
        raise InputError(f"<<between>>: expected two different explanations A,B (effects such "
                         f"as {', '.join(known[:3])}, base, or variables of the shape such as "
                         f"shape:pressure_MPa), got {','.join(between) or '-'}")
    for b in between:
        if is_shape(b):
            parse_shape(b)
            continue
        if b != "base" and b not in known:
            raise InputError(f"<<between>>: unknown explanation {b!r}; expected base, "
                             f"shape:VARIABLE or one of {', '.join(known)}")
        if b in study.config.effects:
            raise InputError(f"<<between>>: {b} is already switched on in the study; name "
                             f"effects it lacks (or base)")
    return list(between)


def model_study(study: Study, name: str) -> Study:
    """The study with the explanation `name` switched on ("base", or a variable of the
    shape whose correction `shape_rival` adds: as written)."""
    if name == "base" or is_shape(name):
        return study
    return study.with_config(effects=tuple(study.config.effects) + (name,))


def _separate(study, plan, between, budget, verbose, timing) -> DesignResult:
    is_timed = plan.unit == "hours"
    fits, runs, keys_of, studies, flags = [], [], [], [], []
    t0 = time.perf_counter()
    base = None
    for name in between:
        st = model_study(study, name)
        keys = study_fit_keys(st)
        if is_shape(name):
            # the study's fit, then the shape's correction along the variable on top
            if base is None:
                base = _fit(st, keys, verbose, "the study (the shape's rivals' base)", flags)
            st, f = base[0], fit_shape(base[0], base[1], name, verbose=verbose)
            flags += f.flags
        elif name == "base" and base is not None:
            st, f = base  # fitted already as a shape rival's base
        else:
            st, f = _fit(st, keys, verbose, f"explanation {name}", flags)
            if name == "base":
                base = (st, f)
        fits.append(f)
        studies.append(st)
        keys_of.append(keys)
    timing["fit_s"] = time.perf_counter() - t0
    _log(verbose, f"design: fits done ({timing['fit_s']:.1f} s; RMSE "
                  + ", ".join(f"{n} {f.rmse_um:.3g} µm" for n, f in zip(between, fits))
                  + f"); running {len(plan.runs)} candidate run(s) per explanation")
    timing["candidates_s"] = 0.0
    if fits[0].problem.cfg.nodes != fits[1].problem.cfg.nodes or (
            fits[0].problem.cfg.steps_per_rev != fits[1].problem.cfg.steps_per_rev):
        raise ModelFailure("design: the two explanations were fitted at different "
                           "resolutions; set [numerics] nodes and steps_per_rev in the study")
    for st, f, keys in zip(studies, fits, keys_of):
        r = run_candidates(st, f, keys, plan.runs, plan.points, is_timed=is_timed,
                           shape=getattr(f, "basis", None), shape_start=shape_start(f))
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
    I_cur = [information_of(f) for f in fits]

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
    beyond, span = beyond_speeds(study, plan)
    flag = beyond_flag(between, sum(beyond), plan.size, span)
    if flag is not None:
        flags.append(flag)
        _log(verbose, f"design: {flag}")
    details = []
    for i in range(plan.size):
        r, s_last = plan.run[i], plan.snaps[i][-1]
        diff = ra.snaps[r, s_last] - rb.snaps[r, s_last]
        details.append({"max_difference_um": float(np.max(np.abs(diff))),
                        "peak_depth_um": {between[0]: float(ra.snaps[r, s_last].max()),
                                          between[1]: float(rb.snaps[r, s_last].max())},
                        "scans_needed": scans[i]})
        if any(is_shape(b) for b in between):
            details[-1]["beyond_study_speeds"] = bool(beyond[i])
    now = (fits[1].rss - fits[0].rss) / sigma ** 2
    info = {"fits": {n: {"rmse_um": float(f.rmse_um), "noise_um": float(f.noise_um),
                         "parameters": f.parameters_json()} for n, f in zip(between, fits)},
            "noise_um": sigma, "chi2_between_now": float(now),
            "criterion": "expected chi-square of the difference of the two explanations' "
                         "predicted rows, against the noise and both models' parameter "
                         "uncertainty (one scan set)",
            "separate_chi2": SEPARATE_CHI2, "flags": flags,
            # the study's own fit, where a rival was fitted on top of it (base, shape:)
            "base_rmse_um": None if base is None else float(base[1].rmse_um),
            "resolution": {"nodes": fits[0].problem.cfg.nodes,
                           "steps_per_rev": fits[0].problem.cfg.steps_per_rev}}
    return DesignResult(goal="separate", between=list(between), plan=plan,
                        values=np.asarray(values, float), better="higher", order=order,
                        recommended=picks, recommended_values=pick_vals, baseline=None,
                        details=details, timing=timing, info=info)


