"""`predict(method="nuts")`: a posterior by NUTS (NumPyro) through the differentiable wear loop.

Parameters are sampled in whitened coordinates v of the fit's own parameterisation u
(log-multipliers of positive parameters, linear strengths):
u = û + (σ/σ̂) L v, with û, σ̂ the least-squares fit and L the Cholesky factor of its Laplace
covariance. The σ/σ̂ factor takes out the funnel between the noise level and the parameters
(with few rows the posterior of σ has a long tail and the parameters' spread grows with σ,
which a constant mass matrix cannot follow: measured on the boom, 3 rows, before this:
16 divergences and R-hat 1.2 at 2 x (120 + 120)); the log-Jacobian p ln(σ/σ̂) is added, so
the posterior in u is unchanged. With the noise given (or no usable covariance) the factor
is 1 (or L = I). Priors, from the study:
- K_d: log-normal around the study's value, σ = ln 100 (positive by construction, broad);
- fitted clearances: the study's Gaussian prior N(nominal, τ) (`[fit] clearance_tolerance_um`,
  design.md §6), on the clearance itself (the log-Jacobian of c = c₀ e^u is added); τ = inf:
  flat in c > 0;
- effect strengths: uniform between the effect's bounds; positive shape parameters
  (`log=True`, e.g. the running-in distance): log-uniform between the bounds;
- other fitted study keys: log-normal (positive) or normal (σ = 10 typical scales);
- the noise σ [µm]: log-uniform on [1e-3, 1e3] µm (scale-invariant), unless given.
Likelihood: independent Gaussian rows, N(model, σ²).

The posterior predictive of the forecast maximum depth evaluates the forecast model at
`n_predictive` draws (thinned evenly); "a new measurement" adds N(0, σ²) with each draw's σ.
Past the last `--at` point the forecast only serves the life estimate, so each draw's run
stops once its depth has passed the layer (≥ any allowed limit; `Schedule.stopping_at`);
later points repeat the last computed profile (a lower bound, the depth only grows: past the
layer either way) instead of being integrated through the substrate (measured on the boom:
~1 000 steps per draw instead of over 30 000 to 10x the last measurement). Each draw's own
limit crossing lies at computed points.

Before sampling, the run time is estimated from a few timed gradient evaluations (after
compilation) times the expected number of gradients (leapfrog steps ≈ `LEAPFROG_GUESS`
per NUTS step) plus the predictive evaluations; above `max_minutes` the run is refused
(InputError naming `--max-minutes`). Chains run one after another (the CPU is shared).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from jaxwear._analyses.predict.draws import DrawForecasts, run_forward
from jaxwear._core import pytree
from jaxwear._core.errors import InputError, ModelFailure
from jaxwear._core.jit import jit
from jaxwear._core.log import log as _log
from jaxwear._inference.attempts import enough_attempts as _enough_attempts
from jaxwear._inference.residual import TRACES

ADAPT_MASS_FROM_WARMUP = 150  # NumPyro's windowed schedule: 75 + 25 + 50 steps
LEAPFROG_GUESS = 10  # mean leapfrog steps per NUTS step (measured ~6 on the rig test, dense mass)


def _arviz():
    with warnings.catch_warnings():  # arviz announces a refactor with a FutureWarning
        warnings.simplefilter("ignore")
        import arviz

    return arviz


def log_prior(problem, u):
    """Log prior density of u (up to a constant): the packing's (`Packing.log_prior`)."""
    return problem.packing.log_prior(u)


class Whitening(pytree.Struct):
    """u = u_hat + exp(log_noise - log_noise_hat) L v (see the module docstring); `scaled`
    False (noise given): u = u_hat + L v."""

    u_hat: jax.Array  # (p,)
    L: jax.Array  # (p, p) lower triangular
    log_noise_hat: jax.Array  # ()
    scaled: bool = pytree.field(static=True, default=True)

    def u_of(self, z):
        f = jnp.exp(z["log_noise"] - self.log_noise_hat) if self.scaled else 1.0
        return self.u_hat + f * (self.L @ z["v"])

    def log_jacobian(self, z):
        if not self.scaled:
            return 0.0
        return self.u_hat.shape[0] * (z["log_noise"] - self.log_noise_hat)


