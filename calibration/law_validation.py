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
        [--seeds 1,2,3,4] [--design paper|rich] [--quick] [--skip-other] [--work DIR]
        [--out TABLE.md] [--jobs N [--threads 2] [--budget-s S] [--min-run-s S]]

Not a test (minutes a case): prints a markdown table and writes a JSON of every case and
seed (WORK/CASE-sSEED-DESIGN.json) and the combined table (WORK/law_validation-DESIGN.md
and .json), with the recovery of the grammar's laws counted two ways: the found law's
constants within 2 SE of the truth, and the truth among the found law and its
equivalents (laws of another structure the data do not tell from it, `shape.law.
equivalents`). `--design rich` (`RICH`): a training study that spans the states more
widely, scanned at six revolution counts. `--jobs N`: cases x seeds in N subprocesses
(`run_parallel`), each with the repository on PYTHONPATH (no install needed), one XLA host
device and `--threads` CPUs; `--budget-s`: no run started after the wall budget, runs
still going at it stopped, the table of what finished written.
"""

from __future__ import annotations

import argparse
import json
import math
import os
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
GRAMMAR = ("g_power_p", "g_exp_h", "g_hinge_v", "g_step_S", "g_step_p_power_v",
           "g_dep_power_W")
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
          "g_step_p_power_v": "grammar: factor S((p − 1.5 MPa)/0.1 MPa) (v/0.04 m/s)",
          "g_dep_power_W": "grammar: deposit 0.002 nm·rad per step (of 72) (|W|/150 N)^2"}


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
    if case == "g_dep_power_W" and "D" in c and "W_ref" in c and a_key:
        # D per step of the study's cycle: the generator's is per step of `g_dep_steps`
        # (72, the quick and auto numerics' steps per revolution)
        q = law["g_dep_exponent"]
        return {"D": A * (c["W_ref"]["value"] / law["g_W1_N"]) ** q, a_key: q}
    return {}


def _against(case: str, truth: dict, found: dict) -> dict:
    """{structure, constants: {NAME: {true, found, stderr, z}}, within_2se} of one fitted
    law's constants (`found`: shape.law.constants or an equivalent's) against the truth."""
    want = truth_constants(case, truth, found)
    out = {"structure": bool(want), "constants": {}}
    for k, v in want.items():
        f = found.get(k, {})
        se = f.get("stderr")
        z = (abs(f["value"] - v) / se) if se and math.isfinite(se) and se > 0 else math.inf
        out["constants"][k] = {"true": v, "found": f.get("value"), "stderr": se, "z": z}
        # the constants' numerical error (`law.numerical`, where checked): z against the
        # standard error and the numerical error together, √(SE² + numerical²)
        if f.get("profile"):
            # the standard error is the profile's (`diagnose.law.profile`): the misfit was
            # not quadratic within 2 linearised standard errors
            p = f["profile"]
            out["constants"][k].update(profile=[p.get("low"), p.get("high")],
                                       stderr_linear=p.get("stderr_linear"))
        n = f.get("numerical_error")
        if n is not None and z < math.inf:
            out["constants"][k].update(numerical_error=n,
                                       z_total=abs(f["value"] - v) / math.hypot(se, n))
    out["within_2se"] = bool(want) and all(x["z"] <= 2.0 for x in out["constants"].values())
    if want and all("z_total" in x for x in out["constants"].values()):
        out["within_2u"] = all(x["z_total"] <= 2.0 for x in out["constants"].values())
    return out


def recovery(case: str, train: Path, law: dict) -> dict:
    """The found law's constants against the truth: each within 2 standard errors
    (`truth_constants`; structure: the hidden law's kinds and variables); and the truth
    among {the found law and its equivalents} (`shape.law.equivalents`: laws of another
    structure the data do not tell from it): `among_equivalents` true where any of them
    is of the hidden law's structure with every constant within 2 SE."""
    truth = json.loads((train.parent / "truth.json").read_text())["law"]
    out = _against(case, truth, law.get("constants") or {})
    eqs = [_against(case, truth, e.get("constants") or {}) | {"formula": e.get("formula")}
           for e in law.get("equivalents") or []]
    out["equivalents"] = eqs
    out["among_equivalents"] = out["within_2se"] or any(e["within_2se"] for e in eqs)
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


# The rich training design (issue 48, recovery where the data determine the law): eight
# specimens spanning the states a law of the grammar depends on more widely than the
# paper's five (speeds 120-320 r/min: sliding speeds and turn rates; clearances 0.05-0.15
# mm and springs 0-1800 N/m, crank lengths 50-90 mm: pressures and loads; 8000-12000
# revolutions: the worn depth and the sliding distance), each scanned at six revolution
# counts (1000, 2000, 3500, 5000, 7000 and the end) instead of three or four: a step in
# the sliding distance at 40 m (about 2500 revolutions) falls between scans, not before
# the first. Same generator, same noise and numerics as the paper's design.
RICH = (
    # name, speed [r/min], revolutions, clearance [mm], spring [N/m], crank length [mm]
    ("r120-c05", 120.0, 10000.0, 0.05, 1009.4, None),
    ("r150-c10-k0", 150.0, 12000.0, 0.10, 0.0, None),
    ("r180-c08-L90", 180.0, 12000.0, 0.08, 1009.4, 90.0),
    ("r230-c12", 230.0, 10000.0, 0.12, 1009.4, None),
    ("r260-c15-k1800", 260.0, 10000.0, 0.15, 1800.0, None),
    ("r276-c05", 276.0, 12000.0, 0.05, 1009.4, None),
    ("r300-c05-k1800-L50", 300.0, 8000.0, 0.05, 1800.0, 50.0),
    ("r320-c06-L50", 320.0, 10000.0, 0.06, 1009.4, 50.0),
)
RICH_SCANS = (1000.0, 2000.0, 3500.0, 5000.0, 7000.0)  # and the end


def rich_conditions(work: Path) -> Path:
    """The `RICH` design as a conditions file of the generator (`hidden_physics.py
    --conditions FILE`)."""
    path = work / "rich-conditions.toml"
    lines = ["# law_validation.py --design rich (RICH): the generator's conditions", ""]
    for name, rpm, revs, cl, k, crank in RICH:
        lines += ["[[experiment]]", f'name = "{name}"', f"speed_rpm = {rpm:g}",
                  f"revolutions = {revs:g}", f"clearance_mm = {cl:g}",
                  f"spring_N_per_m = {k:g}",
                  "interruptions = [" + ", ".join(f"{r:g}" for r in RICH_SCANS) + "]"]
        if crank is not None:
            lines.append(f"crank_length_mm = {crank:g}")
        lines.append("")
    text = "\n".join(lines)
    if not path.exists() or path.read_text() != text:
        path.write_text(text)
    return path


def run_case(case: str, seed: int, work: Path, numerics, design: str = "paper",
             other: bool = True) -> dict:
    """One case at one seed in `work` (its own folder): the training study (`design`:
    "paper" or "rich", `RICH`), `diagnose --shape` on it, the recovery of a grammar law's
    constants, and (`other`) the law carried to the generator's other conditions."""
    t0 = time.perf_counter()
    work.mkdir(parents=True, exist_ok=True)
    conds = "paper" if design == "paper" else str(rich_conditions(work))
    train = sv.make_study(case, conds, seed, work / f"{case}-train", numerics)
    out = work / f"{case}-diagnose"
    rc, so, se, wall = sv._run([sys.executable, "-m", "jaxwear", "diagnose", str(train),
                                "--shape", "--out", str(out)])
    row = {"case": case, "expect": EXPECT[case], "noise_um": 0.3, "seed": seed,
           "design": design, "diagnose_wall_s": wall}
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
               law_equivalents=law.get("equivalents"),
               law_peer_fits=law.get("peer_fits"),
               law_peer_evaluations=law.get("peer_model_evaluations"),
               law_peer_cpu_s=law.get("peer_cpu_s"),
               law_cpu_s=law.get("cpu_s"),
               law_numerical=law.get("numerical"),
               law_against_library=doc["verdict"].get("law_against_library"))
    if case in GRAMMAR:
        row["recovery"] = recovery(case, train, law)
    if not other:
        row["wall_s"] = time.perf_counter() - t0
        return row
    other = sv.make_study(case, "other", seed + 100, work / f"{case}-other", numerics)
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
    eq = ""
    if r.get("law_equivalents"):
        among = rec.get("among_equivalents")
        eq = ("; equivalents: " + ", ".join(f"`{e['formula']}`" for e in r["law_equivalents"])
              + f" (truth among them within 2 SE: {'yes' if among else 'no'})")
    if not rec["structure"]:
        return "; recovery: another structure" + eq
    zs = ", ".join(f"{k} {v['z']:.2f}" for k, v in rec["constants"].items())
    zt = ""
    if "within_2u" in rec:
        zt = (", /√(SE² + numerical²): " + ", ".join(
            f"{k} {v['z_total']:.2f}" for k, v in rec["constants"].items())
            + f" ({'all' if rec['within_2u'] else 'NOT all'} ≤ 2)")
    return (f"; |found − true|/SE: {zs} ({'all' if rec['within_2se'] else 'NOT all'} ≤ 2)"
            + zt + eq)


