"""Validation of the shape's products of variables (issue 43 item 1, docs/shape_validation.md):
on a law of two variables at once from the independent generator, is the surface over the
leading pair found, and does the refit through the loop with it come closer to the noise
than the additive correction?

Data: `benchmarks/hidden_physics.py` (the independent NumPy implementation, no jaxwear
code) at finer numerics than the study's (quick: generator 96 x 144 and M = 100, the study
at 48 x 72), whole-bore scans with 0.3 µm noise on every point. Per case: `diagnose` with
the shape in this process (wall time of the whole diagnosis), the shape's JSON (`best`,
`interaction`, `confounded`, `rmse_after_um`), and the surface over the leading pair tested
on top of three additive fits (the pair and the carriers, as the analysis does; the pair
alone; every variable of the form).

    python calibration/interaction_validation.py [--case pv_tanh] [--seed 1] [--quick]
        [--work DIR] [--out FILE.json]

Not a test (minutes a case).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's jaxwear


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="pv_tanh")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--study", default=None, help="an existing study.toml instead")
    ap.add_argument("--work", default="out/interaction_validation")
    ap.add_argument("--out", default=None)
    ap.add_argument("--force-surface", action="store_true",
                    help="refit with the leading pair's surface whether or not it is "
                         "significant (what the product would bring through the loop)")
    ap.add_argument("--conditions", default="paper")
    a = ap.parse_args(argv)
    import jaxwear as jw
    from jaxwear._analyses.diagnose import diagnose
    from jaxwear._analyses.diagnose.shape.interaction import leading_pair, pair_interaction

    if a.study:
        study = Path(a.study)
    else:
        out = Path(a.work) / f"{a.case}-{a.seed}"
        args = [sys.executable, str(ROOT / "benchmarks" / "hidden_physics.py"), "--law", a.case,
                "--seed", str(a.seed), "--out", str(out), "--conditions", a.conditions]
        if a.quick:
            args += ["--nodes", "96", "--steps", "144", "--M", "100", "--study-numerics",
                     "48x72"]
        subprocess.run(args, check=True, capture_output=True)
        study = out / "study.toml"
    if a.force_surface:
        from dataclasses import replace

        from jaxwear._analyses.diagnose.shape import analysis as _shape

        plain = _shape.interaction_test
        _shape.interaction_test = lambda *x: replace(plain(*x), significant=True)
    t0 = time.perf_counter()
    d = diagnose(jw.load_study(study), shape=True, seed=a.seed, verbose=True)
    wall = time.perf_counter() - t0
    shp = d.shape
    doc = shp.to_json()
    row = {"case": a.case, "seed": a.seed, "verdict": d.status, "wall_s": wall,
           "forced_surface": a.force_surface,
           "best": shp.best, "form": shp.form, "carriers": list(shp.carriers),
           "rmse_before_um": shp.rmse_before_um, "rmse_after_um": shp.rmse_after_um,
           "noise_um": shp.noise_um, "interaction": doc["interaction"],
           "confounded": doc["confounded"], "alternatives": doc["alternatives"],
           "sentence": shp.sentence}
    pair = leading_pair(shp.variables, shp.form) if shp.form else None
    if pair is not None:
        form_vars = [v.name for v in shp.form_variables()]
        for tag, add in (("pair_and_carriers", None), ("pair_only", list(pair)),
                         ("every_variable", form_vars)):
            it = pair_interaction(shp, d.model, *pair, form=shp.form, additive=add,
                                  seed=a.seed)
            row[f"surface_on_{tag}"] = it.to_json()
    print(json.dumps(row, indent=1, default=str))
    if a.out:
        Path(a.out).write_text(json.dumps(row, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
