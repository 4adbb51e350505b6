"""Time to an answer: the CLI as a new user runs it, default numerics, cold compilation cache.

Each row is one `jaxwear` command in a fresh process (JAX's persistent cache off, so every
compilation is paid), timed wall-clock, with the model evaluations its JSON reports. The
studies are the issue-19 cases: a 5-experiment rig study from `jaxwear synth` (full-bore
scans every 2° at three or four interrupted counts, 0.3 µm noise, truth at finer numerics)
and the boom joint of the paper (calibration/boom, Table 5), both with their `[numerics]`
removed so that the defaults decide (adaptive wear integrator, resolution by the error).

    python benchmarks/time_to_answer.py [--out benchmarks/TIME_TO_ANSWER.md] [--only ROW]
    python benchmarks/time_to_answer.py --nuts      # adds NUTS on the boom (~10 min)

Benchmarks are not tests: figures depend on the machine and its load (recorded).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def strip_numerics(path: Path, effects: list[str] | None = None) -> None:
    text = re.sub(r"\[numerics\][^\[]*", "", path.read_text())
    if effects is not None:
        text = text.replace("[model]\n", f"[model]\neffects = {json.dumps(effects)}\n", 1)
    path.write_text(text)


def run(cmd: list[str], json_path: Path | None) -> tuple[float, dict | None, str]:
    env = dict(os.environ, JAXWEAR_NO_CACHE="1")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "jaxwear", *cmd], capture_output=True,
                          text=True, env=env)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}: {proc.stderr[-2000:]}")
    doc = json.loads(json_path.read_text()) if json_path and json_path.exists() else None
    return wall, doc, proc.stderr


def _f(x) -> str:
    return "null" if x is None else f"{x:.1f}"


def evaluations_in(stderr: str) -> str:
    m = re.findall(r"\((\d+) model evaluations\)", stderr)
    return m[-1] if m else "?"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "TIME_TO_ANSWER.md"))
    ap.add_argument("--only", default=None, help="run only rows whose label contains this")
    ap.add_argument("--nuts", action="store_true", help="also NUTS on the boom (minutes)")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="jaxwear-tta-"))
    rows = []
    try:
        # data: the rig matrix (null) and with a speed effect, both at finer numerics
        for name, hidden in (("rig", None), ("rig_speed", "speed_dependence")):
            cmd = ["synth", "--noise-um", "0.3", "--seed", "5", "--out", str(tmp / name)]
            if hidden:
                cmd[1:1] = ["--hidden", hidden]
            run(cmd, None)
            strip_numerics(tmp / name / "study.toml")
        boom = tmp / "boom"
        boom.mkdir()
        shutil.copy(ROOT / "calibration" / "boom" / "boom.csv", boom / "boom.csv")
        shutil.copy(ROOT / "calibration" / "boom" / "study.toml", boom / "study.toml")
        strip_numerics(boom / "study.toml")
        shutil.copy(boom / "study.toml", boom / "study_ri.toml")
        strip_numerics(boom / "study_ri.toml", ["running_in"])

        cases = [
            ("calibrate the 5-experiment rig study (K_d + 5 clearances)", "calibrate",
             [str(tmp / "rig" / "study.toml"), "--fit", "K_d,clearance"], "267 s, 29",
             "<= 30 s, <= 8"),
            ("calibrate the boom, K_d + clearance", "calibrate",
             [str(boom / "study.toml"), "--fit", "K_d,clearance"], "292 s, 21", "<= 20 s"),
            ("calibrate the boom with running_in", "calibrate",
             [str(boom / "study_ri.toml")], "444 s, 25", "<= 30 s"),
            ("predict the boom with running_in, --train-until 15 --noise-um 5 --at 20,25",
             "predict", [str(boom / "study_ri.toml"), "--train-until", "15", "--noise-um",
                         "5", "--at", "20,25"], "730 s", "<= 60 s"),
            ("diagnose the 5-experiment rig study, null", "diagnose",
             [str(tmp / "rig" / "study.toml")], "92-109 s", "<= 90 s"),
            ("diagnose the 5-experiment rig study, speed effect", "diagnose",
             [str(tmp / "rig_speed" / "study.toml")], "513 s", "<= 90 s"),
            ("diagnose --shape, the same study (issue 20: <= 60 s more)", "diagnose",
             [str(tmp / "rig_speed" / "study.toml"), "--shape"], "-", "row above + 60 s"),
        ]
        if args.nuts:
            cases.append(("NUTS on the boom, 2 x (100 + 100), --noise-um 5", "predict",
                          [str(boom / "study.toml"), "--train-until", "15", "--noise-um",
                           "5", "--at", "20,25", "--method", "nuts", "--chains", "2",
                           "--warmup", "100", "--samples", "100", "--max-minutes", "60"],
                          "11.6 min", "<= 3 min"))
        for i, (label, verb, cmd, before, target) in enumerate(cases):
            if args.only and args.only not in label:
                continue
            out = tmp / f"out{i}"
            js = out / "answer.json"
            wall, doc, err = run([verb, *cmd, "--out", str(out), "--json", str(js)], js)
            if verb == "calibrate":
                evals = doc.get("model_evaluations", doc.get("iterations"))
                extra = (f"{doc['status']}; resolution {doc['resolution']['nodes']} x "
                         f"{doc['resolution']['steps_per_rev']}")
            elif verb == "diagnose":
                evals = evaluations_in(err)
                extra = doc["verdict"]["status"] + (
                    f" ({doc['verdict']['missing_effect']})"
                    if doc["verdict"]["missing_effect"] else "")
                if "shape" in doc:
                    extra += f"; shape best: {doc['shape']['best']}"
            else:
                evals = (doc.get("fit") or {}).get("model_evaluations") or "?"
                p = doc["predictions"]
                extra = "; ".join(f"{x['at']:g} h: {_f(x['depth_um'])} [{_f(x['lower_um'])}, "
                                  f"{_f(x['upper_um'])}] µm (measured {_f(x['measured_um'])})"
                                  for x in p)
            rows.append((label, before, target, f"{wall:.1f} s", str(evals), extra))
            print(f"{label}: {wall:.1f} s, {evals} evaluations, {extra}", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    lines = ["# Time to an answer (benchmarks/time_to_answer.py)", "",
             f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
             f"load {os.getloadavg()[0]:.1f} at the end; JAX persistent cache off (cold); "
             f"CLI wall clock per command in a fresh process.", "",
             "| answer (CLI wall, defaults) | before (issue 19) | target | now | model "
             "evaluations | result |", "|---|---|---|---|---|---|"]
    lines += [f"| {a} | {b} | {c} | {d} | {e} | {f} |" for a, b, c, d, e, f in rows]
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
