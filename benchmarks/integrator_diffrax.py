"""diffrax vs the hand-written adaptive wear loop (issue 9): wall time, steps, error.

    python benchmarks/integrator_diffrax.py [--nodes 64] [--steps 72] [--revolutions 10000]
                                            [--atol-um 1e-3,1e-4] [--no-reference]

The rig (276 r/min, no effects, unsymmetric contact) integrated in the cycle count N:
dh/dN = one cycle's Archard wear on the frozen profile (`cycle_increment`).

- hand: `jaxwear` default (`wear_loop`, Bogacki-Shampine 3(2), *global* signed error
  control at `wear_tolerance_um`, warm-started Newton, two-level checkpointed scan).
- diffrax: `diffeqsolve` with `Bosh3` (the same pair) and `Tsit5`, `PIDController` with
  rtol = 0 and atol in µm on the max norm (diffrax controls the *local* error per step; the
  global signed budget of the hand loop is not expressible with its controllers), cold
  Newton start in every evaluation (a vector field has no state to carry a warm start),
  `RecursiveCheckpointAdjoint` (diffrax's default) for the gradient.

Both: the max error against eq 23 at M = 1 (% of peak), accepted (+rejected) steps, wall
time of a jitted forward and of `jax.grad` of a scalar loss (Σ h³ / Σ h² over (K_d, c)),
medians of 3 after a warm-up. Prints a markdown table; the load average is printed with it
(2 shared cores: timings are noisy).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxwear as jw
from jaxwear._physics.adaptive import DEFAULT_WEAR_TOLERANCE_UM
from jaxwear._physics.config import boom_config
from jaxwear._physics.cycle import cycle_increment
from jaxwear._physics.load import load_history
from jaxwear._physics.schedule import crank_segments, duty_segments
from jaxwear._physics.wear import build_schedule, wear_loop


def timed(f, *a, reps=3):
    jax.block_until_ready(f(*a))  # warm-up (compile)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*a))
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def loss_of(depth_fn):
    def f(x, p0):
        p = p0.with_values({"K_d_per_Pa": x[0], "clearance_mm": x[1]})
        h = depth_fn(p) * 1e6
        return jnp.sum(h**3) / jnp.sum(h**2)
    return f


def diffrax_depth(cfg, segments, solver, atol_um, max_steps=4096):
    """One `diffeqsolve` per duty-regime piece (the rate jumps between them)."""
    def depth(p):
        hist = load_history(p, cfg)

        def vf(N, h, reg):
            return cycle_increment(p, cfg, hist, reg, h, jnp.zeros(()))[0]

        h, acc, rej, t = jnp.zeros(cfg.nodes), 0, 0, 0.0
        for reg, n in segments:
            sol = diffrax.diffeqsolve(
                diffrax.ODETerm(vf), solver, t, t + n, n / 64, h, args=reg,
                saveat=diffrax.SaveAt(ts=jnp.asarray([t + n / 2, t + n])),
                stepsize_controller=diffrax.PIDController(
                    rtol=0.0, atol=atol_um * 1e-6, norm=lambda y: jnp.max(jnp.abs(y))),
                max_steps=max_steps)
            h, t = sol.ys[-1], t + n
            acc = acc + sol.stats["num_accepted_steps"]
            rej = rej + sol.stats["num_rejected_steps"]
        return h, acc, rej
    return depth


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=64)
    ap.add_argument("--steps", type=int, default=72)
    ap.add_argument("--revolutions", type=float, default=10000)
    ap.add_argument("--atol-um", default="1e-3,1e-4")
    ap.add_argument("--boom", action="store_true", help="the boom, 25 h, K_d 3.8e-13")
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the M = 1 reference (use the hand loop at 1e-5 µm instead)")
    args = ap.parse_args(argv)
    if args.boom:  # issue 9's boom: fitted K_d, 25 h of the paper's duty cycle
        p0 = jw.preset("boom", K_d_per_Pa=3.8e-13)
        cfg = boom_config(nodes=args.nodes, steps_per_rev=args.steps)
        rev = 25.0
        segments = duty_segments(cfg.duty_cycle, rev, float(p0.swing_period))[0]
        run = {"hours": rev}
    else:
        p0 = jw.preset("rig")
        cfg = jw.ModelConfig(nodes=args.nodes, steps_per_rev=args.steps)
        rev = args.revolutions
        segments = crank_segments(rev)
        run = {"revolutions": rev}
    x0 = jnp.asarray([float(p0.get("K_d_per_Pa")), float(p0.get("clearance_mm"))])
    what = "boom 25 h" if args.boom else f"rig {rev:g} rev"
    print(f"{what}, {args.nodes} nodes x {args.steps} steps/rev, "
          f"load {os.getloadavg()[0]:.2f}", flush=True)

    t0 = time.perf_counter()
    if args.no_reference:
        ref = np.asarray(jw.simulate(p0, cfg, tolerance_um=1e-5, **run).depth)
        ref_name = "hand loop at 1e-5 µm"
    else:
        ref = np.asarray(jw.simulate(p0, cfg, M=1, **run).depth)
        ref_name = "eq 23 at M = 1"
    peak = ref.max()
    print(f"reference ({ref_name}): peak {peak * 1e6:.4f} µm, "
          f"{time.perf_counter() - t0:.1f} s", flush=True)

    rows = []
    sched = build_schedule(p0, cfg, **run)

    def hand(p):
        r = wear_loop(p, cfg, sched)
        return r.depth, r.steps, r.rejected_steps

    cases = [("hand loop (BS3, global)", f"{DEFAULT_WEAR_TOLERANCE_UM:g} µm global", hand)]
    for a in [float(s) for s in args.atol_um.split(",")]:
        for name, solver in (("diffrax Bosh3", diffrax.Bosh3()),
                             ("diffrax Tsit5", diffrax.Tsit5())):
            cases.append((name, f"atol {a:g} µm local", diffrax_depth(cfg, segments, solver, a)))

    for name, tol, depth in cases:
        t0 = time.perf_counter()
        fwd = eqx.filter_jit(depth)
        h, acc, rej = fwd(p0)
        first = time.perf_counter() - t0
        err = float(np.max(np.abs(np.asarray(h) - ref)) / peak)
        t_f = timed(fwd, p0)
        loss = loss_of(lambda p: depth(p)[0])
        g = eqx.filter_jit(jax.grad(loss))
        t_g = timed(g, x0, p0)
        rows.append((name, tol, f"{int(acc)} (+{int(rej)})", f"{100 * err:.4f} %",
                     f"{t_f:.3f}", f"{t_g:.3f}", f"{t_g / t_f:.2f}", f"{first:.1f}"))
        print(" | ".join(rows[-1]), flush=True)

    print(f"\n{what}, {args.nodes}x{args.steps}, error vs {ref_name}, "
          f"load {os.getloadavg()[0]:.2f} (end)")
    print("| integrator | tolerance | steps (+rejected) | max error, % of peak | forward s | "
          "grad s | grad/forward | first call s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