def table(rows) -> str:
    out = ["| case (hidden) | verdict | law (status) | RMSE base → shape → law [µm] | left-out "
           "base → law | other conditions: base → with law.py | diagnose wall [s] (law "
           "search; its model runs) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['case']} (seed {r.get('seed')}) | error: {r['error']} | | | | | |")
            continue
        n = r["noise_um"]
        cs = ", ".join(f"{k} = {v['value']:.4g}" + (f" ± {v['stderr']:.2g}" if v.get("stderr")
                                                     else "") + f" {v['unit']}"
                       for k, v in (r.get("law_constants") or {}).items())
        law = (f"`{r['law_formula']}` ({cs}) **{r.get('law_status')}**{_recovered(r)}"
               if r.get("law_formula") else "none")
        verdict = r["verdict"] + (f" ({', '.join(r['partial'])})" if r.get("partial") else "")
        out.append(f"| {r['case']} (seed {r.get('seed')}, {r.get('design', 'paper')}): "
                   f"{r['expect']} | {verdict} | {law} | "
                   f"{_f(r.get('rmse_base'))} → {_f(r.get('rmse_shape'))} → "
                   f"{_f(r.get('law_rmse'))}{_pct(r.get('law_rmse'), n)} | "
                   f"{_f(r.get('loo_base'))} → {_f(r.get('law_loo'))} | "
                   f"{_f(r.get('rmse_other_base'))} → {_f(r.get('rmse_other_law'))}"
                   f"{_pct(r.get('rmse_other_law'), n)} | {_f(r.get('diagnose_wall_s'), '.0f')}"
                   f" ({_f(r.get('law_wall_s'), '.0f')}; {r.get('law_evaluations') or '-'}) |")
    return "\n".join(out)