def whitening(result, cov, noise_um=None) -> Whitening:
    """The whitening at the fit from its Laplace covariance `cov` (p, p) of u; L = I where
    `cov` is not positive definite (undetermined directions)."""
    u_hat = jnp.asarray(result.u, jnp.float64)
    p = u_hat.shape[0]
    cov = np.asarray(cov, float)
    try:
        L = np.linalg.cholesky(0.5 * (cov + cov.T)) if np.all(np.isfinite(cov)) else None
    except np.linalg.LinAlgError:
        L = None
    if L is None or not np.all(np.isfinite(L)):
        L = np.eye(p)
    return Whitening(u_hat, jnp.asarray(L), jnp.asarray(math.log(max(result.noise_um, 1e-3))),
                     scaled=noise_um is None)


def prior_density(problem, noise_um=None, white: Whitening | None = None):
    """z ↦ (u, ln σ, the log prior with the whitening's log-Jacobian and σ's bounds): the
    part of `log_density` that needs no model run (-inf outside the prior's support)."""
    given = noise_um is not None
    lo_s, hi_s = math.log(1e-3), math.log(1e3)

    def prior(z):
        log_s = jnp.log(noise_um) if given else z["log_noise"]
        if white is None:
            u, jac = z["u"], 0.0
        else:
            zz = {"v": z["v"], "log_noise": log_s}
            u, jac = white.u_of(zz), white.log_jacobian(zz)
        lp = log_prior(problem, u) + jac
        if not given:  # log-uniform σ: flat in log σ within the bounds
            lp = lp + jnp.where((log_s > lo_s) & (log_s < hi_s), 0.0, -jnp.inf)
        return u, log_s, lp

    return prior


def log_density(problem, noise_um=None, white: Whitening | None = None):
    """The posterior's log density (up to a constant) as a function of the position z.

    z = {"u": (p,) the fit's parameterisation, "log_noise": () ln σ[µm]} ("log_noise" absent
    when `noise_um` is given); with `white`, z = {"v": (p,), "log_noise"} and u =
    `white.u_of(z)` (the log-Jacobian added). Gaussian likelihood of the training rows
    times `log_prior` (and the log-uniform σ on [1e-3, 1e3] µm); -inf outside the prior's
    support or where the model is not finite. The one density both samplers use (NumPyro in
    `run_nuts`, BlackJAX in benchmarks/nuts_samplers.py).
    """
    y = problem.data.depth_um
    prior = prior_density(problem, noise_um, white)

    def logp(z):
        TRACES["density"] += 1  # runs when traced only
        u, log_s, lp = prior(z)

        def likelihood(_):
            snaps, res = problem.snapshots(u)
            r = problem.predict_from(snaps, u) - y
            # an adaptive loop that ran out of attempts returned a truncated history
            # (error estimate inf): such a position is not a model evaluation; never
            # sample on it
            r = jnp.where(jnp.isfinite(jnp.max(res.error_estimate)), r, jnp.nan)
            return -0.5 * jnp.sum(r ** 2) / jnp.exp(2 * log_s) - r.shape[0] * log_s

        # outside the prior's support the density is -inf whatever the model says: the
        # wear model is not run there (measured on the boom with running-in: 9 of 12 of
        # the importance proposal's draws, 8 at ~0.85 s, one 94 s at an extreme
        # stiffness). Under vmap both branches run (a select), as before.
        ll = jax.lax.cond(jnp.isfinite(lp), likelihood, lambda _: jnp.asarray(-jnp.inf),
                          None)
        out = ll + lp
        return jnp.where(jnp.isfinite(out), out, -jnp.inf)

    return logp


def u_of_samples(samples, white: Whitening | None, noise_um=None) -> np.ndarray:
    """u (chains, draws, p) from sampled positions (leading axes chains, draws)."""
    if white is None:
        return np.asarray(samples["u"])
    z = {"v": jnp.asarray(samples["v"])}
    z["log_noise"] = (jnp.full(z["v"].shape[:-1], math.log(noise_um)) if noise_um is not None
                      else jnp.asarray(samples["log_noise"]))
    return np.asarray(jax.vmap(jax.vmap(white.u_of))(z))


