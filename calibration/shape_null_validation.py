"""False alarms of the shape of the missing wear on null studies (issue 25: a null that holds
its α at any numerics the user sets).

Each seed: a null study (nothing hidden) made by the independent generator
(`benchmarks/hidden_physics.py`) at finer numerics than the fit, whole-bore scans with
0.3 µm noise, clearance tolerances; diagnosed with `--shape` in this process (the compiled
models are shared by the seeds). A false alarm is a shape analysis that names a variable
(`best` not null). Two numerics: the study's grid left to jaxwear (auto, design.md §6), and a
coarse grid the user sets (`--coarse`), where the model's own discretisation misfit is
largest. The rate is compared with the family-wise α = 1e-3 by its Clopper-Pearson
interval.

    python calibration/shape_null_validation.py --seeds 100 [--numerics auto|48x48]
        [--experiments 3] [--out docs/shape_null_validation.json]

Not a test (tens of seconds a seed).
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

from scipy.stats import beta

ROOT = Path(__file__).resolve().parent.parent


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def conditions(n_exp: int, where: Path) -> Path:
    """The first `n_exp` experiments of the paper's matrix as a conditions file."""
    import hidden_physics as hp

    path = where / f"paper{n_exp}.toml"
    lines = ['[model]', 'preset = "rig"']
    for c in hp.PAPER[:n_exp]:
        lines += ["[[experiment]]", f'name = "{c.name}"', f"speed_rpm = {c.speed_rpm:g}",
                  f"revolutions = {c.revolutions:g}", f"clearance_mm = {c.clearance_mm:g}"]
    path.write_text("\n".join(lines) + "\n")
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--numerics", default="auto", help="auto, or NxS the study states")
    ap.add_argument("--experiments", type=int, default=3)
    ap.add_argument("--generator", default="120x216x50",
                    help="the generator's nodes x steps x M (finer than the study)")
    ap.add_argument("--work", default="out/shape_null")
    ap.add_argument("--out", default=None)
    ap.add_argument("--interaction", action="store_true",
                    help="also test the surface over the two factor variables of smallest "
                         "p on top of their additive fit (the analysis runs it only where "
                         "two are significant): its p-value on null data")
    a = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    sys.path.insert(0, str(ROOT))  # this checkout's jaxwear
    import jax

    import jaxwear as jw
    from jaxwear._analyses.diagnose import diagnose

    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    cond = conditions(a.experiments, work)
    gn, gs, gm = a.generator.split("x")
    rows = []
    t_all = time.perf_counter()
    for k in range(a.seeds):
        seed = a.first_seed + k
        out = work / f"null-{seed}"
        if out.exists():
            shutil.rmtree(out)
        args = [sys.executable, str(ROOT / "benchmarks" / "hidden_physics.py"), "--law", "null",
                "--seed", str(seed), "--out", str(out), "--conditions", str(cond),
                "--nodes", gn, "--steps", gs, "--M", gm]
        if a.numerics != "auto":
            args += ["--study-numerics", a.numerics]
        p = subprocess.run(args, capture_output=True, text=True)
        if p.returncode:
            raise RuntimeError(p.stderr)
        t0 = time.perf_counter()
        d = diagnose(jw.load_study(out / "study.toml"), shape=True, seed=seed)
        shp = d.shape
        ps = [v.p_value for v in shp.variables]
        rows.append({"seed": seed, "verdict": d.status, "best": shp.best, "form": shp.form,
                     "min_p": min(ps), "n_variables": len(ps),
                     "numerical_error": shp.numerical, "wall_s": time.perf_counter() - t0})
        if a.interaction:
            from jaxwear._analyses.diagnose.shape.interaction import pair_interaction

            fac = sorted(shp.form_variables("factor"), key=lambda v: v.p_value)
            it = pair_interaction(shp, d.model, fac[0].name, fac[1].name, seed=seed)
            rows[-1]["interaction"] = it.to_json()
            rows[-1]["min_p_with_interaction"] = min(min(ps), it.p_value)
            print(f"  surface over {fac[0].name} x {fac[1].name}: p {it.p_value:.2e}, "
                  f"explains {it.explained_fraction:.1%}, dof {it.dof:.1f}", flush=True)
        fa = sum(r["best"] is not None for r in rows)
        print(f"seed {seed}: verdict {d.status}, best {shp.best} ({shp.form}), min p "
              f"{min(ps):.2e}; false alarms {fa}/{len(rows)} "
              f"({time.perf_counter() - t_all:.0f} s)", flush=True)
        shutil.rmtree(out)
        # free the seed's compiled programs: each keeps ~18 memory maps, and a long run
        # died past the process's map limit (LLVM: "Unable to allocate section memory")
        jax.clear_caches()
        gc.collect()
    fa = sum(r["best"] is not None for r in rows)
    lo, hi = clopper_pearson(fa, len(rows))
    summary = {"numerics": a.numerics, "generator": a.generator, "experiments": a.experiments,
               "seeds": len(rows), "false_alarms": fa, "rate": fa / len(rows),
               "interval_95": [lo, hi], "alpha": 1e-3, "covers_alpha": lo <= 1e-3 <= hi,
               "min_p_below_0.01": sum(r["min_p"] < 0.01 for r in rows),
               **({"interaction_p": sorted(r["interaction"]["p_value"] for r in rows)}
                  if a.interaction else {}),
               "verdicts": {v: sum(r["verdict"] == v for r in rows)
                            for v in ("adequate", "effect_found", "unexplained")},
               "rows": rows}
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}, indent=1))
    if a.out:
        Path(a.out).write_text(json.dumps(summary, indent=1, default=str) + "\n")
    return 0 if math.isfinite(summary["rate"]) else 1


if __name__ == "__main__":
    main()
