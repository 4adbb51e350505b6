"""Where the time of one rig prediction goes: the wear loop timed piece by piece.

    /work/venv/bin/python benchmarks/profile_forward.py [--nodes 360] [--steps 360] [--M 500]

Each piece is jitted on its own and timed after a warm-up call (median of repeats, wall and
process CPU time): the load history, one cycle's contact + wear increment from a cold start
and from the wear loop's warm start, one semi-smooth Newton iteration of the 2-D contact
solve, and the whole loop. The loop's cost per update minus a warm increment is the loop's
own overhead (carry updates, checkpointing, the padding `cond`).
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxwear as jw
from jaxwear._physics import contact as _contact
from jaxwear._physics.cycle import cycle_increment, node_area
from jaxwear._physics.wear import build_schedule, wear_loop


def timeit(f, *args, repeats=7):
    """Median wall and CPU seconds of `f(*args)` after one warm-up (compile) call."""
    jax.block_until_ready(f(*args))
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(f(*args))
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=360)
    ap.add_argument("--steps", type=int, default=360)
    ap.add_argument("--M", type=float, default=500)
    ap.add_argument("--revolutions", type=float, default=10000)
    args = ap.parse_args(argv)

    p = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=args.nodes, steps_per_rev=args.steps)
    sched = build_schedule(p, cfg, revolutions=args.revolutions, M=args.M, pad=False)
    half = build_schedule(p, cfg, revolutions=args.revolutions / 2, M=args.M, pad=False)
    U = sched.updates
    rows = []

    def row(name, wc, note=""):
        rows.append((name, wc[0], wc[1], note))
        print(f"{name:<44} {wc[0] * 1e3:9.2f} ms wall {wc[1] * 1e3:9.2f} ms cpu  {note}",
              flush=True)

    loop = jax.jit(lambda p, s: wear_loop(p, cfg, s).depth)
    full = timeit(loop, p, sched, repeats=5)
    row(f"wear_loop, {U} updates", full)
    row("  per update", (full[0] / U, full[1] / U))

    hist = jax.jit(lambda p: jw.load_history(p, cfg))(p)
    row("load_history (SCLA, 2 passes)", timeit(jax.jit(lambda p: jw.load_history(p, cfg).load),
                                                 p))
    # Mid-run profiles: half-way and one update later (what a warm start sees).
    h_a = loop(p, half)
    h_b = h_a + (loop(p, build_schedule(p, cfg, revolutions=args.revolutions / 2 + args.M,
                                        M=args.M, pad=False)) - h_a)

    cold = jax.jit(lambda p, h: cycle_increment(p, cfg, hist, 0, h, jnp.zeros(())))
    sol_a = cold(p, h_a)[2]
    its_cold = int(cold(p, h_b)[2].iterations)
    row("cycle_increment, cold start (mid-run h)", timeit(cold, p, h_b),
        f"{its_cold} Newton its (max over steps)")

    ang = hist.angle[0]
    u = jnp.stack([jnp.cos(ang), jnp.sin(ang)], 1)
    grown = _contact.interp_periodic(h_b - h_a, ang)
    start = sol_a.offset + grown[:, None] * u
    warm = jax.jit(lambda p, h, s: cycle_increment(p, cfg, hist, 0, h, jnp.zeros(()), s))
    its_warm = int(warm(p, h_b, start)[2].iterations)
    row("cycle_increment, warm start (as in the loop)", timeit(warm, p, h_b, start),
        f"{its_warm} Newton its")

    # The kernel every Newton iteration runs (written here, independent of the solver's
    # internals): penetrations d_ij = e_i·n_j - g_j, p_ij A_j = kA_j max(d_ij, 0) and the
    # force sums Σ_j p_ij A_j n_j, for all steps × nodes. A Newton iteration needs it about
    # twice (forces at the trial point, then the 2x2 Hessian sums).
    k = _contact.stiffness_per_area(h_b, p, False)
    th = 2 * np.pi * np.arange(cfg.nodes) / cfg.nodes
    nx, ny = jnp.asarray(np.cos(th))[None], jnp.asarray(np.sin(th))[None]
    g = (p.clearance + h_b)[None]
    kA = (k * node_area(p, cfg.nodes))[None]

    @jax.jit
    def kernel(e):
        d = e[:, :1] * nx + e[:, 1:] * ny - g
        q = jnp.where(d > 0, kA * d, 0.0)
        return jnp.stack([jnp.sum(q * nx, 1), jnp.sum(q * ny, 1)], 1)

    kern = timeit(kernel, start, repeats=15)
    row("force kernel Σ_j kA max(e·n-g,0) n_j", kern,
        f"{args.steps}x{args.nodes}: {args.steps * args.nodes / kern[1] / 1e6:.0f} M "
        f"node-evals per CPU s")
    inc = timeit(warm, p, h_b, start)
    notes = [f"a warm cycle increment costs {inc[1] / kern[1]:.1f} force kernels "
             f"({its_warm} Newton iterations)"]
    notes.append(f"the loop costs {full[1] / U * 1e3:.2f} ms cpu per update, a standalone warm "
                 f"increment {inc[1] * 1e3:.2f} ms: the loop's own work (carry, checkpointing, "
                 f"the padding cond) is "
                 + ("not measurable" if full[1] / U < 1.1 * inc[1] else
                    f"{(full[1] / U - inc[1]) * 1e3:.2f} ms per update"))
    for n in notes:
        print(n, flush=True)
    return rows, notes


if __name__ == "__main__":
    main()