def _more_attempts(problem, factor: int):
    sched = problem.schedule
    if not sched.adaptive:
        return problem
    return dataclasses.replace(problem, schedule=sched.more_attempts(factor))


def initial_position(result, noise_um=None, white: Whitening | None = None) -> dict:
    """The sampler's start: the least-squares fit (and its residual noise level)."""
    z0 = {"u": jnp.asarray(result.u)} if white is None else {
        "v": jnp.zeros_like(jnp.asarray(result.u))}
    if noise_um is None:
        z0["log_noise"] = jnp.asarray(math.log(max(result.noise_um, 1e-3)))
    return z0


LOGP_ERROR = 0.05  # the integration's share of a sampled log density's error, at most


def sampling_tolerance_m(problem, result, noise_um=None) -> float:
    """The wear loop's error tolerance [m] for a sampler's runs: the study's, or looser
    where the noise allows. A depth error |δᵢ| ≤ tol on each of the n rows moves the Gaussian
    log likelihood by at most tol·Σ|rᵢ|/σ² + n tol²/(2σ²) ≤ tol·√(n χ²)/σ + ... (Cauchy-
    Schwarz, χ² = Σ rᵢ²/σ²); at a posterior draw χ² ≈ n + d, so with χ² ≤ 2(n + d)
    tol = `LOGP_ERROR` σ / √(2 n (n + d)) keeps the error below `LOGP_ERROR`, a few per
    cent of a weight, far below the Monte Carlo error of a few hundred effective draws.
    σ: the stated noise, or the fit's σ̂ at its posterior's lower edge (ln σ̂ − 3 sd, sd ≈
    1/√(2 dof)). The boom's 3 rows at σ = 5 µm: 0.039 µm against the study's 0.002 µm
    (~1.4x fewer steps a run); a rig profile of 180 rows at σ̂ = 0.1 µm keeps the study's."""
    study_tol = float(np.max(np.asarray(problem.schedule.tolerance))) \
        if problem.schedule.adaptive and problem.schedule.tolerance is not None else 0.0
    n = int(problem.n_data)
    d = len(problem.names) + (0 if noise_um is not None else 1)
    if noise_um is not None:
        sigma = float(noise_um)
    else:
        dof = max(float(result.error_dof), 1.0) if math.isfinite(result.error_dof) else 1.0
        sigma = float(result.noise_um) * math.exp(-3.0 / math.sqrt(2.0 * dof))
    return max(study_tol, LOGP_ERROR * sigma * 1e-6 / math.sqrt(2.0 * n * (n + d)))


def with_tolerance(problem, tol_m: float):
    """`problem` whose adaptive loop's tolerance is at least `tol_m` [m] (the same
    compilation: the tolerance is a traced array)."""
    sched = problem.schedule
    if not sched.adaptive or sched.tolerance is None:
        return problem
    return problem.with_schedule(dataclasses.replace(
        sched, tolerance=jnp.maximum(sched.tolerance, tol_m)))


