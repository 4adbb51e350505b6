"""Validation of the loop "see where the model fails, learn what is missing, add it, watch
the error fall" on physics the library does not have (issue 25, docs/shape_validation.md).

Data: `benchmarks/hidden_physics.py`, an independent NumPy implementation of design.md §1-4
(no jaxwear code) at finer numerics than any fit, whole-bore scans every 2° with 0.3 µm
noise on every point, clearance tolerances, interrupted tests. Library effects are hidden
by `jaxwear synth` at twice the study's nodes and steps and a tenth of its update.

Per case, on a training study (the paper's rig matrix):
1. `diagnose --shape`: verdict, the best variable and form, the variables that carry the
   misfit, RMSE before and after the correction (refitted through the wear loop);
2. the effect file it writes (`missing_wear.py`), loaded in the training study and
   calibrated (its gain fitted): the RMSE with the written effect;
3. the same file in a study of **other conditions** with the same hidden law (other
   speeds, clearances, spring rates and crank lengths; another seed), calibrated: the
   error on experiments the correction never saw, against the base model's there.

    python calibration/shape_validation.py [--cases impact,threshold,two_variable,...]
        [--seed 1] [--out docs/shape_validation.md] [--quick]

Not a test (minutes a case): writes the table (markdown) and a JSON of every case.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

OUTSIDE = ("impact", "threshold", "two_variable")
LIBRARY = {"speed": "speed_dependence", "pressure": "pressure_exponent",
           "running_in": "running_in"}
CASES = OUTSIDE + tuple(LIBRARY) + ("null",)
EXPECT = {"impact": "deposit at the load's reversals (load turn rate / cycle phase)",
          "threshold": "factor along the contact pressure", "two_variable":
          "factor along pressure and sliding speed (PV)", "speed": "sliding speed",
          "pressure": "contact pressure", "running_in": "sliding distance, falling",
          "null": "nothing"}


def _run(args, cwd=None):
    """A command, its output kept; exit status returned."""
    t0 = time.perf_counter()
    p = subprocess.run(args, cwd=cwd, capture_output=True, text=True)
    return p.returncode, p.stdout, p.stderr, time.perf_counter() - t0


def make_study(case: str, conditions: str, seed: int, out: Path, numerics) -> Path:
    """A study with the case's hidden physics, made outside the fit's numerics."""
    if out.exists():
        shutil.rmtree(out)
    if case in OUTSIDE or case == "null":
        args = [sys.executable, str(ROOT / "benchmarks" / "hidden_physics.py"), "--law", case,
                "--seed", str(seed), "--out", str(out), "--conditions", conditions]
        if numerics.get("generator"):
            args += numerics["generator"]
        if numerics.get("study"):
            args += ["--study-numerics", numerics["study"]]
        rc, so, se, _ = _run(args)
        if rc:
            raise RuntimeError(f"hidden_physics {case}: {se.strip()}")
        return out / "study.toml"
    import jaxwear as jw

    nodes, steps = (int(x) for x in numerics.get("study", "90x72").split("x"))
    conds = "paper" if conditions == "paper" else str(_other_conditions(out.parent))
    res = jw.synthesize([LIBRARY[case]], conds, noise_um=0.3, seed=seed, out=out,
                        numerics={"nodes": nodes, "steps_per_rev": steps,
                                  "revolutions_per_update": 250})
    return Path(res.study_path)


def _other_conditions(where: Path) -> Path:
    """A study of the generator's `other` conditions (its null law at cheap numerics), whose
    experiments and measurement points `jaxwear synth --conditions` takes over."""
    out = where / "other-conditions"
    if not (out / "study.toml").exists():
        rc, so, se, _ = _run([sys.executable, str(ROOT / "benchmarks" / "hidden_physics.py"),
                              "--law", "null", "--conditions", "other", "--seed", "0",
                              "--out", str(out), "--nodes", "48", "--steps", "72", "--M",
                              "500"])
        if rc:
            raise RuntimeError(f"hidden_physics other conditions: {se.strip()}")
    return out / "study.toml"


def with_effect(study: Path, effect_file: Path, out: Path) -> Path:
    """A copy of `study` (and its data) that loads `effect_file` and switches it on."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(study.parent, out)
    shutil.copy(effect_file, out / "missing_wear.py")
    text = (out / study.name).read_text()
    line = 'effect_files = ["missing_wear.py"]\neffects = ["missing_wear"]\n'
    if "[model]" in text:
        text = text.replace("[model]\n", "[model]\n" + line, 1)
    else:
        text = "[model]\n" + line + text
    (out / study.name).write_text(text)
    return out / study.name