def tag(case: str, seed: int, design: str) -> str:
    """The name of one run's folder, log and JSON in --work."""
    return f"{case}-s{seed}-{design}"


def summary(rows, unfinished=()) -> str:
    """Recovery over the grammar's cases that finished: the found law's constants within
    2 SE, and the truth among the found law and its equivalents; runs left unfinished."""
    g = [r for r in rows if r.get("case") in GRAMMAR and r.get("recovery")]
    k1 = sum(bool(r["recovery"]["within_2se"]) for r in g)
    k2 = sum(bool(r["recovery"].get("among_equivalents")) for r in g)
    found = sum(r.get("law_status") == "found" for r in g)
    k3 = sum(bool(r["recovery"].get("within_2u")) for r in g)
    out = [f"- grammar runs finished: {len(g)}; law found: {found}; the found law's constants "
           f"within 2 SE: **{k1} of {len(g)}**; within 2 √(SE² + numerical error²) "
           f"(`law.numerical`): **{k3} of {len(g)}**; the truth among the found law and its "
           f"equivalents: **{k2} of {len(g)}**"]
    for case in dict.fromkeys(r["case"] for r in g):
        rc = [r for r in g if r["case"] == case]
        out.append(f"  - {case}: {sum(r['recovery']['within_2se'] for r in rc)} / "
                   f"{sum(bool(r['recovery'].get('among_equivalents')) for r in rc)} of "
                   f"{len(rc)} (seeds {', '.join(str(r['seed']) for r in rc)})")
    errs = [r for r in rows if "error" in r]
    if errs:
        out.append("- errors: " + "; ".join(f"{r['case']} seed {r.get('seed')}: {r['error']}"
                                             for r in errs))
    if unfinished:
        out.append("- not finished within the budget: " + ", ".join(unfinished))
    cpu = [r["cpu_s"] for r in rows if r.get("cpu_s") is not None]
    if cpu:
        out.append(f"- CPU per run (user + sys, the run and its subprocesses): "
                   f"{min(cpu):.0f}-{max(cpu):.0f} s, total {sum(cpu):.0f} s")
    return "\n".join(out)