def sampling_setup(problem, result, noise_um=None, cov=None, compiled=None,
                   dynamic: bool = True):
    """(problem with room for the draws, `Whitening`, log density, start position): what
    `run_nuts` samples, and the benchmark's samplers with it. `compiled(logp)`: the
    compiled function of the log density checked for a finite value at the start
    (default `jit(logp)`, jaxwear's wrapper); a sampler passes the program it will time, so
    that the check costs no compilation of its own (12 s of the boom's 200 s NUTS answer).
    `dynamic`: the adaptive loop's attempt count a traced bound (forward and forward-mode
    only: a reverse-mode gradient needs the static count)."""
    # Room for the draws: the training problem's attempt count was estimated at the start
    # values, so first raise it to what the fitted values need (K_d moves by orders), then
    # leave 4x headroom for the posterior's tails (larger K_d: more steps on a stiff layer).
    # Unused attempts cost nothing; a draw that still runs out gets log density -inf.

    p = len(problem.names)
    problem = _more_attempts(_enough_attempts(problem, np.asarray(result.u)), 4)
    problem = with_tolerance(problem, sampling_tolerance_m(problem, result, noise_um))
    if dynamic and problem.schedule.adaptive:
        # the attempt count a traced bound (a while loop): the headroom's unused attempts
        # cost nothing, where a static scan spends ~50 µs on each (measured on the boom
        # with running-in: 16 384 attempts for ~1 200 used, 1.21 s a density against 0.51)
        problem = problem.with_schedule(problem.schedule.with_dynamic_attempts())
    white = whitening(result, np.eye(p) if cov is None else cov, noise_um)
    z_fit = initial_position(result, noise_um, white)
    for i in range(4):  # the estimate may still fall short at the fit itself
        logp = log_density(problem, noise_um, white)
        f = (jit if compiled is None else compiled)(logp)
        finite = math.isfinite(float(f(z_fit)))  # one compile per try
        if finite or not problem.schedule.adaptive or i == 3:
            break
        problem = _more_attempts(problem, 2)
    if not finite:
        raise ModelFailure("predict/nuts: the log density is not finite at the fitted "
                           "parameters; the sampler cannot start there")
    return problem, white, logp, z_fit


def _start_inverse_mass(z0, dof: int):
    """The warm-up's first mass matrix, in NumPyro's flattening of z (dict keys sorted):
    v is whitened by the Laplace covariance (variance 1), while ln σ's posterior variance is
    about 1/(2 dof) for dof = rows - parameters. Started from the identity, the step size
    must first shrink to ln σ's scale (~0.05 for 240 rows): measured on the rig test (2 x 40
    warm-up steps), deep trees until the mass matrix adapted took most of the sampling
    time."""
    flat, _ = jax.flatten_util.ravel_pytree(
        {k: (jnp.full(jnp.shape(a), 1.0 / (2.0 * max(dof, 1))) if k == "log_noise"
             else jnp.ones(jnp.shape(a))) for k, a in z0.items()})
    return jnp.diag(flat)


