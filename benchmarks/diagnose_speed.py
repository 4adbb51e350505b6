"""How long `diagnose` takes on a 5-experiment full-circumference study (issue 10, Speed).

    python benchmarks/diagnose_speed.py [--case null|running_in|outside|...] [--nodes 360]
        [--steps 360] [--integrator paper|adaptive] [--M 100] [--fine-nodes 540]
        [--fine-steps 540] [--fine-M 50] [--json FILE]

The study: the paper's rig matrix (5 experiments, interrupted at 2000/5000/10000/15000
revolutions), profiles every 2° around the whole bore, Gaussian noise (0.3 µm) on every
point, zero-mean (negative depths outside the scar included). The truth is made by
`jaxwear synth` noise-free at finer numerics than the study states (`--fine-*`: the
discretisation mismatch a real part brings), the noise is added here, and the study is
diagnosed at `--nodes` x `--steps` (default 360 x 360) with eq 23 at `--M` (default 100,
`--integrator paper`, as docs/performance.md's table) or the adaptive integrator at its default
tolerance (`--integrator adaptive`, the package default for a study without numerics).

Printed: wall and process CPU time of `diagnose` (compilation included: a fresh process;
on a shared machine CPU time / cores is the better guide to the unloaded wall time), the
number of model evaluations and the time spent in them, the time of the last evaluation
that compiled, the verdict, and the load average (`os.getloadavg`) before and after,
since the machine may be shared. Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

HIDDEN = {"null": [], "running_in": ["running_in"], "speed_dependence": ["speed_dependence"],
          "friction": ["friction"], "creep": ["creep"],
          "pressure_exponent": ["pressure_exponent"], "unsymmetric": ["unsymmetric"],
          "outside": []}  # null truth plus wear no candidate makes (see `make_study`)


def make_study(case: str, *, nodes: int, steps: int, M: float, fine: tuple, noise_um: float,
               seed: int, angle_step_deg: float = 2.0, cache: str | None = None,
               integrator: str = "paper"):
    """The full-scan noisy study (in memory) and the truth."""
    from jaxwear._analyses.synth import synthesize
    from jaxwear._study.study import Profile

    fn, fs, fm = fine
    tag = "+".join(HIDDEN[case]) or "null"
    cached = Path(cache) / f"truth-{tag}-{seed}-{fn}x{fs}-M{fm:g}.pickle" if cache else None
    if cached is not None and cached.exists():
        with open(cached, "rb") as f:
            res = pickle.load(f)
    else:
        res = synthesize(HIDDEN[case], "paper", noise_um=0.0, seed=seed,
                         numerics=dict(nodes=fn, steps_per_rev=fs, revolutions_per_update=fm),
                         angle_step_deg=angle_step_deg)
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            with open(cached, "wb") as f:
                pickle.dump(res, f)
    rng = np.random.default_rng(seed + 1000)
    ang = np.arange(0.0, 360.0, angle_step_deg)
    exps = []
    for e in res.study.experiments:
        p = e.profile
        rows_a, rows_d, rows_r = [], [], []
        for rev in sorted(set(p.revolutions.tolist())):
            m = p.revolutions == rev
            truth = np.zeros(len(ang))  # outside the scar the true depth is zero
            idx = np.rint(np.degrees(p.angle[m]) / angle_step_deg).astype(int) % len(ang)
            truth[idx] = p.depth[m] * 1e6
            if case == "outside":
                # physics outside the library: a narrow pit 40° past the deepest point,
                # growing with revolutions (1 µm per 10⁴ rev, 4° wide)
                a0 = ang[np.argmax(truth)] + 40.0
                d = (ang - a0 + 180.0) % 360.0 - 180.0
                truth = truth + rev / 1e4 * np.exp(-0.5 * (d / 4.0) ** 2)
            rows_a.append(np.radians(ang))
            rows_d.append((truth + noise_um * rng.standard_normal(len(ang))) * 1e-6)
            rows_r.append(np.full(len(ang), rev))
        prof = Profile(np.concatenate(rows_a), np.concatenate(rows_d), np.concatenate(rows_r),
                       "")
        exps.append(replace(e, profile=prof))
    st = replace(res.study, experiments=tuple(exps), revolutions_per_update=float(M),
                 integrator=integrator, path=Path(f"benchmark-{case}"))
    return st.with_config(nodes=nodes, steps_per_rev=steps), res.truth


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="null", choices=sorted(HIDDEN))
    ap.add_argument("--nodes", type=int, default=360)
    ap.add_argument("--steps", type=int, default=360)
    ap.add_argument("--M", type=float, default=100.0)
    ap.add_argument("--integrator", default="paper", choices=("paper", "adaptive"))
    ap.add_argument("--fine-nodes", type=int, default=540)
    ap.add_argument("--fine-steps", type=int, default=540)
    ap.add_argument("--fine-M", type=float, default=50.0)
    ap.add_argument("--noise-um", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", help="append the result as one JSON line to this file")
    ap.add_argument("--truth-cache", help="folder to keep the noise-free truth in between runs")
    ap.add_argument("--compilation-cache", help="JAX persistent compilation cache folder (as "
                    "the CLI uses one): a second run with the same shapes skips compiling")
    a = ap.parse_args(argv)

    import jax

    import jaxwear  # noqa: F401  (float64)

    if a.compilation_cache:
        jax.config.update("jax_compilation_cache_dir", a.compilation_cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    from jaxwear._analyses.diagnose import Model, diagnose

    load0 = os.getloadavg()
    t = time.perf_counter()
    study, truth = make_study(a.case, nodes=a.nodes, steps=a.steps, M=a.M,
                              fine=(a.fine_nodes, a.fine_steps, a.fine_M),
                              noise_um=a.noise_um, seed=a.seed, cache=a.truth_cache,
                              integrator=a.integrator)
    t_synth = time.perf_counter() - t
    n0, s0 = Model.evaluations, Model.evaluation_s
    t, cpu = time.perf_counter(), time.process_time()
    d = diagnose(study, verbose=True)
    wall = time.perf_counter() - t
    cpu = time.process_time() - cpu
    n, s = Model.evaluations - n0, Model.evaluation_s - s0
    out = {"case": a.case, "status": d.status, "effects": d.effects, "wall_s": round(wall, 1),
           "cpu_s": round(cpu, 1),
           "evaluations": n, "evaluation_s": round(s, 1),
           "first_evaluation_s": round(Model.first_evaluation_s, 1),
           "grid": f"{a.nodes}x{a.steps}, " + (f"M={a.M:g}" if a.integrator == "paper"
                                                 else "adaptive"),
           "truth_grid": f"{a.fine_nodes}x{a.fine_steps}, M={a.fine_M:g}",
           "rows": d.model.n, "noise_um": round(d.noise_um, 4),
           "synth_s": round(t_synth, 1), "hidden": truth["hidden"],
           "load_before": [round(x, 2) for x in load0],
           "load_after": [round(x, 2) for x in os.getloadavg()],
           "cpus": os.cpu_count(), "compilation_cache": bool(a.compilation_cache)}
    print(json.dumps(out))
    if a.json:
        with open(a.json, "a", encoding="utf-8") as f:
            f.write(json.dumps(out) + "\n")
    return 0 if math.isfinite(wall) else 1


if __name__ == "__main__":
    sys.exit(main())
