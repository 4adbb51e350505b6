"""XLA:CPU compiler options for jaxwear's programs: compile CPU time against run CPU time.

Each variant is a set of per-program options added to `jaxwear._core.jit.LEGACY_EMITTERS`,
forced on every jaxwear program (`jit.options`); "base" is the legacy emitters alone, "O1"
what jaxwear adopted (`jit.FAST_COMPILE`: LLVM's O1, and O0 for its `once` programs, which
every variant that sets a level gets). Every measurement is a fresh process
(no persistent cache: nothing is compiled before), variants interleaved round by round, and
process CPU time (all threads), not wall: a loaded machine slows wall time by whatever else
runs, CPU time much less. Per process:

- the rig, 276 r/min, 10 000 rev at 360 x 360, and the boom's 25 h duty cycle (K_d 3.8e-13)
  at 360 x 360, both through `jw.simulate` with the default adaptive integrator;
- a Jacobian program as a fit compiles one (`jax.jacfwd` of the rig's 360-node profile in
  K_d and clearance through the wear loop, forward mode as `_inference.evaluation`);

XLA's compile CPU time of each program (`backend_compile_and_load`, the part the options can
change; tracing and lowering are not) and the median run CPU time of its repeats. The depth
profiles and the Jacobian are compared with the first variant's (max relative difference).
`--cases` picks some of `rig,boom,jacobian` (LLVM's O0 runs the boom's 25 h for minutes).

`--cli ARGS...` instead times one command line per variant in a fresh process (CPU time of
the process, XLA's compile CPU summed). Usage:

    python benchmarks/compile_options.py --rounds 3 --variants base,O1
    python benchmarks/compile_options.py --rounds 2 --variants base,O1 \
        --cli calibrate S.toml --fit K_d,clearance --out '{out}'

(`{out}`: a fresh output folder per run.) Results: benchmarks/TIME_TO_ANSWER.md.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

VARIANTS = {
    "base": {},
    "O1": {"xla_backend_optimization_level": 1},
    "O0": {"xla_backend_optimization_level": 0},
    "cheap": {"xla_llvm_disable_expensive_passes": True},
    "O1cheap": {"xla_backend_optimization_level": 1, "xla_llvm_disable_expensive_passes": True},
    "split1": {"xla_cpu_parallel_codegen_split_count": 1},
    "noinline": {"xla_llvm_force_inline_before_split": False},
    "default": None,  # no options forced: what jaxwear asks for by itself
    "ratesO0": {},  # LLVM's O0 for the work estimate's small rate programs only (_child)
}
RATES_O0 = {"xla_backend_optimization_level": 0}

# Installed in the child before jaxwear compiles anything: XLA's compile CPU per program.
_PATCH = r"""
import time
from jax._src import compiler as _c
COMPILES = []
_orig = _c.backend_compile_and_load
def _timed(backend, module, *a, **k):
    c0, w0 = time.process_time(), time.perf_counter()
    out = _orig(backend, module, *a, **k)
    COMPILES.append((str(module.operation.attributes["sym_name"]).strip('"'),
                     time.process_time() - c0, time.perf_counter() - w0))
    return out