def run_nuts(problem, result, fprob, fprob_fine=None, *, noise_um=None, level=0.9,
             verbose=False, draws: int = 500, warmup: int = 300, chains: int = 2,
             seed: int = 0, max_minutes: float = 20.0, n_predictive: int = 200, out=None,
             forward_mode: bool = True, cov=None, workers: int = 2):
    """NUTS posterior of the training problem's parameters and the forecast's predictive.

    Returns (draws dict: `max_um` (D, E, S), `new_um` (D, E, S), `snapshots_um`
    (D, E, S, N), `noise` (D,); extra JSON dict with the sampler's diagnostics: R-hat and
    bulk ESS per parameter, divergences, time, netCDF path; `forecast_draws(fprob,
    fprob_fine)`, the same draws' dict at another forecast problem's points, for the life's
    refinement; `_predict_draws.DrawForecasts`). `fprob_fine`: the forecast problem at the
    level the fit's answer is corrected to (None: none).
    `forward_mode`: gradients by forward mode (p tangents through the wear loop: measured
    faster than reverse mode for p ≤ ~6, when reverse mode still ran the contact solves'
    Newton iterations again; it keeps them since 2026-11-30, `_physics.remat`, and the
    crossover was not measured again).
    `cov`: the fit's Laplace covariance of u (p, p) for the whitening (None: L = I).
    `fprob` may carry an early stop (`Schedule.stopping_at`): its +inf snapshots are
    filled with the last computed one (`_predict.fill_past_stop`).
    """
    from numpyro.infer import MCMC, NUTS

    names = list(problem.names)
    p = len(names)
    given = noise_um is not None
    built = {}

    def value_and_gradient(logp):
        # the potential's value and gradient, computed as NumPyro does (forward mode: the
        # value as jacfwd's aux, one pass; a separate value pass made the run-time estimate
        # ~2x long on the boom); compiled once, for the start's check and the timing
        def potential(z):
            return -logp(z)

        def with_value(z):
            v = potential(z)
            return v, v

        if forward_mode:
            f = jit(lambda z: jax.jacfwd(with_value, has_aux=True)(z)[::-1])
        else:
            f = jit(jax.value_and_grad(potential))
        built.update(grad=f, potential=potential)

        def first_call(z):  # compiles; the check reads the log density
            t0 = time.perf_counter()
            out = jax.block_until_ready(f(z))
            built["t_compile"] = time.perf_counter() - t0
            return -out[0]

        return first_call

    problem, white, logp, z_fit = sampling_setup(problem, result, noise_um, cov,
                                                 compiled=value_and_gradient,
                                                 dynamic=forward_mode)
    grad, potential, t_compile = built["grad"], built["potential"], built["t_compile"]
    # the draws' forecasts at the density's tolerance (a depth error far below the noise)
    fprob = with_tolerance(fprob, sampling_tolerance_m(problem, result, noise_um))
    z0 = z_fit
    t0 = time.perf_counter()
    for _ in range(3):
        jax.block_until_ready(grad(z0))
    t_grad = (time.perf_counter() - t0) / 3
    u_fit = np.asarray(result.u, np.float64)
    t0 = time.perf_counter()
    _, _, _, fprob = run_forward(fprob, u_fit)  # compiles, settles the attempt count
    t_fc_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    run_forward(fprob, u_fit)
    t_fc = time.perf_counter() - t0
    n_grad = chains * (warmup + draws) * LEAPFROG_GUESS
    n_pred = min(n_predictive, chains * draws)
    est = n_grad * t_grad + n_pred * t_fc
    _log(verbose, f"predict/nuts: {p} parameters{'' if given else ' + noise'}; gradient "
                  f"{t_grad * 1e3:.0f} ms (compiled in {t_compile:.0f} s), forecast "
                  f"{t_fc * 1e3:.0f} ms; estimated run time {est / 60:.1f} min "
                  f"({n_grad} gradients, {n_pred} forecasts)")
    if est > 60 * max_minutes:
        raise InputError(f"<<max_minutes>>: NUTS would take about {est / 60:.0f} min "
                         f"({chains} chains x {warmup + draws} steps x ~{LEAPFROG_GUESS} "
                         f"gradients of {t_grad:.2g} s) > the limit of {max_minutes:g} min; "
                         f"raise <<max_minutes>>, lower <<draws>>/<<warmup>>/<<chains>>, or use "
                         f"<<method>> laplace")
    kernel = NUTS(potential_fn=potential, dense_mass=True, target_accept_prob=0.85,
                  forward_mode_differentiation=forward_mode, max_tree_depth=8,
                  inverse_mass_matrix=_start_inverse_mass(z0, problem.n_data - p),
                  adapt_mass_matrix=warmup >= ADAPT_MASS_FROM_WARMUP)
    # NumPyro's progress bar steps the chain from Python, a dispatch per NUTS step: nothing
    # next to the gradients of a run long enough to need it (estimated over a minute)
    progress = bool(verbose) and est > 60
    _log(verbose, f"predict/nuts: sampling {chains} chain(s) x ({warmup} warm-up + {draws} "
                  f"draws), one after another" + (" (progress below)" if progress else ""))
    mcmc = MCMC(kernel, num_warmup=warmup, num_samples=draws, num_chains=chains,
                chain_method="sequential", progress_bar=progress)
    t0 = time.perf_counter()
    # numpyro takes one chain's start unbatched, several with a leading chain axis
    init = z0 if chains == 1 else jax.tree.map(
        lambda a: jnp.broadcast_to(a, (chains, *jnp.shape(a))), z0)
    mcmc.run(jax.random.PRNGKey(seed), init_params=init, extra_fields=("diverging",
                                                                        "num_steps"))
    t_run = time.perf_counter() - t0
    samples = mcmc.get_samples(group_by_chain=True)
    extra = mcmc.get_extra_fields(group_by_chain=True)
    u_s = u_of_samples(samples, white, noise_um)  # (chains, draws, p)
    vals = np.asarray(jax.vmap(jax.vmap(problem.values))(jnp.asarray(u_s)))
    post = {n: vals[..., i] for i, n in enumerate(names)}
    if given:
        noise = np.full(u_s.shape[:2], float(noise_um))
    else:
        noise = np.exp(np.asarray(samples["log_noise"]))
        post["noise_um"] = noise
    az = _arviz()
    idata = az.from_dict(posterior={k.replace("/", ":"): v for k, v in post.items()},
                         sample_stats={"diverging": np.asarray(extra["diverging"]),
                                       "n_steps": np.asarray(extra["num_steps"])})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        summ = az.summary(idata, kind="diagnostics")
    diag = {}
    for k in post:
        row = summ.loc[k.replace("/", ":")]
        diag[k] = {"r_hat": _f(row["r_hat"]), "ess_bulk": _f(row["ess_bulk"]),
                   "ess_tail": _f(row["ess_tail"]),
                   "mean": float(np.mean(post[k])), "sd": float(np.std(post[k])),
                   "lower": float(np.quantile(post[k], (1 - level) / 2)),
                   "upper": float(np.quantile(post[k], (1 + level) / 2))}
    n_div = int(np.sum(np.asarray(extra["diverging"])))
    mean_steps = float(np.mean(np.asarray(extra["num_steps"])))
    # posterior predictive at evenly thinned draws (u in the training problem's coordinates,
    # which the forecast problems share)
    flat_u = u_s.reshape(-1, p)
    flat_s = noise.reshape(-1)
    idx = np.linspace(0, len(flat_u) - 1, n_pred).round().astype(int)
    _log(verbose, f"predict/nuts: sampled in {t_run:.0f} s ({n_div} divergences, "
                  f"{mean_steps:.1f} leapfrog steps per step); forecasting {n_pred} draws")
    forecast_draws = DrawForecasts(flat_u[idx], flat_s[idx], u_fit, seed=seed,
                                   workers=workers, verbose=verbose, label="predict/nuts")
    t0 = time.perf_counter()
    draws_out = forecast_draws(fprob, fprob_fine)
    t_pred = time.perf_counter() - t0
    # the same dict object each time: a refined forecast updates the JSON's block
    extra_json = {"integration": forecast_draws.integration}
    path = None
    if out is not None:  # through a temporary name, like every other output
        path = out.write_with("posterior.nc",
                              lambda tmp: idata.to_netcdf(str(tmp), engine="h5netcdf"))
    r_hat_flags = r_hat_warnings(diag, chains)
    extra_json["nuts"] = {
        "sampler": "numpyro NUTS (dense mass matrix, "
                   + ("forward-mode" if forward_mode else "reverse-mode") + " gradients)",
        "chains": chains, "warmup": warmup, "draws": draws, "seed": seed,
        "divergences": n_div, "mean_leapfrog_steps": mean_steps,
        "seconds": t_run, "estimated_seconds": est, "gradient_seconds": t_grad,
        "compile_seconds": t_compile + t_fc_compile, "predictive_draws": int(n_pred),
        "predictive_seconds": t_pred,
        "parameterisation": ("whitened by the Laplace covariance"
                             + ("" if noise_um is not None else ", scaled by σ/σ̂")),
        "posterior": diag, "netcdf": None if path is None else str(path),
        # a non-finite R-hat (a stuck chain, or one chain only) is reported as null and
        # flagged; it once became 0.0 here, hiding the worst chain
        "max_r_hat": worst(diag, "r_hat", max),
        "min_ess_bulk": worst(diag, "ess_bulk", min),
        "flags": r_hat_flags}
    return draws_out, extra_json, forecast_draws


def worst(diag: dict, key: str, pick):
    """`pick` (max or min) of `key` over the parameters; None (JSON null) when any of them
    is not finite (`_f` gives None), or when there are none."""
    vals = [v[key] for v in diag.values()]
    if not vals or any(x is None for x in vals):
        return None
    return pick(vals)


def r_hat_warnings(diag: dict, chains: int) -> list[str]:
    """Flags for parameters whose R-hat is not finite."""
    bad = [k for k, v in diag.items() if v["r_hat"] is None]
    if not bad:
        return []
    why = ("R-hat needs at least 2 chains (--chains)" if chains < 2 else
           "a chain did not move (constant draws) or gave non-finite values")
    return [f"nuts: R-hat is not finite for {', '.join(bad)} ({why}): convergence is not "
            f"checked; max_r_hat is null"]


def _f(x):
    x = float(x)
    return x if math.isfinite(x) else None
