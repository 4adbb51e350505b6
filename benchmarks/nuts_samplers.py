"""NumPyro or BlackJAX for `jaxwear predict --method nuts`? Same density, same settings, both.

    python benchmarks/nuts_samplers.py --case boom|rig [--warmup 200] [--draws 200]
        [--chains 2] [--seed 0] [--samplers numpyro,blackjax] [--json FILE]

Both samplers draw from exactly one log density, `jaxwear._analyses.predict.nuts.log_density` in
the whitened coordinates of `sampling_setup` (what `predict --method nuts` samples), with its
gradient by forward mode (p tangents through the
wear loop, as `run_nuts` does; BlackJAX asks for reverse mode, so the density is wrapped in a
`custom_vjp` whose forward pass is `jacfwd`), started at the least-squares fit, with NUTS,
a dense mass matrix adapted in Stan-style windows, target acceptance 0.85, at most 2^8
leapfrog steps per step, the same warmup/draws/chains (run one after another: the CPU is
shared) and seed.

Cases (the problems `predict` samples):
- boom: `calibration/boom/study.toml` trained on 5-15 h, K_d fitted, noise estimated
  (2 unknowns), under the default adaptive integrator (its `revolutions_per_update` dropped);
- rig: a synthetic rig study made by `jaxwear.simulate` at finer numerics (128 nodes,
  144 steps, M = 25) than it is sampled at (64 x 72, M = 100), two experiments, whole scans
  every 3° with 0.3 µm noise, trained until 2000 rev; K_d and both clearances (prior 5 µm)
  and the noise (4 unknowns).

Printed per sampler: wall time (compilation included: a fresh jit per sampler), gradient
evaluations (leapfrog steps, warmup + draws), divergences, min bulk/tail ESS, max R-hat
(ArviZ), ESS per second and ESS per 1000 gradients (load-independent: the machine is
shared), the posterior mean and 90 % interval per parameter, and the load average before
and after. Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import jaxwear as jw  # noqa: E402
from jaxwear._analyses.predict.grid import training_study  # noqa: E402
from jaxwear._analyses.predict.nuts import _arviz, sampling_setup, u_of_samples  # noqa: E402
from jaxwear._inference.calibrate import build_problem, fit, parse_fit  # noqa: E402
from jaxwear._study.study import load_study  # noqa: E402

TARGET_ACCEPT, MAX_DEPTH = 0.85, 8


def boom_problem():
    study = load_study(ROOT / "calibration/boom/study.toml")
    study = dataclasses.replace(study, integrator="adaptive")
    train = training_study(study, 15.0)
    problem = build_problem(train, parse_fit(train, "K_d"))
    return problem, fit(problem)


def write_rig_study(tmp: Path, seed: int = 7) -> Path:
    """Two rig experiments, data at finer numerics than the sampled model (no inverse crime);
    returns the study file's path (`tmp/study.toml`)."""
    rng = np.random.default_rng(seed)
    fine, nodes_fine = dict(nodes=128, steps_per_rev=144), 128
    exps = [("i276", 276.0, (1000.0, 2000.0, 3000.0), 0.052),
            ("b148", 148.0, (2000.0, 3000.0), 0.047)]
    node_deg = np.arange(nodes_fine) * 360.0 / nodes_fine
    angles = np.arange(0.0, 360.0, 3.0) + 0.4
    lines = ['[model]', 'preset = "rig"', '[model.parameters]', 'K_d_per_Pa = 1e-13',
             '[numerics]', 'nodes = 64', 'steps_per_rev = 72', 'revolutions_per_update = 100',
             '[fit]', 'clearance_tolerance_um = 5']
    for name, speed, pts, c in exps:
        p = jw.preset("rig", speed_rpm=speed, clearance_mm=c, K_d_per_Pa=2.2e-13)
        res = jw.simulate(p, jw.ModelConfig(**fine), revolutions=max(pts), snapshots=list(pts),
                          M=25)
        snaps = np.asarray(res.snapshots) * 1e6
        with open(tmp / f"{name}.csv", "w") as f:
            f.write("angle_deg,depth_um,revolutions\n")
            for s, prof in zip(pts, snaps):
                d = np.interp(angles, node_deg, prof, period=360.0)
                y = d + 0.3 * rng.standard_normal(len(d))
                f.writelines(f"{a:.3f},{v:.6f},{s:g}\n" for a, v in zip(angles, y))
        lines += ['[[experiment]]', f'name = "{name}"', f'speed_rpm = {speed}',
                  f'revolutions = {max(pts):g}', 'clearance_mm = 0.05', f'profile = "{name}.csv"']
    (tmp / "study.toml").write_text("\n".join(lines) + "\n")
    return tmp / "study.toml"


