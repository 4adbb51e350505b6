"""Validation of the law search (issue 43 item 5, docs/shape_validation.md): on laws whose
structure neither the shape's basis nor the law grammar contains exactly, does the law
that `diagnose --shape` writes (`law.py`) bring the error to the noise, on the training
study and on a study of other conditions?

Data: `benchmarks/hidden_physics.py`, the independent NumPy implementation (no jaxwear
code) at finer numerics than the study's, whole-bore scans every 2° with 0.3 µm noise on
every point (negative depths included), clearance tolerances, interrupted tests. Laws:
`pv_tanh` (a rate factor of pressure and speed at once), `worn_soft` (a factor of the
depth already worn, a Hill function), `running_pressure` (running-in stronger at high
pressure), `impact_load` (impact events whose size also follows the load), the earlier
`impact`, `threshold`, `two_variable` and `null`, the grammar's own laws (`g_*`), two with
memory (`fatigue`, `film`), and two of forms the grammar does not hold (issue 48 item 6):
`bump_v` (a rate not monotone in the sliding speed) and `thermal` (a rate of the bushing's
bulk temperature, which the model has no state for).

Per case:
1. `jaxwear diagnose --shape --out` on the training study (the paper's rig matrix): the
   verdict, the shape, the law found (`shape.law`: formula, constants, RMSE in-sample and
   on left-out experiments) and the wall time of the whole command;
2. a study of **other conditions** with the same hidden law (other speeds, clearances,
   spring rates and crank lengths; another seed): its base model calibrated, and with
   `law.py` loaded (its constants held at the training's values, its strength refitted
   with K_d and the clearances: the law is learned on the training conditions only).

    python calibration/law_validation.py [--cases pv_tanh,worn_soft,...] [--seed 1]
        [--quick] [--work DIR] [--out TABLE.md]

Not a test (minutes a case): prints a markdown table and writes a JSON of every case.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "calibration"))
sys.path.insert(0, str(ROOT))

import shape_validation as sv  # noqa: E402

NEW = ("pv_tanh", "worn_soft", "running_pressure", "impact_load")
MEMORY = ("fatigue", "film")  # laws with memory (issue 48 item 4)
# laws of forms outside the grammar (issue 48 item 6): a rate not monotone in its variable,
# and a rate of a quantity the model has no state for (the bushing's bulk temperature)
BEYOND = ("bump_v", "thermal")
# laws of the grammar itself, written in the generator (issue 48 item 6: recovery)
GRAMMAR = ("g_power_p", "g_exp_h", "g_hinge_v", "g_step_S", "g_step_p_power_v")
CASES = NEW + ("impact", "threshold", "two_variable", "null") + GRAMMAR + MEMORY + BEYOND
# made by the generator, not by `jaxwear synth`
sv.OUTSIDE = sv.OUTSIDE + NEW + GRAMMAR + MEMORY + BEYOND
EXPECT = {"pv_tanh": "factor of p and v at once: (p/1.5 MPa) tanh(v/0.02 m/s)",
          "worn_soft": "factor of the worn depth: h²/(h² + (3 µm)²)",
          "running_pressure": "factor (p/1.5 MPa)²/(1 + S/20 m)",
          "impact_load": "deposit at the reversals ∝ (ω − ω0)² tanh(W/40 N)",
          "impact": "deposit at the reversals ∝ (ω − ω0)²",
          "threshold": "factor: logistic step at 1.5 MPa",
          "two_variable": "factor: logistic step at p v = 0.08 MPa·m/s", "null": "nothing",
          "fatigue": "damage dD/dN = max(p_max/0.7 MPa − 1, 0)²/6000, K_d (1 + 1.5 (1 − "
                     "exp(−D³)))",
          "film": "film df/dN = 3e-4 (1 − f)² sqrt(t_off/0.1 s) − 3e-4 f (w/8 kJ/m²)^1.5, "
                  "K_d (1 − 0.6 f)",
          "bump_v": "factor 1 + 1.5 exp(−((v − 0.05 m/s)/0.007 m/s)²) (not monotone)",
          "thermal": "bulk temperature rise θ, dθ/dt = (0.15 mean(|W| v) − θ/(10 K/W))/(60 "
                     "J/K), factor 1 + 0.5 (exp(θ/10 K) − 1)",
          "g_power_p": "grammar: factor (p/1.5 MPa)^2",
          "g_exp_h": "grammar: factor 0.5 exp((h − 5 µm)/6 µm)",
          "g_hinge_v": "grammar: factor 1.5 (max(v − 0.04, 0)/0.04 m/s)^2",
          "g_step_S": "grammar: factor 0.8 S((S − 40 m)/5 m)",
          "g_step_p_power_v": "grammar: factor S((p − 1.5 MPa)/0.1 MPa) (v/0.04 m/s)"}


def truth_constants(case: str, law: dict, found: dict) -> dict:
    """{NAME: true value} of the found law's constants (`found`: shape.law.constants), in
    the grammar's parametrisation: the strength referred to the found law's own references
    (A (z_ref/z1)^q for a power, A exp((z_ref − z1)/z_e) for an exponential); {} where
    the found law is not of the hidden law's structure."""
    c = found
    a_key = next((k for k in c if k.startswith("a") and k[1:].isdigit()), None)
    A = law["strength"]
    if case == "g_power_p" and "p_ref" in c and a_key:
        q = law["g_exponent"]
        return {"A": A * (c["p_ref"]["value"] / law["g_p1_MPa"]) ** q, a_key: q}
    if case == "g_exp_h" and "h_e" in c:
        he = law["g_he_um"]
        return {"A": A * math.exp((c["h_ref"]["value"] - law["g_h1_um"]) / he), "h_e": he}
    if case == "g_hinge_v" and "v0" in c and a_key:
        q = law["g_exponent"]
        return {"A": A * (c["v_ref"]["value"] / law["g_v1_m_per_s"]) ** q,
                "v0": law["g_v0_m_per_s"], a_key: q}
    if case == "g_step_S" and "S0" in c:
        return {"A": A, "S0": law["g_S0_m"], "S_width": law["g_Sw_m"]}
    if case == "g_step_p_power_v" and "p0" in c and "v_ref" in c and a_key:
        q = law["g_exponent2"]
        return {"A": A * (c["v_ref"]["value"] / law["g_v1_m_per_s"]) ** q,
                "p0": law["g_p0_MPa"], "p_width": law["g_pw_MPa"], a_key: q}
    return {}


