"""Calibration engines compared on one problem in one process: host Levenberg-Marquardt
(`engine="lm"`) against `optimistix.LevenbergMarquardt` (`engine="optimistix"`).

The problem is `run.py`'s synthetic rig matrix (5 experiments, K_d and 5 clearances with the
default 5 µm prior, 2 fit passes). Each engine is timed on its first `fit` in the process
(cold: includes whatever it compiles that an earlier engine did not) and on a repeat (cached).
Run it twice with the order swapped to see each engine cold:

    python benchmarks/calibrate_engines.py --nodes 64 --steps 72 --order lm,optimistix
    python benchmarks/calibrate_engines.py --nodes 64 --steps 72 --order optimistix,lm

`optimistix-inline` is the optimistix engine with the model traced into its own jit (one more
compile of the wear loop; for comparison only); `optimistix:ATOL` sets its absolute
tolerance. Prints one line per run and a JSON summary.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import run as bench  # noqa: E402

from jaxwear import _calibrate as cal  # noqa: E402
from jaxwear._study import load_study  # noqa: E402


def one_fit(study_path, engine, tol=None):
    """fit() of a freshly built problem: (result, wall s, cpu s, model evaluations)."""
    calls = [0]
    orig_eval = cal.evaluate
    orig_optx = cal._fit_optimistix

    def counting(*a, **k):
        calls[0] += 1
        return orig_eval(*a, **k)

    cal.evaluate = counting
    kw = {} if tol is None else {"rtol": tol[0], "atol": tol[1]}
    if ":" in engine:  # optimistix:ATOL
        engine, atol = engine.split(":")
        kw["atol"] = float(atol)
    if engine == "optimistix-inline":
        kw["inline"] = True
    cal._fit_optimistix = functools.partial(orig_optx, **kw)
    try:
        study = load_study(study_path)
        problem = cal.build_problem(study, cal.with_registration(
            study, cal.parse_fit(study, "K_d,clearance")))
        t0, c0 = time.perf_counter(), time.process_time()
        res = cal.fit(problem, engine="optimistix" if engine.startswith("optimistix")
                      else engine)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        cal.evaluate, cal._fit_optimistix = orig_eval, orig_optx
    return res, wall, cpu, calls[0]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=64)
    ap.add_argument("--steps", type=int, default=72)
    ap.add_argument("--M", type=int, default=500)
    ap.add_argument("--order", default="lm,optimistix")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--optx-tol", default=None,
                    help="optimistix rtol,atol (default: the engine's)")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="jaxwear-engines-"))
    study = bench.write_synthetic_study(tmp, args.nodes, args.steps, args.M)
    print(f"# {args.nodes} nodes x {args.steps} steps/rev, M = {args.M}, order {args.order}, "
          f"load {os.getloadavg()[0]:.2f}", flush=True)
    out, first = {}, None
    for engine in args.order.split(","):
        runs = []
        for rep in range(args.repeats):
            tol = None if args.optx_tol is None else [float(x) for x in
                                                      args.optx_tol.split(",")]
            res, wall, cpu, evals = one_fit(study, engine, tol)
            cost = 0.5 * float(np.sum(res.residuals_um ** 2))
            runs.append({"wall_s": wall, "cpu_s": cpu, "evaluations": evals,
                         "iterations": res.iterations, "cost_um2": cost, "converged": res.converged,
                         "load": os.getloadavg()[0]})
            print(f"{engine:18s} {'cold' if rep == 0 else 'cached'}: {wall:7.2f} s "
                  f"({cpu:7.2f} s cpu), "
                  f"{evals:3d} model evaluations, cost ½Σr² {cost:.8f} µm², "
                  f"converged {res.converged} ({res.message}); load "
                  f"{os.getloadavg()[0]:.2f}", flush=True)
        if first is None:
            first = res
        else:
            dse = np.abs(res.values - first.values) / first.stderr
            print(f"  |Δ value| / SE vs {args.order.split(',')[0]}: max {np.max(dse):.2e}; "
                  f"SE ratio - 1: max {np.max(np.abs(res.stderr / first.stderr - 1)):.2e}; "
                  f"flags {res.flags == first.flags}")
        out[engine] = runs
    print(json.dumps(out))


if __name__ == "__main__":
    main()