def rig_problem(tmp: Path, seed: int = 7):
    study = load_study(write_rig_study(tmp, seed))
    train = training_study(study, 2000.0)
    problem = build_problem(train, parse_fit(train, "K_d,clearance"))
    return problem, fit(problem)


def forward_mode_density(logp):
    """`logp` whose reverse-mode gradient is computed by forward mode (jacfwd)."""

    @jax.custom_vjp
    def f(z):
        return logp(z)

    def f_fwd(z):
        return logp(z), jax.jacfwd(logp)(z)

    def f_bwd(g, ct):
        return (jax.tree.map(lambda x: ct * x, g),)

    f.defvjp(f_fwd, f_bwd)
    return f


def run_numpyro(logp, z0, warmup, draws, chains, seed):
    from numpyro.infer import MCMC, NUTS

    kernel = NUTS(potential_fn=lambda z: -logp(z), dense_mass=True,
                  target_accept_prob=TARGET_ACCEPT, forward_mode_differentiation=True,
                  max_tree_depth=MAX_DEPTH)
    mcmc = MCMC(kernel, num_warmup=warmup, num_samples=draws, num_chains=chains,
                chain_method="sequential", progress_bar=False)
    # NumPyro takes one chain's start unbatched, several with a leading chain axis
    init = z0 if chains == 1 else jax.tree.map(
        lambda a: jnp.broadcast_to(a, (chains, *jnp.shape(a))), z0)
    mcmc.run(jax.random.PRNGKey(seed), init_params=init, extra_fields=("diverging",
                                                                        "num_steps"))
    s = mcmc.get_samples(group_by_chain=True)
    e = mcmc.get_extra_fields(group_by_chain=True)
    # NumPyro counts only the sampling phase in extra fields: warmup gradients are estimated
    # from the sampling phase's mean (reported as such)
    steps = np.asarray(e["num_steps"])
    return (jax.tree.map(np.asarray, s), int(np.sum(e["diverging"])),
            float(steps.sum() * (1 + warmup / draws)), float(steps.mean()))


def run_blackjax(logp, z0, warmup, draws, chains, seed):
    import blackjax

    f = forward_mode_density(logp)
    key = jax.random.PRNGKey(seed)
    out, n_div, n_grad, n_steps_draws = [], 0, 0.0, []

    @jax.jit
    def adapt(key, z):
        wa = blackjax.window_adaptation(blackjax.nuts, f, is_mass_matrix_diagonal=False,
                                        target_acceptance_rate=TARGET_ACCEPT,
                                        max_num_doublings=MAX_DEPTH)
        (state, params), info = wa.run(key, z, num_steps=warmup)
        return state, params, jnp.sum(info.info.num_integration_steps)

    @jax.jit
    def sample(key, state, step_size, imm):
        kern = blackjax.nuts(f, step_size, imm, max_num_doublings=MAX_DEPTH)

        def body(st, k):
            st, info = kern.step(k, st)
            return st, (st.position, info.is_divergent, info.num_integration_steps)

        _, (pos, div, nst) = jax.lax.scan(body, state, jax.random.split(key, draws))
        return pos, div, nst

    for c in range(chains):
        key, k1, k2 = jax.random.split(key, 3)
        state, params, wsteps = adapt(k1, z0)
        pos, div, nst = sample(k2, state, params["step_size"], params["inverse_mass_matrix"])
        out.append(jax.tree.map(np.asarray, pos))
        n_div += int(np.sum(div))
        n_grad += float(wsteps) + float(np.sum(nst))
        n_steps_draws.append(np.asarray(nst))
    samples = {k: np.stack([o[k] for o in out]) for k in out[0]}
    return samples, n_div, n_grad, float(np.mean(n_steps_draws))


