"""Forecasts of wear and remaining life with stated uncertainty: `jaxwear.predict` (design.md §7).

The study is calibrated (as `calibrate` does, with its effects) on the measurements at or
before `train_until`; the fitted model is then run to every forecast point, and its
uncertainty is carried there.

`laplace` (default): the fit's Gauss-Newton covariance C of the parameters u (the residual
variance σ̂² of the data rows and the clearance prior's rows, design.md §6) is pushed through
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
from dataclasses import replace

import numpy as np

from jaxwear._analyses.predict.bands import Asked, Fitted, _assemble, t_quantile
from jaxwear._analyses.predict.grid import (
    LAPLACE_STOP_LAYERS,
    forecast_layout,
    forecast_points,
    forecast_problem,
    forecast_snapshots,
    stop_past_layer,
    training_study,
    unit_of_study,
)
from jaxwear._analyses.predict.life import (
    LIFE_REFINE_ROUNDS,
    LIFE_RTOL,
    guided_points,
    refined_points,
)
from jaxwear._analyses.predict.result import PredictResult
from jaxwear._analyses.predict.snapshots import fill_past_stop, on_nodes
from jaxwear._analyses.state_range import law_ranges, range_flags
from jaxwear._core.errors import InputError
from jaxwear._core.log import log as _log
from jaxwear._core.optional import check_method_packages
from jaxwear._inference.calibrate import (
    build_problem,
    check_noise_determined,
    fit,
    fit_study,
    study_fit_keys,
)
from jaxwear._inference.evaluation import forward_run
from jaxwear._inference.residual import traces, traces_since
from jaxwear._inference.result import FitResult
from jaxwear._study import resolution as _resolution
from jaxwear._study.outside import OUTSIDE, forecast_flags
from jaxwear._study.resolution import at_level, at_stable_update
from jaxwear._study.study import Study

# The forecast's fit stops when the next step would move every parameter by < 0.1 of its
# standard error (calibrate's reported values: 0.01): a forecast then moves by < 0.1 of
# its model band, which is what a band can show; on the boom with running-in, 3 training
# rows, the last 0.1 -> 0.01 took 6 more evaluations along the amplitude/distance valley.
FORECAST_SE_TOL = 0.1
METHODS = ("laplace", "nuts", "importance")


# ---------------------------------------------------------------- training subset, forecast


# ---------------------------------------------------------------- covariance, quantiles


# ---------------------------------------------------------------- the API


def _check_args(study, at, train_until, level, limit_um, method, noise_um):
    if method not in METHODS:
        raise InputError(f"<<method>> must be one of {', '.join(METHODS)}, got {method!r}")
    check_method_packages(method)
    if not (isinstance(level, (int, float)) and 0 < level < 1):
        raise InputError(f"<<level>> must be in (0, 1), got {level!r}")
    at = [float(a) for a in (at if np.ndim(at) else [at])]
    if not at or not all(math.isfinite(a) and a > 0 for a in at):
        raise InputError(f"<<at>> must be a list of counts > 0 ({unit_of_study(study)}), "
                         f"got {at}")
    if train_until is not None and not (math.isfinite(train_until) and train_until > 0):
        raise InputError(f"<<train_until>> must be > 0, got {train_until}")
    layer_um = min(float(study.params(e).layer_thickness) for e in study.experiments) * 1e6
    if limit_um is None:
        limit_um = layer_um
    if not (math.isfinite(limit_um) and 0 < limit_um <= layer_um * (1 + 1e-12)):
        raise InputError(f"<<limit_um>> must be in (0, {layer_um:g}] (the layer thickness), "
                         f"got {limit_um}")
    if noise_um is not None and not (math.isfinite(noise_um) and noise_um > 0):
        raise InputError(f"<<noise_um>> must be > 0, got {noise_um}")
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

    **Returns:** a `PredictResult` (`.to_json()` is the design.md §7 document).
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
    check_noise_determined(problem, noise_um, hint="<<noise_um>> (or [fit] noise_um)")
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
    # The explicit update beyond its stability limit at the fitted K_d: refit at a stable
    # M (`at_stable_update`: the depth may look smooth while the band blows up)
    stable, flag = at_stable_update(study, dict(zip(result.names, map(float, result.values))),
                                    done="fitted and forecast")
    if flag is not None:
        flags.append(flag)
        _log(verbose, f"predict: {flags[-1]}")
    if stable is not study:
        study = stable
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
        return _assemble(Asked(study, train, at, limit_um, level, method, unit, train_until,
                               life),
                         Fitted(result, cov, null_dirs, noise, result.noise_given, dof, q),
                         points, list(flags), snaps, J, draws, extra)

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
        # the samplers imported where asked for (scipy.special, ~0.1 s of every start-up)
        if method == "nuts":
            from jaxwear._analyses.predict.nuts import run_nuts as run_sampler
        else:
            from jaxwear._analyses.predict.importance import run_importance as run_sampler

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
    res.flags.extend(f for f in law_range_flags(train, result, res) if f not in res.flags)
    # compilations of the whole answer (fit, checks and every forecast), by kind
    res.extra["compiles"] = traces_since(before)
    # answers outside the model first: the fit's values, forecasts below measured depths
    outside = list(dict.fromkeys(
        [f for f in res.flags if f.startswith(OUTSIDE)]
        + forecast_flags(res.predictions, res.measured, res.noise_um, res.unit)))
    res.flags[:] = outside + [f for f in res.flags if f not in outside]
    return replace(res, outside=outside)


def law_range_flags(train: Study, result: FitResult, res: PredictResult) -> list[str]:
    """A loaded law (`law.py`) used beyond the states it was fitted on (`state_range`), at
    the training answer and where the forecasts go: their deepest forecast depth and the
    sliding distance at their count (each experiment's training sliding scaled by the
    count over its last trained point)."""
    if not law_ranges(train):
        return []
    deepest = [float(p.depth_um) for p in res.predictions
               if p.depth_um is not None and math.isfinite(float(p.depth_um))]
    extra = {"worn_depth_um": (max(deepest), max(deepest))} if deepest else {}
    names = [e.name for e in train.experiments]
    sliding = np.asarray(result.evaluation.sliding_m, float)
    far = []
    for p in res.predictions:
        if p.experiment in names:
            i = names.index(p.experiment)
            end = max(train.experiments[i].snapshot_points[-1], 1e-300)
            far.append(float(sliding[i]) * float(p.at) / float(end))
    if far:
        extra["sliding_distance_m"] = (max(far), max(far))
    return range_flags(train, result.problem, result.evaluation, extra)


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