def _cpu_s() -> float:
    """CPU seconds (user + sys) of this process and its waited-for subprocesses."""
    import resource

    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def child_env(threads: int) -> dict:
    """The environment of one run of the parallel runner: the repository on PYTHONPATH (no
    install needed), the CPU platform unless told otherwise, one XLA host device and
    `threads` threads for the BLAS and OpenMP pools."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"]
                                     if env.get("PYTHONPATH") else "")
    env.setdefault("JAX_PLATFORMS", "cpu")
    flags = [f for f in env.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    env["XLA_FLAGS"] = " ".join(flags + ["--xla_force_host_platform_device_count=1"])
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
              "NUMEXPR_NUM_THREADS"):
        env[k] = str(threads)
    return env


def run_parallel(cases, seeds, design: str, work: Path, *, jobs: int, threads: int,
                 budget_s: float | None, quick: bool, other: bool,
                 min_run_s: float = 0.0) -> tuple[list, list]:
    """cases x seeds in `jobs` subprocesses (this script with --one), each pinned to its
    own `threads` CPUs where there are enough (its subprocesses inherit them), seed by
    seed (every case's first seed first). `budget_s`: no run is launched after
    `budget_s − min_run_s` seconds of wall, and runs still going at `budget_s` are
    stopped (their process group terminated) and listed as unfinished. Returns (rows of
    the runs that wrote their JSON, tags not finished)."""
    import signal
    import subprocess

    todo = [(c, s) for s in seeds for c in cases]
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    pin = len(cpus) >= jobs * threads > 0
    free = list(range(jobs))
    running, launched, unfinished = {}, [], []
    t0 = time.monotonic()
    env = child_env(threads)

    def elapsed():
        return time.monotonic() - t0

    while todo or running:
        while (todo and free and (budget_s is None or elapsed() < budget_s - min_run_s)):
            case, seed = todo.pop(0)
            slot = free.pop(0)
            name = tag(case, seed, design)
            cmd = [sys.executable, str(Path(__file__).resolve()), "--one", f"{case}:{seed}",
                   "--design", design, "--work", str(work)]
            cmd += ["--quick"] if quick else []
            cmd += [] if other else ["--skip-other"]
            mine = set(cpus[slot * threads:(slot + 1) * threads]) if pin else None
            log = open(work / f"{name}.log", "w")
            p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                 start_new_session=True,
                                 preexec_fn=(lambda m=mine: os.sched_setaffinity(0, m))
                                 if mine else None)
            running[name] = (p, slot, log)
            launched.append((name, case, seed))
            print(f"[{elapsed():6.0f} s] start {name} (slot {slot}"
                  + (f", CPUs {sorted(mine)}" if mine else "") + ")", flush=True)
        for name, (p, slot, log) in list(running.items()):
            if p.poll() is not None:
                log.close()
                free.append(slot)
                del running[name]
                print(f"[{elapsed():6.0f} s] done {name} (rc {p.returncode})", flush=True)
        if budget_s is not None and elapsed() >= budget_s and running:
            for name, (p, slot, log) in running.items():
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
            for name, (p, slot, log) in running.items():
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
                log.close()
                unfinished.append(name)
                print(f"[{elapsed():6.0f} s] stopped {name} (the budget)", flush=True)
            running.clear()
        if not running and (not todo or (budget_s is not None
                                         and elapsed() >= budget_s - min_run_s)):
            break
        time.sleep(1.0)
    unfinished += [tag(c, s, design) + " (not started)" for c, s in todo]
    rows = []
    for name, case, seed in launched:
        f = work / f"{name}.json"
        if f.exists():
            rows.append(json.loads(f.read_text()))
        elif name not in unfinished:
            rows.append({"case": case, "seed": seed, "design": design,
                         "error": f"no JSON; see {name}.log"})
    return rows, unfinished


def write_table(rows, unfinished, work: Path, design: str, out=None) -> str:
    text = table(rows) + "\n\n" + summary(rows, unfinished)
    print(text)
    dest = Path(out) if out else work / f"law_validation-{design}.md"
    dest.write_text(text + "\n")
    dest.with_suffix(".json").write_text(json.dumps({"rows": rows, "unfinished": unfinished},
                                                    indent=1, default=str))
    print(f"wrote {dest} and {dest.with_suffix('.json')}")
    return text


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--seed", type=int, default=1, help="one seed (see --seeds)")
    ap.add_argument("--seeds", default=None, help="seeds, e.g. 1,2,3,4 (default: --seed)")
    ap.add_argument("--design", choices=("paper", "rich"), default="paper",
                    help="the training study: the paper's matrix, or RICH (8 specimens "
                         "spanning the states more widely, scans at 6 revolution counts)")
    ap.add_argument("--work", default="out/law_validation")
    ap.add_argument("--out", default=None, help="markdown table (JSON beside it; default "
                                                "WORK/law_validation-DESIGN.md)")
    ap.add_argument("--quick", action="store_true",
                    help="cheap numerics (generator 96 x 144, M 100; study 48 x 72)")
    ap.add_argument("--skip-other", action="store_true",
                    help="no carrying of law.py to the other conditions (recovery only)")
    ap.add_argument("--jobs", type=int, default=0,
                    help="run cases x seeds in N subprocesses (0: one after another here)")
    ap.add_argument("--threads", type=int, default=2, help="CPUs per subprocess (--jobs)")
    ap.add_argument("--budget-s", type=float, default=None,
                    help="wall budget (--jobs): no run started after BUDGET − MIN_RUN, "
                         "runs still going at BUDGET stopped; the table of what finished "
                         "is written")
    ap.add_argument("--min-run-s", type=float, default=0.0,
                    help="no run started with less than this left of --budget-s")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)  # CASE:SEED (--jobs)
    ap.add_argument("--table", action="store_true",
                    help="only the table of the runs' JSON already in --work")
    a = ap.parse_args(argv)
    # `python -m jaxwear` in the subprocesses finds this repository without an install
    os.environ["PYTHONPATH"] = str(ROOT) + (os.pathsep + os.environ["PYTHONPATH"]
                                            if os.environ.get("PYTHONPATH") else "")
    cases = a.cases.split(",")
    unknown = [c for c in cases if c not in EXPECT]
    if unknown:
        ap.error(f"unknown case(s) {unknown}; expected some of {list(EXPECT)}")
    seeds = [int(x) for x in (a.seeds.split(",") if a.seeds else [a.seed])]
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    if a.table:
        rows = [json.loads((work / f"{tag(c, s, a.design)}.json").read_text())
                for s in seeds for c in cases
                if (work / f"{tag(c, s, a.design)}.json").exists()]
        write_table(rows, [], work, a.design, a.out)
        return
    numerics = ({"generator": ["--nodes", "96", "--steps", "144", "--M", "100"],
                 "study": "48x72"} if a.quick else {})
    if a.one:
        case, seed = a.one.rsplit(":", 1)
        name = tag(case, int(seed), a.design)
        try:
            row = run_case(case, int(seed), work / name, numerics, a.design,
                           other=not a.skip_other)
        except Exception as e:  # noqa: BLE001 (a run's failure is a row of the table)
            row = {"case": case, "seed": int(seed), "design": a.design,
                   "error": f"{type(e).__name__}: {e}"}
        row["cpu_s"] = _cpu_s()
        (work / f"{name}.json").write_text(json.dumps(row, indent=1, default=str))
        return
    if a.jobs > 0:
        rows, unfinished = run_parallel(cases, seeds, a.design, work, jobs=a.jobs,
                                        threads=a.threads, budget_s=a.budget_s,
                                        quick=a.quick, other=not a.skip_other,
                                        min_run_s=a.min_run_s)
        write_table(rows, unfinished, work, a.design, a.out)
        return
    rows = []
    for seed in seeds:
        for case in cases:
            print(f"== {case} seed {seed}", flush=True)
            name = tag(case, seed, a.design)
            row = run_case(case, seed, work / name, numerics, a.design,
                           other=not a.skip_other)
            row["cpu_s"] = _cpu_s()  # cumulative in this process
            rows.append(row)
            print(json.dumps(row, indent=1, default=str)[:4000], flush=True)
            (work / f"{name}.json").write_text(json.dumps(row, indent=1, default=str))
    write_table(rows, [], work, a.design, a.out)


if __name__ == "__main__":
    main()