def summarize(problem, samples, white, level=0.9):
    names = list(problem.names)
    u = jnp.asarray(u_of_samples(samples, white))
    vals = np.asarray(jax.vmap(jax.vmap(problem.values))(u))
    post = {n.replace("/", ":"): vals[..., i] for i, n in enumerate(names)}
    if "log_noise" in samples:
        post["noise_um"] = np.exp(samples["log_noise"])
    az = _arviz()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        summ = az.summary(az.from_dict(posterior=post), kind="diagnostics")
    a = (1 - level) / 2
    rows = {k: {"r_hat": float(summ.loc[k, "r_hat"]), "ess_bulk": float(summ.loc[k, "ess_bulk"]),
                "ess_tail": float(summ.loc[k, "ess_tail"]), "mean": float(np.mean(v)),
                "lower": float(np.quantile(v, a)), "upper": float(np.quantile(v, 1 - a))}
            for k, v in post.items()}
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=("boom", "rig"), default="boom")
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--chains", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--samplers", default="numpyro,blackjax")
    ap.add_argument("--json", default=None)
    ap.add_argument("--write-rig-study", default=None, metavar="DIR",
                    help="only write the rig case's study (study.toml and CSVs) into DIR")
    a = ap.parse_args(argv)
    if a.write_rig_study:
        Path(a.write_rig_study).mkdir(parents=True, exist_ok=True)
        print(write_rig_study(Path(a.write_rig_study)))
        return None
    with tempfile.TemporaryDirectory() as tmp:
        problem, result = boom_problem() if a.case == "boom" else rig_problem(Path(tmp))
    cov = result.covariance.cov  # the fit's Laplace covariance of u, as predict takes it
    problem, white, logp, z0 = sampling_setup(problem, result, None, cov)
    print(f"case {a.case}: {list(problem.names)} + noise, {problem.n_data} rows; "
          f"warmup {a.warmup}, draws {a.draws}, chains {a.chains}, seed {a.seed}", flush=True)
    report = {"case": a.case, "warmup": a.warmup, "draws": a.draws, "chains": a.chains,
              "seed": a.seed, "samplers": {}}
    runners = {"numpyro": run_numpyro, "blackjax": run_blackjax}
    for name in a.samplers.split(","):
        load0 = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), time.process_time()
        samples, n_div, n_grad, mean_steps = runners[name](logp, z0, a.warmup, a.draws,
                                                           a.chains, a.seed)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        rows = summarize(problem, samples, white)
        ess = min(r["ess_bulk"] for r in rows.values())
        rec = {"wall_s": wall, "cpu_s": cpu, "load_before": load0,
               "load_after": os.getloadavg()[0], "divergences": n_div, "gradients": n_grad,
               "mean_leapfrog_steps_draws": mean_steps, "min_ess_bulk": ess,
               "min_ess_tail": min(r["ess_tail"] for r in rows.values()),
               "max_r_hat": max(r["r_hat"] for r in rows.values()),
               "ess_per_s": ess / wall, "ess_per_1000_gradients": 1000 * ess / n_grad,
               "posterior": rows}
        report["samplers"][name] = rec
        print(f"{name:>9}: {wall:6.0f} s wall ({cpu:.0f} s CPU, load {load0:.1f} → "
              f"{rec['load_after']:.1f}), {n_grad:.0f} gradients "
              f"({mean_steps:.1f} leapfrog/step in draws), {n_div} divergences, "
              f"min ESS bulk {ess:.0f} tail {rec['min_ess_tail']:.0f}, max R-hat "
              f"{rec['max_r_hat']:.3f}; {ess / wall:.2f} ESS/s, "
              f"{rec['ess_per_1000_gradients']:.1f} ESS/1000 gradients", flush=True)
        for k, r in rows.items():
            print(f"           {k}: mean {r['mean']:.4g}, 90 % [{r['lower']:.4g}, "
                  f"{r['upper']:.4g}], R-hat {r['r_hat']:.3f}, ESS {r['ess_bulk']:.0f}",
                  flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