_c.backend_compile_and_load = _timed
"""


def _child(variant: str, cli: list[str] | None, out: Path, cases: list[str]) -> None:
    ns: dict = {}
    exec(_PATCH, ns)
    compiles = ns["COMPILES"]
    from jaxwear._core import jit as J

    opts = (J.current_options() if VARIANTS[variant] is None
            else {**J.LEGACY_EMITTERS, **VARIANTS[variant]})
    if variant == "ratesO0":
        from jaxwear._inference import attempts
        from jaxwear._physics import adaptive
        for prog in (attempts._experiment_rates, adaptive._regime_rates_jit):
            prog.variant = lambda o, _v=prog.variant: _v({**o, **RATES_O0} if o else o)
    if cli is not None:
        from jaxwear import cli as C
        c0 = time.process_time()
        with J.options(opts) if VARIANTS[variant] is not None else contextlib.nullcontext():
            rc = C.main(cli)
        doc = {"cpu": time.process_time() - c0, "rc": rc,
               "xla_cpu": sum(c[1] for c in compiles), "n_compiles": len(compiles),
               "largest": sorted(([c[0], round(c[1], 3)] for c in compiles),
                                 key=lambda c: -c[1])[:8]}
        out.write_text(json.dumps(doc))
        return

    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxwear as jw
    from jaxwear._physics.config import boom_config
    from jaxwear._physics.wear import build_schedule, wear_loop

    # for the whole process: the context manager is held, since a discarded one is closed
    # at once (its generator's `finally` pops the options again)
    held = J.options(opts)
    held.__enter__()
    assert J.current_options() == opts, J.current_options()
    doc: dict = {"options": opts}
    arrays = {}

    def timed(name, f, repeats):
        n0 = len(compiles)
        c0 = time.process_time()
        r = jax.block_until_ready(f())
        first = time.process_time() - c0
        runs = []
        for _ in range(repeats):
            c0 = time.process_time()
            jax.block_until_ready(f())
            runs.append(time.process_time() - c0)
        mine = compiles[n0:]
        doc[name] = {"xla_compile_cpu": sum(c[1] for c in mine),
                     "programs": [c[0] for c in mine], "first_cpu": first,
                     "run_cpu": statistics.median(runs)}
        return r

    cfg = jw.ModelConfig(nodes=360, steps_per_rev=360)
    rig = jw.preset("rig")
    if "rig" in cases:
        r = timed("rig", lambda: jw.simulate(rig, cfg, revolutions=10_000), 5)
        arrays["rig"] = np.asarray(r.depth)
    if "boom" in cases:
        boom = jw.preset("boom", K_d_per_Pa=3.8e-13)
        r = timed("boom", lambda: jw.simulate(boom, boom_config(nodes=360, steps_per_rev=360),
                                              hours=25.0), 3)
        arrays["boom"] = np.asarray(r.depth)

    sched = build_schedule(rig, cfg, revolutions=10_000)
    x0 = jnp.asarray([float(rig.get("K_d_per_Pa")), float(rig.get("clearance_mm"))])

    def profile(x):
        q = rig.with_values({"K_d_per_Pa": x[0], "clearance_mm": x[1]})
        return wear_loop(q, cfg, sched).depth * 1e6

    jac = J.jit(jax.jacfwd(profile))
    if "jacobian" in cases:
        arrays["jacobian"] = np.asarray(timed("jacobian", lambda: jac(x0), 3))
    np.savez(out.with_suffix(".npz"), **arrays)
    out.write_text(json.dumps(doc))


def _rel(a, b) -> float:
    import numpy as np
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default="base,O1,cheap,O1cheap")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--cases", default="rig,boom,jacobian")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--json", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--cli", nargs=argparse.REMAINDER, default=None,
                    help="time this command line (jaxwear's arguments) instead")
    args = ap.parse_args(argv)
    if args.child:
        _child(args.child, args.cli, Path(args.json), args.cases.split(","))
        return 0

    import numpy as np

    names = args.variants.split(",")
    tmp = Path(tempfile.mkdtemp(prefix="jaxwear-copts-"))
    env = {**os.environ, "JAXWEAR_NO_CACHE": "1", "PYTHONPATH": str(ROOT)}
    env.pop("XLA_FLAGS", None)
    res: dict[str, list[dict]] = {n: [] for n in names}
    for k in range(args.rounds):
        for n in names:
            out = tmp / f"{n}-{k}.json"
            cmd = [sys.executable, __file__, "--child", n, "--json", str(out),
                   "--cases", args.cases]
            if args.cli is not None:
                cli = [a.replace("{out}", str(tmp / f"out-{n}-{k}")) for a in args.cli]
                cmd += ["--cli", *cli]
            load = os.getloadavg()[0]
            subprocess.run(cmd, env=env, check=True, cwd=ROOT,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            doc = json.loads(out.read_text())
            doc["load"] = load
            res[n].append(doc)
            print(f"round {k} {n}: load {load:.1f} " + json.dumps(
                {c: ({kk: round(v, 3) for kk, v in doc[c].items() if isinstance(v, float)}
                     if isinstance(doc[c], dict) else doc[c]) for c in doc
                 if c not in ("options",)}), flush=True)
    med = statistics.median
    print(f"\nmedians over {args.rounds} rounds (CPU seconds; ratio to {names[0]}); "
          f"load {min(d['load'] for v in res.values() for d in v):.1f}-"
          f"{max(d['load'] for v in res.values() for d in v):.1f}")
    if args.cli is not None:
        b = med(d["cpu"] for d in res[names[0]])
        bx = med(d["xla_cpu"] for d in res[names[0]])
        for n in names:
            c, x = med(d["cpu"] for d in res[n]), med(d["xla_cpu"] for d in res[n])
            print(f"{n}: process cpu {c:.1f} ({c / b:.3f}), xla compile cpu {x:.1f} "
                  f"({x / bx:.3f}), rc {[d['rc'] for d in res[n]]}")
        return 0
    ref = np.load(tmp / f"{names[0]}-0.npz")
    for n in names:
        line = [n]
        for case in args.cases.split(","):
            comp = med(d[case]["xla_compile_cpu"] for d in res[n])
            run = med(d[case]["run_cpu"] for d in res[n])
            comp0 = med(d[case]["xla_compile_cpu"] for d in res[names[0]])
            run0 = med(d[case]["run_cpu"] for d in res[names[0]])
            diff = max(_rel(np.load(tmp / f"{n}-{k}.npz")[case], ref[case])
                       for k in range(args.rounds))
            line.append(f"{case}: compile {comp:.2f} ({comp / comp0:.2f}) run {run:.4f} "
                        f"({run / run0:.3f}) maxrel {diff:.1e}")
        print(" | ".join(line))
    return 0


if __name__ == "__main__":
    sys.exit(main())