def recovery(case: str, train: Path, law: dict) -> dict:
    """The found law's constants against the truth: each within 2 standard errors
    (`truth_constants`; structure: the hidden law's kinds and variables)."""
    truth = json.loads((train.parent / "truth.json").read_text())["law"]
    found = law.get("constants") or {}
    want = truth_constants(case, truth, found)
    out = {"structure": bool(want), "constants": {}}
    for k, v in want.items():
        f = found.get(k, {})
        se = f.get("stderr")
        z = (abs(f["value"] - v) / se) if se and math.isfinite(se) and se > 0 else math.inf
        out["constants"][k] = {"true": v, "found": f.get("value"), "stderr": se, "z": z}
    out["within_2se"] = bool(want) and all(x["z"] <= 2.0 for x in out["constants"].values())
    return out


def with_law(study: Path, law_file: Path, out: Path) -> Path:
    """A copy of `study` (and its data) that loads `law_file` and switches it on."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(study.parent, out)
    shutil.copy(law_file, out / "law.py")
    text = (out / study.name).read_text()
    line = 'effect_files = ["law.py"]\neffects = ["found_law"]\n'
    text = (text.replace("[model]\n", "[model]\n" + line, 1) if "[model]" in text
            else "[model]\n" + line + text)
    (out / study.name).write_text(text)
    return out / study.name


def calibrate_held(study: Path, strength_key: str) -> dict:
    """The study calibrated with K_d, the clearances and the law's strength only (its
    other constants held at law.py's defaults: the training's values)."""
    import jaxwear as jw
    from jaxwear._inference.calibrate import fit_study
    from jaxwear._inference.packing import parse_fit
    from jaxwear.effects import unregister_effect

    try:
        st = jw.load_study(study)
        keys = [k for k in parse_fit(st, "K_d,clearance") if not k.startswith("found_law_")]
        t0 = time.perf_counter()
        r = fit_study(st, keys + [strength_key])
        vals = dict(zip(r.names, (float(v) for v in r.values)))
        return {"rmse_um": float(r.rmse_um), "strength": vals.get(strength_key),
                "wall_s": time.perf_counter() - t0}
    finally:
        unregister_effect("found_law")


def run_case(case: str, seed: int, work: Path, numerics) -> dict:
    t0 = time.perf_counter()
    train = sv.make_study(case, "paper", seed, work / f"{case}-train", numerics)
    other = sv.make_study(case, "other", seed + 100, work / f"{case}-other", numerics)
    out = work / f"{case}-diagnose"
    rc, so, se, wall = sv._run([sys.executable, "-m", "jaxwear", "diagnose", str(train),
                                "--shape", "--out", str(out)])
    row = {"case": case, "expect": EXPECT[case], "noise_um": 0.3, "seed": seed,
           "diagnose_wall_s": wall}
    if rc:
        row["error"] = se.strip().splitlines()[-3:]
        return row
    doc = json.loads((out / "diagnosis.json").read_text())
    shp = doc.get("shape") or {}
    law = shp.get("law") or {}
    row.update(verdict=doc["verdict"]["status"], partial=doc["verdict"].get("partial"),
               missing_effect=doc["verdict"]["missing_effect"],
               noise_est_um=doc["baseline"]["noise_um"],
               rmse_base=doc["baseline"]["rmse_um"],
               loo_base=doc["baseline"].get("loo_rmse_um"),
               best=shp.get("best"), form=shp.get("form"), rmse_shape=shp.get("rmse_after_um"),
               law_formula=law.get("formula"), law_constants=law.get("constants"),
               law_rmse=law.get("rmse_um"), law_loo=law.get("loo_rmse_um"),
               law_candidates=[(c["label"], c["rmse_um"], c["loo_rmse_um"])
                               for c in law.get("candidates", [])],
               law_wall_s=law.get("wall_s"), summary=doc["verdict"]["summary"],
               law_status=law.get("status"), law_front=law.get("front"),
               law_loo_before=law.get("loo_rmse_before_um"),
               law_evaluations=law.get("model_evaluations"),
               law_refused=law.get("refused"),
               law_against_library=doc["verdict"].get("law_against_library"))
    if case in GRAMMAR:
        row["recovery"] = recovery(case, train, law)
    rmse_other, _ = sv.calibrate_rmse(other, work / f"{case}-other-cal")
    row["rmse_other_base"] = rmse_other
    lf = out / "law.py"
    if law.get("file") and lf.exists():
        from jaxwear._report.law_file import parameter_key

        cs = law.get("constants") or {}
        key = next((parameter_key(n, cs[n]["unit"]) for n in ("A", "D") if n in cs), None)
        st = with_law(other, lf, work / f"{case}-other-law")
        row["other_law"] = calibrate_held(st, key)
        row["rmse_other_law"] = row["other_law"]["rmse_um"]
    row["wall_s"] = time.perf_counter() - t0
    return row


def _f(x, fmt=".3f"):
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else \
        format(x, fmt)


def _pct(x, noise):
    return "" if x is None or not math.isfinite(x) else f" ({x / noise - 1:+.1%})"


def _recovered(r) -> str:
    rec = r.get("recovery")
    if not rec:
        return ""
    if not rec["structure"]:
        return "; recovery: another structure"
    zs = ", ".join(f"{k} {v['z']:.2f}" for k, v in rec["constants"].items())
    return f"; |found − true|/SE: {zs} ({'all' if rec['within_2se'] else 'NOT all'} ≤ 2)"


def table(rows) -> str:
    out = ["| case (hidden) | verdict | law (status) | RMSE base → shape → law [µm] | left-out "
           "base → law | other conditions: base → with law.py | diagnose wall [s] (law "
           "search; its model runs) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['case']} | error: {r['error']} | | | | | |")
            continue
        n = r["noise_um"]
        cs = ", ".join(f"{k} = {v['value']:.4g}" + (f" ± {v['stderr']:.2g}" if v.get("stderr")
                                                     else "") + f" {v['unit']}"
                       for k, v in (r.get("law_constants") or {}).items())
        law = (f"`{r['law_formula']}` ({cs}) **{r.get('law_status')}**{_recovered(r)}"
               if r.get("law_formula") else "none")
        verdict = r["verdict"] + (f" ({', '.join(r['partial'])})" if r.get("partial") else "")
        out.append(f"| {r['case']}: {r['expect']} | {verdict} | {law} | "
                   f"{_f(r.get('rmse_base'))} → {_f(r.get('rmse_shape'))} → "
                   f"{_f(r.get('law_rmse'))}{_pct(r.get('law_rmse'), n)} | "
                   f"{_f(r.get('loo_base'))} → {_f(r.get('law_loo'))} | "
                   f"{_f(r.get('rmse_other_base'))} → {_f(r.get('rmse_other_law'))}"
                   f"{_pct(r.get('rmse_other_law'), n)} | {_f(r.get('diagnose_wall_s'), '.0f')}"
                   f" ({_f(r.get('law_wall_s'), '.0f')}; {r.get('law_evaluations') or '-'}) |")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--work", default="out/law_validation")
    ap.add_argument("--out", default=None, help="markdown table (JSON beside it)")
    ap.add_argument("--quick", action="store_true",
                    help="cheap numerics (generator 96 x 144, M 100; study 48 x 72)")
    ap.add_argument("--table", action="store_true",
                    help="only the table of the cases' JSON already in --work")
    a = ap.parse_args(argv)
    if a.table:
        rows = [json.loads((Path(a.work) / f"{c}.json").read_text())
                for c in a.cases.split(",") if (Path(a.work) / f"{c}.json").exists()]
        print(table(rows))
        return
    numerics = ({"generator": ["--nodes", "96", "--steps", "144", "--M", "100"],
                 "study": "48x72"} if a.quick else {})
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in a.cases.split(","):
        print(f"== {case}", flush=True)
        rows.append(run_case(case, a.seed, work, numerics))
        print(json.dumps(rows[-1], indent=1, default=str)[:4000], flush=True)
        (work / f"{case}.json").write_text(json.dumps(rows[-1], indent=1, default=str))
    text = table(rows)
    print(text)
    if a.out:
        Path(a.out).write_text(text + "\n")
        Path(a.out).with_suffix(".json").write_text(json.dumps(rows, indent=1, default=str))


if __name__ == "__main__":
    main()
