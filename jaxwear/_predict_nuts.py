"""`predict(method="nuts")`: a posterior by NUTS (NumPyro) through the differentiable wear loop.

Parameters are sampled in the fit's own parameterisation u (log-multipliers of positive
parameters, linear strengths), with priors from the study:
- K_d: log-normal around the study's value, σ = ln 100 (positive by construction, broad);
- fitted clearances: the study's Gaussian prior N(nominal, τ) (`[fit] clearance_tolerance_um`,
  DESIGN §6), on the clearance itself (the log-Jacobian of c = c₀ e^u is added); τ = inf:
  flat in c > 0;
- effect strengths: uniform between the effect's bounds; positive shape parameters
  (`log=True`, e.g. the running-in distance): log-uniform between the bounds;
- other fitted study keys: log-normal (positive) or normal (σ = 10 typical scales);
- the noise σ [µm]: log-uniform on [1e-3, 1e3] µm (scale-invariant), unless given.
Likelihood: independent Gaussian rows, N(model, σ²).

The posterior predictive of the forecast maximum depth evaluates the forecast model at
`n_predictive` draws (thinned evenly); "a new measurement" adds N(0, σ²) with each draw's σ.

Before sampling, the run time is estimated from a few timed gradient evaluations (after
compilation) times the expected number of gradients (leapfrog steps ≈ `LEAPFROG_GUESS`
per NUTS step) plus the predictive evaluations; above `max_minutes` the run is refused
(InputError naming `--max-minutes`). Chains run one after another (the CPU is shared).
"""

from __future__ import annotations

import math
import sys
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._errors import InputError
from .effects import effect_parameter_specs

LEAPFROG_GUESS = 10  # mean leapfrog steps per NUTS step (measured ~6 on the rig test, dense mass)


def _log(verbose, msg):
    if verbose:
        print(msg, file=sys.stderr, flush=True)


def _arviz():
    with warnings.catch_warnings():  # arviz announces a refactor with a FutureWarning
        warnings.simplefilter("ignore")
        import arviz

    return arviz


def log_prior(problem, u):
    """Log prior density of u (up to a constant), per the module docstring."""
    specs = effect_parameter_specs()
    vals = problem.values(u)
    lp = 0.0
    for i, f in enumerate(problem.fits):
        if f.key == "clearance_mm":
            tol_mm = problem.tolerance_um / 1e3
            c0 = problem.nominal_clearance_mm[f.experiment]
            gauss = jnp.where(jnp.isfinite(tol_mm), -0.5 * ((vals[i] - c0) / tol_mm) ** 2, 0.0)
            lp = lp + gauss + u[i]  # + log |dc/du| (c = start·e^u)
        elif f.key in specs:
            s = specs[f.key]
            lo, hi = s.lower, s.upper
            # uniform (or log-uniform) between the bounds: -inf outside
            inside = (vals[i] >= lo) & (vals[i] <= hi)
            lp = lp + jnp.where(inside, 0.0, -jnp.inf)
        elif f.log:
            lp = lp - 0.5 * (u[i] / math.log(100.0)) ** 2
        else:
            lp = lp - 0.5 * (u[i] / 10.0) ** 2
    return lp


def log_density(problem, noise_um=None):
    """The posterior's log density (up to a constant) as a function of the position z.

    z = {"u": (p,) the fit's parameterisation, "log_noise": () ln σ[µm]} ("log_noise" absent
    when `noise_um` is given). Gaussian likelihood of the training rows times `log_prior`
    (and the log-uniform σ on [1e-3, 1e3] µm); -inf outside the prior's support or where
    the model is not finite. The one density both samplers use (NumPyro in `run_nuts`,
    BlackJAX in benchmarks/nuts_samplers.py).
    """
    y = problem.data.depth_um
    given = noise_um is not None
    lo_s, hi_s = math.log(1e-3), math.log(1e3)

    def logp(z):
        u, log_s = z["u"], (jnp.log(noise_um) if given else z["log_noise"])
        snaps, res = problem.snapshots(u)
        r = problem.predict_from(snaps, u) - y
        # an adaptive loop that ran out of attempts returned a truncated history (error
        # estimate inf): such a position is not a model evaluation; never sample on it
        r = jnp.where(jnp.isfinite(jnp.max(res.error_estimate)), r, jnp.nan)
        s2 = jnp.exp(2 * log_s)
        ll = -0.5 * jnp.sum(r ** 2) / s2 - r.shape[0] * log_s
        if not given:  # log-uniform σ: flat in log σ within the bounds
            ll = ll + jnp.where((log_s > lo_s) & (log_s < hi_s), 0.0, -jnp.inf)
        out = ll + log_prior(problem, u)
        return jnp.where(jnp.isfinite(out), out, -jnp.inf)

    return logp


