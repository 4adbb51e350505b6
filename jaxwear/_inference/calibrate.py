"""Calibration: least squares of measured minus predicted depth over a whole study (§6-7).

The study is posed as a residual model (`_residual.ResidualModel`, its parameter vector
packed by `_packing`) and solved by the one least-squares core (`_inference.lsq`); this module
drives it: the noise rule (`_noise.stated_noise`), the robust start, the guard against
trials that would make the integrator crawl, the integration error re-checked at the
answer, the resolution chosen by the error (design.md §6), and the result (`FitResult`, its
design.md §7 JSON).

Outcome semantics: a fit that stops without meeting its convergence test still returns its
result, with `status` ("stalled", "budget", "undetermined", "worn_through",
"contact_unresolved") and a `message` saying why; `converged` is `status == "converged"`.
Only a start that cannot be evaluated at all (worn through whatever K_d, or non-finite)
raises `FitError`, and a noise level the data cannot determine raises `InputError` before
any evaluation.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core import background
from jaxwear._core.errors import FitError, InputError
from jaxwear._core.host import to_device
from jaxwear._core.log import log as _log
from jaxwear._core.noise import stated_noise
from jaxwear._inference import lsq
from jaxwear._inference.attempts import attempts_needed, needs_more_attempts, work_failure
from jaxwear._inference.evaluation import (
    Evaluation,
    Forward,
    compile_forward,
    evaluate,
    forward_run,
    integration_report,
    unusable_point,
)
from jaxwear._inference.packing import parse_fit, study_fit_keys, unit_of, with_registration
from jaxwear._inference.residual import Layout, ResidualModel, build_model, traces, traces_since
from jaxwear._inference.result import FitResult, summarize
from jaxwear._study import resolution as res
from jaxwear._study.outside import parameter_flags
from jaxwear._study.resolution import amplification_warnings
from jaxwear._study.study import Study

__all__ = ["FitError", "FitResult", "build_problem", "calibrate", "fit",
           "fit_study", "parse_fit", "registered", "study_fit_keys", "unit_of",
           "with_registration"]


def build_problem(study: Study, keys: list[str], start: dict | None = None,
                  layout: Layout | None = None) -> ResidualModel:
    """The residual model of `study` fitting `keys` (`_residual.build_model`; `layout`:
    shared schedule capacities)."""
    return build_model(study, keys, start, layout=layout)


def registered(study: Study, result) -> Study:
    """`study` with every scan rotated by its fitted registration (`angle_offset_deg/EXP`
    of `result`) and the registration then held (`angle_tolerance_deg` 0): what diagnose
    compares its candidates at, after the base fit found the offsets."""

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


def check_noise_determined(problem: ResidualModel, noise_um: float | None, *, hint: str
                           ) -> None:
    """Refuse, before any evaluation, what is known then: a noise level neither given nor
    measurable from the data, which the residuals cannot determine either (no more data
    rows than fitted parameters; `hint` names how to give σ), and a per-experiment
    parameter that no measured row can see (an experiment without data, its clearance
    free of any prior)."""
    n, p = problem.n_data, problem.packing.size
    noise = stated_noise(problem.data, problem.noise_um if noise_um is None else noise_um)
    if noise.sigma_um is None and p and n <= p:
        raise InputError(f"the {n} data rows do not determine the noise level with {p} fitted "
                         f"parameters ({', '.join(problem.names)}); give the measurement "
                         f"noise with {hint} (or fit fewer parameters, or add data)")
    seen = set(np.asarray(problem.data.exp).tolist())
    blind = [c.name for c in problem.columns if c.experiment is not None
             and c.experiment not in seen and not c.has_prior]
    if blind:
        raise InputError(f"no measured row can see {', '.join(blind)}: the experiment has no "
                         f"profile or history; give its data, a finite [fit] "
                         f"clearance_tolerance_um, or leave it out of the fit")


def fit(problem: ResidualModel, u0=None, *, noise_um: float | None = None,
        max_evaluations: int = 30, verbose: bool = False, robust: bool = True,
        label: str = "fit", se_tol: float = lsq.SE_TOL, ev0: Evaluation | None = None,
        on_start=None, on_first=None) -> FitResult:
    """Least-squares fit through the one core (`_inference.lsq.solve`), then standard errors,
    correlations and flags.

    **Arguments:**
    - `u0`: start in the problem's parameterisation (default: the problem's start values).
    - `noise_um`: measurement noise σ [µm] if known; default: the study's `[fit]
      noise_um`, else the noise rule (`_noise.stated_noise`: the data's own estimate, or
      re-estimated from the residuals inside the loop).
    - `max_evaluations`: budget of the iteration (the robust start's evaluations come on
      top; all are counted in `iterations`).
    - `verbose`: one line per evaluation on stderr. `robust`: rescale K_d first.
    - `se_tol`: the stop, as a fraction of a standard error (`lsq.solve`).
    - `ev0`: the problem's evaluation at `u0` when known (no start evaluation, no robust
      start: a refit from an answer).
    - `on_start`: called with the problem once the checks made before any evaluation
      have passed (`fit_study` starts compiling the resolution check's program there);
      `on_first`: called after every model evaluation (`fit_study` opens its gates at the
      first).

    Raises `InputError` before any evaluation when σ is not given and the data rows do not
    outnumber the fitted parameters; `FitError` when no start can be evaluated.
    """
    given = problem.noise_um if noise_um is None else noise_um
    check_noise_determined(problem, given, hint="[fit] noise_um")
    noise = stated_noise(problem.data, given)
    if on_start is not None:
        on_start(problem)
    P = problem.packing.size
    u = np.zeros(P) if u0 is None else np.asarray(u0, np.float64)
    log = (lambda m: _log(True, m)) if verbose else None
    held = [problem]

    def run(v, doublings):
        ev, used = evaluate(held[0], v, doublings=doublings)
        if on_first is not None:
            on_first()
        if used.schedule.attempts > held[0].schedule.attempts:
            _log(verbose, f"    {label}: integration attempts raised {held[0].schedule.attempts}"
                          f" -> {used.schedule.attempts} for these values")
            held[0] = used  # the largest attempt count any evaluation needed is kept
        return ev.point()

    def model(v):
        # A trial that needs far more integration steps than the fit's current point (a
        # stiff corner: running-in over a millimetre, K_d 100x) is cut off unevaluated and
        # counts as a rejected step: the trust region then shrinks towards where the model
        # is affordable, and a fit that truly goes there gets there in steps (at most 4x
        # the cost each). A trial doubles the attempt count once at most.
        # A trial whose work estimate is not finite is not run at all (the core's progress
        # line names the cause).
        if not math.isfinite(attempts_needed(held[0], v)):
            return unusable_point(held[0], v, work_failure(held[0], v))
        if needs_more_attempts(held[0], v):
            return unusable_point(held[0], v, "cut off unevaluated: it needs over 4x the "
                                  "integration steps of the current point (a stiff corner)")
        return run(v, 1)

    def describe(v):
        return ", ".join(f"{n} = {x:.6g}" for n, x in
                         zip(problem.names, problem.packing.values_np(v)))

    k = next((i for i, c in enumerate(problem.columns) if c.key == "K_d_per_Pa"), None)
    if ev0 is not None:
        pt, evals0 = ev0.point(), 0
    elif robust and P:
        u, pt, evals0, why = lsq.robust_start(lambda v: run(v, 3), u, k,
                                              measured=problem.measured, log=log)
        if why:
            raise FitError(f"cannot start the fit: {why} "
                           f"{dict(zip(problem.names, problem.packing.values_np(u)))}")
    else:
        pt, evals0 = run(u, 3), 1
    lo, hi = problem.packing.bounds_u()
    _log(verbose, f"  fit: {P} parameters, {problem.n_data} data rows; noise "
                  + (f"{noise.sigma_um:.3g} µm ({noise.describe()})" if noise.sigma_um
                     else "estimated from the residuals"))
    out = lsq.solve(model, u, point0=pt, lower=lo, upper=hi, noise_um=noise.sigma_um,
                    noise_dof=noise.dof, max_evaluations=max_evaluations, label=label,
                    log=log, project=problem.packing.project, se_tol=se_tol,
                    describe=describe)
    return summarize(held[0], out, evals0 + out.evaluations, noise)


def calibrate(study: Study, fit_spec=None, *, start=None, verbose=False,
              max_evaluations: int = 30, noise_um: float | None = None) -> FitResult:
    """Fit a study's parameters to its data (design.md §7 `calibrate`).

    **Arguments:**
    - `study`: a loaded study with profile and/or history data.
    - `fit_spec`: comma-separated study keys (a string or a list), e.g. "K_d,clearance";
      None (default): the study's `[fit] parameters`, else "K_d,clearance", as the command
      line does. Strengths of the effects the study switches on are always added.
    - `start`: optional start values by output name (user units), e.g.
      `{"K_d_per_Pa": 1e-12, "clearance_mm/n276": 0.06}`.
    - `noise_um`: measurement noise σ [µm] if known (default: the study's `[fit] noise_um`,
      else the noise rule of `_noise`).
    - `max_evaluations`: the fit's budget of model evaluations.

    **Returns:** a `FitResult` (`.to_json()` gives the design.md §7 document).
    """
    keys = study_fit_keys(study, fit_spec)
    return fit_study(study, keys, start=start, noise_um=noise_um,
                     max_evaluations=max_evaluations, verbose=verbose)


def fit_study(study: Study, keys: list[str], *, start=None, noise_um: float | None = None,
              max_evaluations: int = 30, verbose: bool = False,
              se_tol: float = lsq.SE_TOL, layout: Layout | None = None,
              meanwhile=None) -> FitResult:
    """The whole fit of a study: build the problem, refuse what is known before any
    evaluation, fit, re-check the integration error at the answer and, where the study
    leaves the resolution to the error (design.md §6), fit at the coarsest level of
    `_resolution.LEVELS` and consult the finer levels by forward runs only
    (`correct_to_finer`): one Jacobian compilation per answer. `result.resolution` reports
    it, `result.iterations` counts every model evaluation (forward runs and checks
    included, `result.forward_runs` of them without a Jacobian) and `result.compiles` the
    compilations by kind. `layout`: shared schedule capacities (a forecast's).
    `meanwhile(result, level)`: called with the answer as it stands at `level` (nodes,
    steps per revolution) while the program of a finer level's check compiles, for work
    on that answer that the check may leave as it is (the command line draws its
    figures then: `correct_to_finer`)."""

    before = traces()
    noise_um = study.noise_um if noise_um is None else noise_um
    kw = dict(noise_um=noise_um, max_evaluations=max_evaluations, verbose=verbose,
              se_tol=se_tol)
    if not study.auto_resolution:
        result = _fit_at(study, keys, start, layout, **kw)
        result.resolution = res.given(study)
    else:
        # the check's forward program at the next level compiles while the coarse fit
        # runs (from when the fit has passed what it refuses before any evaluation: no
        # program compiled for an answer that is an input error), traced while the fit's
        # own Jacobian program compiles and compiled once that is done, with the
        # least-squares core's programs for this fit (`evaluation.Compiling` says why)
        compiling: dict = {}
        lowered = background.lowered("_evaluate_jit")
        compiled = threading.Event()  # the fit's first evaluation has returned

        def first():
            lowered.set()  # a program already compiled is not lowered again
            compiled.set()

        def start_compiling(problem):
            P = problem.packing.size
            rows = problem.n_data + len(problem.prior_rows(np.zeros(P))[0])
            ahead = (_level_builder(study, keys, start, layout, 2) if len(res.LEVELS) > 2
                     else None)
            compiling[1] = compile_forward(_level_builder(study, keys, start, layout, 1),
                                           trace_after=(lowered,), compile_after=(compiled,),
                                           core=(rows, P), ahead=ahead)

        try:
            result = _fit_at(res.at_level(study, res.LEVELS[0]), keys, start, layout,
                             on_start=start_compiling, on_first=first, **kw)
            result = correct_to_finer(study, keys, result, layout, compiling=compiling,
                                      meanwhile=meanwhile, **kw)
        finally:
            for c in compiling.values():  # one the answer did not use is not started
                c.cancel()
            background.forget(lowered)
            first()
    result.compiles = traces_since(before)
    result.outside = parameter_flags(result.names, result.values, study.preset)
    result.flags[:0] = [f for f in result.outside if f not in result.flags]  # first
    return result


MAX_CORRECTIONS = 4  # defect corrections towards one level before it is called unsettled


def _level_builder(study: Study, keys, start, layout, i: int):
    """The builder of `study`'s problem at `res.LEVELS[i]` (for `evaluation.compile_forward`)."""
    return lambda: build_problem(res.at_level(study, res.LEVELS[i]), keys, start,
                                 layout=layout)


def correct_to_finer(study: Study, keys, result: FitResult, layout: Layout | None = None,
                     compiling: dict | None = None, meanwhile=None, **fit_kw) -> FitResult:
    """`result` (a fit at the coarsest level) checked against the finer levels, and
    corrected to them where needed, by forward runs there only (design.md §6).

    At the answer û, one forward run at the next finer level gives its rows; the
    change those residuals make to the Gauss-Newton step with the fit's own Jacobian (the
    step from the coarse rows, what the fit's own stop left, subtracted), in standard
    errors, is the check (what a finer grid changes is mostly the residual, by the discretisation
    error; its change of the Jacobian moves the answer by that relative change times the
    residuals, in standard errors about the Jacobian's relative discretisation error,
    which this check does not see: docs/numerics.md, "Resolution chosen by the error"). Within
    `FIT_SE_TOL` (0.1): the answer stands, checked against that level. Else defect
    correction: the difference δ = rows_fine(û) − rows_coarse(û) is held as a fixed
    correction of the rows (`ResidualModel.defect_um`), the coarse model refitted from û
    with its Jacobian (no recompilation), δ recomputed at the new answer, until the finer
    level moves no parameter by 0.1 SE; the answer is then that level's (its residuals,
    fitted rows and snapshots), and it is checked against the next finer level the same
    way. The finest level is not checked against a finer one (flagged).

    `compiling`: level index -> its forward program compiling in the background
    (`evaluation.Compiling`), waited for before that level's first run; the next level's
    starts compiling here when a defect correction begins (the check will follow).
    `meanwhile(result, level)`: called whenever that wait is for a program still
    compiling, with the answer as it stands (`fit_study`)."""

    verbose = fit_kw.get("verbose")
    levels = res.LEVELS
    coarse = result.problem
    tol = (result.integration or {}).get("tolerance_um")
    base = study if tol is None else dataclasses.replace(study, wear_tolerance_um=tol)
    start = dict(zip(coarse.names, map(float, np.asarray(coarse.start))))
    lo, hi = coarse.packing.bounds_u()
    at, corrections, correction_step = 0, 0, None
    spent = result.iterations  # every evaluation of the answer, the first fit's on
    forward = 0  # of them, forward runs
    report = None
    t_start = time.perf_counter()
    finest_s, finest_runs = 0.0, 0  # forward runs at the finest level, and their time
    compiling = {} if compiling is None else compiling
    for i in range(1, len(levels)):
        fine = build_problem(res.at_level(base, levels[i]), keys, start, layout=layout)
        if i in compiling:
            if meanwhile is not None and not compiling[i].ready.is_set():
                # XLA's compilation holds no lock of the interpreter's: the caller's work
                # on the answer runs beside it
                meanwhile(result, tuple(levels[at]))
            compiling[i].wait()
        ratio, tries, still = math.inf, 0, False
        while True:
            t0 = time.perf_counter()
            f = forward_run(fine, result.u)
            if i + 1 == len(levels):
                finest_s += time.perf_counter() - t0
                finest_runs += 1
            fine = f.model
            spent, forward = spent + 1, forward + 1
            if not f.usable:
                result.flags.append(f"resolution: the model at {_lv(levels[i])} is not "
                                    f"usable at the answer (worn through or not finite): "
                                    f"the answer is not checked against it")
                break
            ev = result.evaluation
            shift = f.rows - ev.pred  # the change of the correction that gives its rows
            pt = ev.shifted(shift).point()
            ratio = lsq.step_in_standard_errors(pt, result.error_scale_um, lo, hi,
                                                relative_to=ev.point())[0]
            ok = ratio <= res.FIT_SE_TOL
            if tries == 0:
                first = ratio  # this level's check before any correction to it
            _log(verbose, f"  resolution: a Gauss-Newton step with the rows of "
                          f"{_lv(levels[i])} (forward run) moves the answer at "
                          f"{_lv(levels[at])} by {ratio:.2g} standard errors"
                          + ("" if ok else f" (> {res.FIT_SE_TOL:g}): defect correction"))
            if ok or tries >= MAX_CORRECTIONS or not result.converged:
                break
            if i + 1 < len(levels) and i + 1 not in compiling:
                # traced ahead (`fit_study`) where it could be: compiled here
                build = _level_builder(base, keys, start, layout, i + 1)
                compiling[i + 1] = (compiling[i].compile_next(build) if i in compiling
                                    else compile_forward(build))
            tries += 1
            corrections += 1
            refit = fit(coarse.with_defect(coarse.defect + shift), result.u,
                        ev0=ev.shifted(shift), label=f"corrected to {_lv(levels[i])}",
                        **fit_kw)
            spent += refit.iterations
            # a refit that converged where it started leaves δ, and so the check, as they
            # were: another round would repeat them (the fit's own stop, which judges the
            # step against the scale the residuals will support, found it settled)
            still = refit.converged and np.array_equal(np.asarray(refit.u),
                                                       np.asarray(result.u))
            coarse, result, at = refit.problem, _carry(refit, result), i
            if still:  # its rows already carry this δ: nothing more to add below
                shift = np.zeros_like(shift)
                break
        if not f.usable:
            report = res.report(levels[at], None, kind="fit", value=None, ok=False)
            break
        if at < i:  # the answer stands at its level, checked against this one
            report = res.report(levels[at], levels[i], kind="fit", value=ratio,
                                ok=ratio <= res.FIT_SE_TOL)
            # the check's rows are the answer's numerical error (a diagnosis's shape
            # analysis counts it without a forward run of its own)
            result = dataclasses.replace(result, finer_minus_rows_um=f.rows - ev.pred,
                                         finer_level=tuple(levels[i]))
            break
        # corrected to this level: the answer is this level's, to within `ratio`
        coarse = coarse.with_defect(coarse.defect + shift)
        result = at_corrected(result, coarse, shift, f, ratio)
        correction_step = ratio
        if (ratio > res.FIT_SE_TOL and not still) or not result.converged:
            result.flags.append(f"resolution: the defect correction to {_lv(levels[i])} did "
                                f"not settle ({tries} corrections; the last step is "
                                f"{ratio:.2g} standard errors)")
            report = res.report(levels[i], None, kind="fit", value=ratio, ok=False)
            break
        if i + 1 == len(levels):
            # one line on why and what it cost: a model whose rows still move between the
            # two finest levels has wear made by what a coarser cycle does not resolve
            # (fast events: a load that swings round at the force reversals, an impact)
            result.flags.append(
                f"resolution: the fit needed the finest level {_lv(levels[i])}, which is "
                f"not checked against a finer one: at {_lv(levels[i - 1])} the answer was "
                f"{first:.2g} standard errors away (wear made by something the coarser "
                f"cycle does not resolve, e.g. fast events at the force reversals); "
                f"{finest_runs} forward run(s) there took {finest_s:.0f} s of the "
                f"{time.perf_counter() - t_start:.0f} s the resolution checks took")
            report = res.report(levels[i], None, kind="fit", value=None, ok=False)
    report.update(res.correction_report(levels[0], levels[at] if at else None, corrections,
                                        correction_step))
    result.resolution = report
    result.iterations = spent
    result.forward_runs = forward
    return result


def _lv(level) -> str:
    return f"{level[0]} x {level[1]}"


def _carry(refit: FitResult, before: FitResult) -> FitResult:
    """A corrected refit keeps the flags of what came before it (integration notes)."""
    refit.flags = list(dict.fromkeys(before.flags + refit.flags))
    return refit


def at_corrected(result: FitResult, problem: ResidualModel, shift, f: Forward,
                 step_se: float) -> FitResult:
    """`result` reported at the level its correction reaches: `problem` carries the
    correction recomputed at the answer, so its rows there are the finer level's (`f`, its
    forward run): fitted rows, residuals and RMSE are that level's, the snapshots its
    `f.snaps`; standard errors stay those of the last corrected fit (its residuals differ
    from these by less than the check's `step_se` standard errors)."""
    ev = result.evaluation.shifted(shift)
    r = ev.r
    exp_idx = np.asarray(problem.data.exp)
    per = {name: float(np.sqrt(np.mean(r[exp_idx == i] ** 2)))
           for i, name in enumerate(problem.exp_names) if np.any(exp_idx == i)}
    return dataclasses.replace(result, problem=problem, evaluation=ev, residuals_um=r,
                               predicted_um=ev.pred, rmse_um=float(np.sqrt(np.mean(r ** 2))),
                               rmse_per_experiment=per, snapshots_um=f.snaps,
                               step_se=float(step_se))


def _fit_at(study: Study, keys, start, layout=None, *, noise_um, max_evaluations, verbose,
            se_tol, on_start=None, on_first=None) -> FitResult:
    problem = build_problem(study, keys, start, layout)
    result = fit(problem, noise_um=noise_um, max_evaluations=max_evaluations, verbose=verbose,
                 se_tol=se_tol, on_start=on_start, on_first=on_first)
    return recheck_integration(study, result, noise_um=noise_um,
                               max_evaluations=max_evaluations, verbose=verbose,
                               se_tol=se_tol)


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
        pb = problem.batched_params(np.asarray(u, np.float64))
        return [jax.tree.map(lambda x: x[i], pb) for i in range(len(names))]

    if study.integrator == "paper":

        for line in amplification_warnings(study, per_exp(result.u)):
            result.flags.append(line.removeprefix("warning: "))
        return result
    tol = study.wear_tolerance_um
    checks = 0  # evaluations of the check itself (counted with the fit's)
    for k in range(refits + 1):
        # the attempt count at the fitted values (`evaluate` raises it where they need
        # more; never lowered: the same shapes, no recompilation)
        fitted = at_tolerance(problem, tol)
        ev, fitted = evaluate(fitted, result.u)
        checks += 1
        err = float(ev.error_um)
        if err <= study.wear_tolerance_um or k == refits:
            break
        tol /= 4
        _log(fit_kw.get("verbose"), f"  integration error {err:.3g} µm above tolerance at "
                                    f"the fitted values: refit at {tol:.3g} µm")
        result = fit(fitted.with_schedule(at_tolerance(fitted, tol).schedule), result.u,
                     **fit_kw)
        problem = result.problem
    result.integration = integration_report(fitted, ev)
    result.iterations += checks
    if err <= study.wear_tolerance_um:
        return result
    note = (f"integration error estimate {err:.3g} µm at the fitted values exceeds the "
            f"tolerance {study.wear_tolerance_um:g} µm (after {refits} refits); lower "
            f"[numerics] wear_tolerance_um")
    result.flags.append(note)
    result.message += "; " + note
    return result


def at_tolerance(problem: ResidualModel, tol_um: float) -> ResidualModel:
    """`problem` with its adaptive schedules' error tolerance set to `tol_um` [µm] (a traced
    value: no recompilation; the attempt count follows in `evaluate`)."""
    sched = problem.schedule
    if not sched.adaptive:
        return problem

    tol = sched.tolerance
    if getattr(tol, "weak_type", False):  # as built elsewhere: keep its type (one program)
        return problem.with_schedule(dataclasses.replace(
            sched, tolerance=jnp.full_like(tol, tol_um * 1e-6)))
    # on the host: eager `full_like` compiled a program of its own
    return problem.with_schedule(dataclasses.replace(
        sched, tolerance=to_device(np.full(np.shape(tol), tol_um * 1e-6, np.float64))))