def calibrate_rmse(study: Path, out: Path) -> tuple[float, dict]:
    rc, so, se, wall = _run([sys.executable, "-m", "jaxwear", "calibrate", str(study), "--out",
                             str(out)])
    if rc:
        return math.nan, {"error": se.strip().splitlines()[-1:], "wall_s": wall}
    doc = json.loads((out / "calibration.json").read_text())
    return float(doc["rmse_um"]), {"wall_s": wall, "status": doc["status"],
                                   "parameters": doc["parameters"],
                                   "noise_um": doc["noise_um"]}


def run_case(case: str, seed: int, work: Path, numerics) -> dict:
    t0 = time.perf_counter()
    train = make_study(case, "paper", seed, work / f"{case}-train", numerics)
    other = make_study(case, "other", seed + 100, work / f"{case}-other", numerics)
    truth_noise = 0.3
    rc, so, se, wall = _run([sys.executable, "-m", "jaxwear", "diagnose", str(train), "--shape",
                             "--out", str(work / f"{case}-diagnose")])
    row = {"case": case, "expect": EXPECT[case], "noise_um": truth_noise, "seed": seed}
    if rc:
        row["error"] = se.strip().splitlines()[-3:]
        return row
    doc = json.loads((work / f"{case}-diagnose" / "diagnosis.json").read_text())
    shp = doc.get("shape") or {}
    row.update(verdict=doc["verdict"]["status"], missing_effect=doc["verdict"]["missing_effect"],
               best=shp.get("best"), form=shp.get("form"), carriers=shp.get("carriers"),
               alternatives=shp.get("alternatives"), rmse_before=shp.get("rmse_before_um"),
               rmse_after=shp.get("rmse_after_um"), when_where=shp.get("when_where"),
               diagnose_wall_s=wall, shape_evaluations=shp.get("model_evaluations"),
               summary=shp.get("summary"))
    effect = work / f"{case}-diagnose" / "missing_wear.py"
    if shp.get("effect_file") and effect.exists():
        st = with_effect(train, effect, work / f"{case}-train-effect")
        row["rmse_written_effect"], row["written_effect_fit"] = calibrate_rmse(
            st, work / f"{case}-train-effect-cal")
        row["rmse_other_base"], _ = calibrate_rmse(other, work / f"{case}-other-cal")
        st = with_effect(other, effect, work / f"{case}-other-effect")
        row["rmse_other_effect"], row["other_effect_fit"] = calibrate_rmse(
            st, work / f"{case}-other-effect-cal")
    row["wall_s"] = time.perf_counter() - t0
    return row


def table(rows) -> str:
    def f(x, fmt=".3f"):
        return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else \
            format(x, fmt)

    out = ["| case (hidden) | expected | verdict | best (form) | carriers | RMSE base → "
           "corrected [µm] | with missing_wear.py | other conditions: base → with the file | "
           "noise | diagnose wall [s] |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['case']} | {r['expect']} | error: {r['error']} |  |  |  |  |  |  "
                       f"|  |")
            continue
        best = f"{r['best']} ({r['form']})" if r.get("best") else "none"
        out.append(f"| {r['case']} | {r['expect']} | {r['verdict']} | {best} | "
                   f"{', '.join(r.get('carriers') or []) or '-'} | {f(r.get('rmse_before'))} → "
                   f"{f(r.get('rmse_after'))} | {f(r.get('rmse_written_effect'))} | "
                   f"{f(r.get('rmse_other_base'))} → {f(r.get('rmse_other_effect'))} | "
                   f"{r['noise_um']} | {f(r.get('diagnose_wall_s'), '.0f')} |")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--work", default="out/shape_validation")
    ap.add_argument("--out", default=None, help="markdown table (JSON beside it)")
    ap.add_argument("--quick", action="store_true",
                    help="cheap numerics (generator 96 x 144, M 100; study 48 x 72)")
    a = ap.parse_args(argv)
    numerics = ({"generator": ["--nodes", "96", "--steps", "144", "--M", "100"],
                 "study": "48x72"} if a.quick else {})
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in a.cases.split(","):
        print(f"== {case}", flush=True)
        rows.append(run_case(case, a.seed, work, numerics))
        print(json.dumps(rows[-1], indent=1, default=str)[:3000], flush=True)
    text = table(rows)
    print(text)
    if a.out:
        Path(a.out).write_text(text + "\n")
        Path(a.out).with_suffix(".json").write_text(json.dumps(rows, indent=1, default=str))


if __name__ == "__main__":
    main()