def _more_attempts(problem, factor: int):
    import dataclasses

    sched = problem.schedule
    if not sched.adaptive:
        return problem
    return dataclasses.replace(problem, schedule=sched.more_attempts(factor))


def initial_position(result, noise_um=None) -> dict:
    """The sampler's start: the least-squares fit (and its residual noise level)."""
    z0 = {"u": jnp.asarray(result.u)}
    if noise_um is None:
        z0["log_noise"] = jnp.asarray(math.log(max(result.noise_um, 1e-3)))
    return z0


def run_nuts(problem, result, fprob, *, noise_um=None, level=0.9, verbose=False,
             draws: int = 500, warmup: int = 300, chains: int = 2, seed: int = 0,
             max_minutes: float = 20.0, n_predictive: int = 200, out=None,
             forward_mode: bool = True):
    """NUTS posterior of the training problem's parameters and the forecast's predictive.

    Returns (draws dict: `max_um` (D, E, S), `new_um` (D, E, S), `profile_um` (D, E, N) at
    the last `--at` point's snapshot, `profile_new_um`; extra JSON dict with the sampler's
    diagnostics: R-hat and bulk ESS per parameter, divergences, time, netCDF path).
    `forward_mode`: gradients by forward mode (p tangents through the wear loop: measured
    faster than reverse mode, which re-runs the checkpointed loop, for p ≤ ~6).
    """
    from numpyro.infer import MCMC, NUTS

    names = list(problem.names)
    p = len(names)
    given = noise_um is not None
    # Room for the draws: the training problem's attempt count was estimated at the start
    # values, so first raise it to what the fitted values need (K_d moves by orders), then
    # leave 4x headroom for the posterior's tails (larger K_d: more steps on a stiff layer).
    # Unused attempts cost nothing; a draw that still runs out gets log density -inf.
    from ._calibrate import _enough_attempts

    problem = _enough_attempts(problem, np.asarray(result.u))
    problem, fprob = (_more_attempts(x, 4) for x in (problem, fprob))
    z_fit = initial_position(result, noise_um)
    for i in range(4):  # the estimate may still fall short at the fit itself
        logp = log_density(problem, noise_um)
        finite = math.isfinite(float(jax.jit(logp)(z_fit)))  # one compile per try
        if finite or not problem.schedule.adaptive or i == 3:
            break
        problem = _more_attempts(problem, 2)
    if not finite:
        raise RuntimeError("predict/nuts: the log density is not finite at the fitted "
                           "parameters; the sampler cannot start there")

    def potential(z):
        return -logp(z)

    z0 = initial_position(result, noise_um)
    u_fit = z0["u"]
    # time the gradient (compile first) for the run-time estimate, computed as NumPyro
    # does (forward mode: value as jacfwd's aux, one pass; a separate value pass made the
    # estimate ~2x long on the boom)
    def _with_value(z):
        v = potential(z)
        return v, v

    grad = jax.jit(jax.value_and_grad(potential)) if not forward_mode else jax.jit(
        jax.jacfwd(_with_value, has_aux=True))
    t0 = time.perf_counter()
    jax.block_until_ready(grad(z0))
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(3):
        jax.block_until_ready(grad(z0))
    t_grad = (time.perf_counter() - t0) / 3
    fc = jax.jit(lambda u: jnp.max(fprob.snapshots(u)[0], axis=-1))
    t0 = time.perf_counter()
    jax.block_until_ready(fc(u_fit))
    t_fc_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(fc(u_fit))
    t_fc = time.perf_counter() - t0
    n_grad = chains * (warmup + draws) * LEAPFROG_GUESS
    n_pred = min(n_predictive, chains * draws)
    est = n_grad * t_grad + n_pred * t_fc
    _log(verbose, f"predict/nuts: {p} parameters{'' if given else ' + noise'}; gradient "
                  f"{t_grad * 1e3:.0f} ms (compiled in {t_compile:.0f} s), forecast "
                  f"{t_fc * 1e3:.0f} ms; estimated run time {est / 60:.1f} min "
                  f"({n_grad} gradients, {n_pred} forecasts)")
    if est > 60 * max_minutes:
        raise InputError(f"--max-minutes: NUTS would take about {est / 60:.0f} min "
                         f"({chains} chains x {warmup + draws} steps x ~{LEAPFROG_GUESS} "
                         f"gradients of {t_grad:.2g} s) > the limit of {max_minutes:g} min; "
                         f"raise --max-minutes, lower --draws/--warmup/--chains, or use "
                         f"--method laplace")
    kernel = NUTS(potential_fn=potential, dense_mass=True, target_accept_prob=0.85,
                  forward_mode_differentiation=forward_mode, max_tree_depth=8)
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
    u_s = np.asarray(samples["u"])  # (chains, draws, p)
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
    # posterior predictive at evenly thinned draws
    # the forecast problem's u = 0 is the LM fit: map each draw by its parameter values
    flat_u = np.array([fprob.u_of(v) for v in vals.reshape(-1, p)]).reshape(-1, p)
    flat_s = noise.reshape(-1)
    idx = np.linspace(0, len(flat_u) - 1, n_pred).round().astype(int)
    _log(verbose, f"predict/nuts: sampled in {t_run:.0f} s ({n_div} divergences, "
                  f"{mean_steps:.1f} leapfrog steps per step); forecasting {n_pred} draws")
    @eqx.filter_jit
    def fcs(fp, u):
        snaps, res = fp.snapshots(u)
        return snaps, jnp.max(res.error_estimate)

    mx, prof = [], []
    for j in idx:
        s, err = fcs(fprob, jnp.asarray(flat_u[j]))
        for _ in range(3):  # a draw whose forecast needs more integration steps
            if np.isfinite(float(err)):
                break
            fprob = _more_attempts(fprob, 2)
            s, err = fcs(fprob, jnp.asarray(flat_u[j]))
        s = np.asarray(s)  # (E, S, N)
        mx.append(s.max(axis=-1))
        prof.append(s)
    mx = np.stack(mx)
    snaps = np.stack(prof)  # (D, E, S, N)
    rng = np.random.default_rng(seed)
    new = mx + flat_s[idx][:, None, None] * rng.standard_normal(mx.shape)
    draws_out = {"max_um": mx, "new_um": new, "snapshots_um": snaps, "noise": flat_s[idx]}
    path = None
    if out is not None:
        path = out.path("posterior.nc")
        idata.to_netcdf(str(path), engine="h5netcdf")
    extra_json = {"nuts": {
        "sampler": "numpyro NUTS (dense mass matrix, "
                   + ("forward-mode" if forward_mode else "reverse-mode") + " gradients)",
        "chains": chains, "warmup": warmup, "draws": draws, "seed": seed,
        "divergences": n_div, "mean_leapfrog_steps": mean_steps,
        "seconds": t_run, "estimated_seconds": est, "gradient_seconds": t_grad,
        "compile_seconds": t_compile + t_fc_compile, "predictive_draws": int(n_pred),
        "posterior": diag, "netcdf": None if path is None else str(path),
        "max_r_hat": max((v["r_hat"] or 0.0) for v in diag.values()),
        "min_ess_bulk": min((v["ess_bulk"] or 0.0) for v in diag.values())}}
    return draws_out, extra_json


def _f(x):
    x = float(x)
    return x if math.isfinite(x) else None
