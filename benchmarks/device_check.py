"""The kernel and a batched sweep on whatever device JAX picks (a GPU where there is one),
against answers computed on the CPU beforehand.

    python benchmarks/device_check.py --save ref.npz          # here, on the CPU
    python benchmarks/device_check.py --against ref.npz       # on the GPU machine

Prints, for the rig (10 000 rev) and the boom (25 h) with the default adaptive integrator
and for the rig with eq 23 at M = 500, all at `--nodes` x `--nodes`: the first call
(compile and run), the median of repeats after it, steps, and the largest difference
from the CPU's answer in µm (the same float64 arithmetic in another order: round-off,
and where the adaptive controller takes another step, about its tolerance). Then a
`jaxwear.sweep` of `--side`² speed x clearance points (eq 23, M = 500, 120 x 120) with
its default method for the device, against single calls (a few, scaled up). Not a
test: one-shot figures for docs/performance.md.
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import numpy as np

import jaxwear as jw
from jaxwear._physics.config import boom_config


def timed(fn, repeats):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return out, first, statistics.median(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=360)
    ap.add_argument("--side", type=int, default=16)
    ap.add_argument("--save", default=None, help="write the answers here (.npz)")
    ap.add_argument("--against", default=None, help="compare with these answers (.npz)")
    ap.add_argument("--skip-boom", action="store_true")
    args = ap.parse_args(argv)
    n = args.nodes
    print(f"jax {jax.__version__}, devices {jax.devices()}, x64 "
          f"{jax.config.jax_enable_x64}", flush=True)
    ref = dict(np.load(args.against)) if args.against else {}
    got = {}
    rig, cfg = jw.preset("rig"), jw.ModelConfig(nodes=n, steps_per_rev=n)
    cases = {"rig adaptive": (lambda: jw.simulate(rig, cfg, revolutions=10000), 5),
             "rig eq23 M500": (lambda: jw.simulate(rig, cfg, revolutions=10000, M=500), 5)}
    if not args.skip_boom:
        boom = jw.preset("boom", K_d_per_Pa=3.8e-13)
        bcfg = boom_config(nodes=n, steps_per_rev=n)
        cases["boom adaptive"] = (lambda: jw.simulate(boom, bcfg, hours=25), 3)
    for name, (fn, reps) in cases.items():
        r, first, med = timed(fn, reps)
        h = np.asarray(r.depth)
        got[name] = h
        diff = (f", max |h - h_cpu| {np.max(np.abs(h - ref[name])) * 1e6:.2e} µm"
                if name in ref else "")
        print(f"{name}: first {first:.2f} s, median {med:.4f} s, steps {int(r.steps)} "
              f"(+{int(r.rejected_steps)}), peak {h.max() * 1e6:.4f} µm{diff}", flush=True)
    side = args.side
    speeds = np.linspace(148.0, 276.0, side)
    clear = np.linspace(0.05, 0.15, side)
    scfg = jw.ModelConfig(nodes=120, steps_per_rev=120)

    def sweep():
        return jw.sweep(rig, scfg, {"speed_rpm": speeds, "clearance_mm": clear},
                        revolutions=10000, M=500).depth_um

    out, first, med = timed(sweep, 3)
    got["sweep"] = np.asarray(out)
    k = min(8, side * side)

    def singles():
        # `with_values` takes SI values (rad/s, m), the sweep's grid the keys' units
        return [jw.simulate(rig.with_values({"speed_rpm": s * np.pi / 30,
                                             "clearance_mm": c * 1e-3}), scfg,
                            revolutions=10000, M=500).depth
                for s, c in zip(np.repeat(speeds, side)[:k], np.tile(clear, side)[:k])]

    _, s_first, s_med = timed(singles, 3)
    per = s_med / k
    diff = (f", max |Δ| vs CPU {np.max(np.abs(got['sweep'] - ref['sweep'])):.2e} µm"
            if "sweep" in ref else "")
    print(f"sweep {side}x{side} (120 x 120, eq 23 M 500): first {first:.2f} s, median "
          f"{med:.3f} s; single calls {per * 1e3:.2f} ms each ({k} timed), "
          f"{side * side} of them {per * side * side:.3f} s: batched "
          f"{per * side * side / med:.1f}x{diff}", flush=True)
    if args.save:
        np.savez(args.save, **got)


if __name__ == "__main__":
    main()
