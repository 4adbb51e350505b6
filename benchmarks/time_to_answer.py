"""Time to an answer: the CLI as a new user runs it, default numerics, cold and warm.

Each row is one `jaxwear` command run twice in fresh processes sharing one persistent
compilation cache (`JAXWEAR_CACHE_DIR`, a new empty folder per row): the first run is
**cold** (every compilation paid), the second **warm** (compilations loaded from the
cache). Wall clock per command, with the model evaluations and compilations its JSON
reports, and every answer checked against an independent fact:
- calibrate the rig study: K_d within 5 % of the truth the data were made with
  (`jaxwear synth`, truth at finer numerics, `truth.json`);
- calibrate the boom: the RMSE documented in docs/guide/diagnose.md (16.9 µm for the base
  model, 2.0 µm with running-in), within 10 %;
- predict: every forecast within 5 % of the held-out measurement;
- diagnose: the verdict the data were made for (null: adequate; speed: effect_found
  speed_dependence);
- importance / NUTS: the sampler's own diagnostics (k̂ ≤ 0.7 or R-hat ≤ 1.01, ESS ≥ 400
  for every parameter) and, on the boom, its bands within 5 % of the Laplace bands.

The studies are the issue-19 cases: a 5-experiment rig study from `jaxwear synth`
(full-bore scans every 2° at three or four interrupted counts, 0.3 µm noise, truth at finer
numerics), the boom joint of the paper (calibration/boom, Table 5), both with their
`[numerics]` removed so that the defaults decide (adaptive wear integrator, resolution by
the error), and a one-experiment rig study at 64 x 72 for the posterior samplers.

    python benchmarks/time_to_answer.py [--out benchmarks/TIME_TO_ANSWER.md] [--only TEXT|TEXT]
        [--cold-only] [--held-out] [--samplers] [--logs DIR]

`--held-out` adds a diagnosis whose verdict is partly explained (the shape and the law
search run by themselves): a study of `benchmarks/hidden_physics.py` with its fatigue law
(a law with memory, outside jaxwear's library), checked by its verdict and by the law's
left-out error against the noise the generator added.

Where each answer's time goes (the columns after the wall times): `import` (Python's
imports, jax's included), `compile` (tracing + lowering + XLA's compilation, summed over
threads: a background compilation overlaps the rest), `cache` (reading compiled programs
from the persistent cache, warm runs), `runs` (jaxwear's compiled programs running, each
top-level call timed to its result, the compilation in its own thread taken out; calls in
several threads at once are each counted) and `host` (the rest: NumPy, the fits'
bookkeeping, the outputs, waiting; negative where compilations or runs overlapped).
Recorded in the command's own process by `jax.monitoring` listeners and a timer around
`jaxwear._core.jit.Jit` (`_RUNNER`), which then ends the process as the command line does
(`_core.interrupt.end_process`: the exit hooks, no interpreter teardown; until 2026-11-29
midday the runner left the teardown to Python, 0.2-0.5 s a command that `jaxwear` does not
spend).

A fixed reference runs before every command: `benchmarks/numpy_reference.py`'s rig, 10 000
rev at 360 x 360, M = 500 (plain NumPy, no compilation; 1.46 s on the quiet machine of
2026-11-26). The `/ ref` column divides the command's wall time by it, a figure that moves
less with the machine's speed and load than the wall time does (an answer's target over
1.46 s is its target in that unit: 10 s is 6.8).

Benchmarks are not tests: figures depend on the machine and its load (recorded before and
after every command).
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


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else the platform's: hosts of the same core
    count differed 2x in speed between sessions, so the table says which one it is."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{platform.machine()} ({line.split(':', 1)[1].strip()})"
    except OSError:
        pass
    return platform.processor() or platform.machine()


def strip_numerics(path: Path, effects: list[str] | None = None) -> None:
    text = re.sub(r"\[numerics\][^\[]*", "", path.read_text())
    if effects is not None:
        text = text.replace("[model]\n", f"[model]\neffects = {json.dumps(effects)}\n", 1)
    path.write_text(text)


# The command line, timed from inside its process (see the module's docstring).
_RUNNER = r"""
import json, os, sys, threading, time
t0 = time.perf_counter()
import jax
import jax.monitoring as mon
acc = {"trace": 0.0, "lower": 0.0, "xla": 0.0, "cache": 0.0}
mine = {}  # thread id: its own compile seconds (a background compilation is another's)
names = {"/jax/core/compile/jaxpr_trace_duration": "trace",
         "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
         "/jax/core/compile/backend_compile_duration": "xla",
         "/jax/compilation_cache/cache_retrieval_time_sec": "cache"}
def listen(event, duration, **kw):
    if event in names:
        acc[names[event]] += duration
        t = threading.get_ident()
        mine[t] = mine.get(t, 0.0) + duration
mon.register_event_duration_secs_listener(listen)
from jaxwear import cli
from jaxwear._core import jit as J
t_import = time.perf_counter() - t0
runs = {"calls": 0, "seconds": 0.0}
plain_call = J.Jit.__call__
def timed_call(self, *a, **k):
    if J._traced(a, k):
        return plain_call(self, *a, **k)
    t = threading.get_ident()
    c0, s0 = mine.get(t, 0.0), time.perf_counter()
    out = jax.block_until_ready(plain_call(self, *a, **k))
    runs["seconds"] += time.perf_counter() - s0 - (mine.get(t, 0.0) - c0)
    runs["calls"] += 1
    return out
J.Jit.__call__ = timed_call
try:
    rc = cli.main(sys.argv[1:])
finally:
    wall = time.perf_counter() - t0
    with open(os.environ["JAXWEAR_TTA_TIMES"], "w") as f:
        json.dump({"wall": wall, "import": t_import, "compile": acc["trace"] + acc["lower"]
                   + acc["xla"], "cache": acc["cache"], "runs": runs["seconds"],
                   "calls": runs["calls"], **acc}, f)
# as `python -m jaxwear` ends (`cli.main` ends its own process only when it is the command
# line: here it is called from this runner)
from jaxwear._core.interrupt import end_process
end_process(rc)
"""


def run(cmd: list[str], json_path: Path | None, cache: Path | None, times: Path | None = None):
    """(wall [s], JSON document or None, stderr, load before, load after) of one command in
    a fresh process; `cache`: the persistent compilation cache folder (None: off); `times`:
    where the command writes where its time went (`_RUNNER`), None: a plain `-m jaxwear`."""
    env = dict(os.environ)
    env.pop("JAXWEAR_NO_CACHE", None)
    if cache is None:
        env["JAXWEAR_NO_CACHE"] = "1"
    else:
        env["JAXWEAR_CACHE_DIR"] = str(cache)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    if json_path is not None and json_path.exists():
        json_path.unlink()
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    if times is not None:
        env["JAXWEAR_TTA_TIMES"] = str(times)
    launch = ["-m", "jaxwear"] if times is None else ["-c", _RUNNER]
    proc = subprocess.run([sys.executable, *launch, *cmd], capture_output=True,
                          text=True, env=env)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}: {proc.stderr[-2000:]}")
    doc = json.loads(json_path.read_text()) if json_path and json_path.exists() else None
    return wall, doc, proc.stderr, load0, os.getloadavg()[0]


def reference() -> float:
    """Wall seconds of the fixed NumPy reference (the module's docstring)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import numpy_reference

    t0 = time.perf_counter()
    numpy_reference.simulate_rig(speed_rpm=276.0, revolutions=10000, M=500, nodes=360,
                                 steps=360, clearance_m=0.05e-3, K_d=1e-13, spring=1009.4,
                                 contact="unsymmetric")
    return time.perf_counter() - t0


def _f(x) -> str:
    return "null" if x is None else f"{x:.1f}"


def _compiles(doc) -> str:
    c = doc.get("compiles")
    if isinstance(c, dict):
        return "+".join(f"{v} {k}" for k, v in c.items() if v) or "0"
    by = doc.get("compiles_by_kind") or (doc.get("cost") or {}).get("compiles") or {}
    return "+".join(f"{v} {k}" for k, v in by.items() if v) or str(c)


def _shares(t: dict) -> str:
    """One run's time by where it went (`_RUNNER`'s record), in seconds."""
    host = t["wall"] - t["import"] - t["compile"] - t["cache"] - t["runs"]
    return (f"import {t['import']:.1f}, compile {t['compile']:.1f} (xla {t['xla']:.1f}), "
            f"cache {t['cache']:.1f}, runs {t['runs']:.1f} ({t['calls']}), host {host:.1f}")


def within(a, b, rel) -> bool:
    return a is not None and b is not None and abs(a - b) <= rel * abs(b)


# ---------------------------------------------------------------- checks, one per verb


def check_calibrate_rig(doc, truth):
    kd, ref = doc["parameters"]["K_d_per_Pa"]["value"], truth["K_d_per_Pa"]
    ok = within(kd, ref, 0.05)
    return ok, f"K_d {kd:.4g} vs truth {ref:.4g} ({(kd / ref - 1) * 100:+.1f} %)"


def check_rmse(ref):
    def check(doc, _):
        r = doc["rmse_um"]
        return within(r, ref, 0.10), f"RMSE {r:.2f} µm (docs {ref} µm)"
    return check


def check_forecasts(doc, _):
    parts, ok = [], True
    for p in doc["predictions"]:
        m, d = p["measured_um"], p["depth_um"]
        good = m is not None and within(d, m, 0.05)
        ok &= good
        parts.append(f"{p['at']:g}: {_f(d)} [{_f(p['lower_um'])}, {_f(p['upper_um'])}] "
                     f"(measured {_f(m)}{'' if good else ', > 5 %'})")
    return ok, "; ".join(parts)


def check_verdict(status, effect=None):
    def check(doc, _):
        v = doc["verdict"]
        ok = v["status"] == status and (effect is None or v["missing_effect"] == effect)
        text = v["status"] + (f" ({v['missing_effect']})" if v["missing_effect"] else "")
        if "shape" in doc:
            text += f"; shape best: {doc['shape']['best']}"
        return ok, text
    return check


def check_held_out(noise_um):
    """A partly explained verdict whose law of the grammar predicts the left-out
    experiments within 15 % of the noise the generator added (`noise_um`): the data carry
    a law outside jaxwear's library (`write_held_out`)."""
    def check(doc, _):
        v = doc["verdict"]
        law = (doc.get("shape") or {}).get("law") or {}
        loo = law.get("loo_rmse_um")
        ok = v["status"] == "partly_explained" and loo is not None and loo <= 1.15 * noise_um
        text = v["status"] + (f"; law left-out {loo:.3f} µm (noise {noise_um} µm): "
                              f"{law.get('formula', '')[:60]}" if loo is not None else
                              "; no law")
        return ok, text
    return check


def write_held_out(root: Path, law: str, seed: int = 1) -> str:
    """A study of `benchmarks/hidden_physics.py` (`law` hidden, the paper's rig matrix,
    0.3 µm noise on the whole bore), made at 96 x 144 and M = 100 and written for a fit at
    48 x 72 (calibration/law_validation.py's `--quick` numerics)."""
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "hidden_physics.py"),
                           "--law", law, "--seed", str(seed), "--out", str(root),
                           "--conditions", "paper", "--nodes", "96", "--steps", "144",
                           "--M", "100", "--study-numerics", "48x72"],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"hidden_physics {law}: {proc.stderr[-2000:]}")
    return str(root / "study.toml")


def check_sampler(method, laplace_doc=None):
    def check(doc, _):
        block = doc[method]
        post = block["posterior"]
        ess_key = "ess" if method == "importance" else "ess_bulk"
        ess = min(v[ess_key] or 0 for v in post.values())
        rhat = block.get("max_r_hat")
        ok = ess >= 400 and rhat is not None and rhat <= 1.01
        text = f"ESS {ess:.0f}, R-hat {rhat if rhat is None else round(rhat, 4)}"
        if method == "importance":
            ok &= block["k_hat"] <= 0.7
            text += f", k̂ {block['k_hat']:.2f}"
        ok2, fc = check_forecasts(doc, None)
        text += "; " + fc
        if laplace_doc is not None:
            lap = {(p["experiment"], p["at"]): p for p in laplace_doc["predictions"]}
            gaps = []
            for p in doc["predictions"]:
                q = lap[(p["experiment"], p["at"])]
                for k in ("lower_um", "depth_um", "upper_um"):
                    gaps.append(abs(p[k] - q[k]) / abs(q[k]))
            ok &= max(gaps) <= 0.05
            text += f"; bands vs Laplace within {max(gaps) * 100:.1f} %"
        return ok, text
    return check


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "TIME_TO_ANSWER.md"))
    ap.add_argument("--only", default=None,
                    help="run only rows whose label contains this (alternatives: A|B)")
    ap.add_argument("--cold-only", action="store_true", help="skip the warm runs")
    ap.add_argument("--logs", default=None,
                    help="folder for each run's log (stderr: where its time went)")
    ap.add_argument("--held-out", action="store_true",
                    help="also a diagnosis whose verdict is partly explained, on a study of "
                         "benchmarks/hidden_physics.py (the shape and the law search run: "
                         "minutes)")
    ap.add_argument("--samplers", action="store_true",
                    help="also the posterior samplers (importance, NUTS: minutes each)")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="jaxwear-tta-"))
    rows = []
    try:
        # data: the rig matrix (null) and with a speed effect, both at finer numerics
        for name, hidden in (("rig", None), ("rig_speed", "speed_dependence")):
            cmd = ["synth", "--noise-um", "0.3", "--seed", "5", "--out", str(tmp / name)]
            if hidden:
                cmd[1:1] = ["--hidden", hidden]
            run(cmd, None, None)
            strip_numerics(tmp / name / "study.toml")
        truth = json.loads((tmp / "rig" / "truth.json").read_text())
        boom = tmp / "boom"
        boom.mkdir()
        shutil.copy(ROOT / "calibration" / "boom" / "boom.csv", boom / "boom.csv")
        shutil.copy(ROOT / "calibration" / "boom" / "study.toml", boom / "study.toml")
        strip_numerics(boom / "study.toml")
        shutil.copy(boom / "study.toml", boom / "study_ri.toml")
        strip_numerics(boom / "study_ri.toml", ["running_in"])
        boom_predict = [str(boom / "study_ri.toml"), "--train-until", "15", "--noise-um",
                        "5", "--at", "20,25"]

        cases = [
            ("calibrate the 5-experiment rig study (K_d + 5 clearances)", "calibrate",
             [str(tmp / "rig" / "study.toml"), "--fit", "K_d,clearance"], "267 s, 29 / 38.3 s, 11",
             "<= 10 s", check_calibrate_rig),
            ("calibrate the boom, K_d + clearance", "calibrate",
             [str(boom / "study.toml"), "--fit", "K_d,clearance"], "292 s, 21 / 25.3 s, 7",
             "<= 8 s",
             check_rmse(16.9)),
            ("calibrate the boom with running_in", "calibrate",
             [str(boom / "study_ri.toml")], "444 s, 25 / 80.0 s, 28", "<= 12 s", check_rmse(2.0)),
            ("predict the boom with running_in, --train-until 15 --noise-um 5 --at 20,25",
             "predict", boom_predict, "730 s / 135.6 s, 28", "<= 15 s", check_forecasts),
            ("diagnose the 5-experiment rig study, null", "diagnose",
             [str(tmp / "rig" / "study.toml")], "92-109 s / 74.9 s, 8", "<= 30 s",
             check_verdict("adequate")),
            ("diagnose the 5-experiment rig study, speed effect", "diagnose",
             [str(tmp / "rig_speed" / "study.toml")], "513 s / 175.6 s, 17",
             "<= 30 s (60 s partly explained)",
             check_verdict("effect_found", "speed_dependence")),
            ("diagnose --shape, the same study (issue 20: <= 60 s more)", "diagnose",
             [str(tmp / "rig_speed" / "study.toml"), "--shape"], "- / 339.9 s, 28",
             "<= 2 min",
             check_verdict("effect_found", "speed_dependence")),
        ]
        if args.held_out:
            fatigue = write_held_out(tmp / "fatigue", "fatigue")
            cases += [
                ("diagnose a held-out study, partly explained (the generator's fatigue law)",
                 "diagnose", [fatigue], "114-146 s (issue 50)", "<= 60 s",
                 check_held_out(0.3))]
        if args.samplers:
            one = write_one_experiment_rig(tmp / "one")
            cases += [
                ("predict --method importance, the boom with running_in (as above)",
                 "predict", [*boom_predict, "--method", "importance"], "-", "<= 60 s",
                 "importance-boom"),
                ("predict --method importance, one rig experiment at 64 x 72", "predict",
                 [*one, "--method", "importance"], "-", "<= 3 min", check_sampler("importance")),
                ("predict --method nuts, one rig experiment at 64 x 72, 2 x (300 + 300)",
                 "predict", [*one, "--method", "nuts", "--draws", "300", "--warmup", "300",
                             "--max-minutes", "60"], "34 min (estimate)", "<= 3 min",
                 check_sampler("nuts"))]
        docs = {}
        for i, (label, verb, cmd, before, target, check) in enumerate(cases):
            if args.only and not any(o in label for o in args.only.split("|")):
                continue
            cache = tmp / f"cache{i}"
            cache.mkdir()
            walls, loads, shares = [], [], []
            ref = reference()
            for which in ("cold",) if args.cold_only else ("cold", "warm"):
                out = tmp / f"out{i}-{which}"
                js = out / "answer.json"
                tj = tmp / f"times{i}-{which}.json"
                wall, doc, err, l0, l1 = run([verb, *cmd, "--out", str(out), "--json", str(js)],
                                             js, cache, tj)
                shares.append(_shares(json.loads(tj.read_text())))
                if args.logs:
                    Path(args.logs).mkdir(parents=True, exist_ok=True)
                    Path(args.logs, f"row{i}-{which}.log").write_text(err)
                walls.append(wall)
                loads.append(f"{l0:.1f}/{l1:.1f}")
            docs[label] = doc
            if check == "importance-boom":
                lap = docs.get(cases[3][0])
                check = check_sampler("importance", lap)
            ok, text = check(doc, truth)
            evals = (doc.get("model_evaluations") or (doc.get("fit") or {}).get(
                "model_evaluations") or "?")
            row = (label, before, target, f"{walls[0]:.1f} s",
                   f"{walls[1]:.1f} s" if len(walls) > 1 else "-",
                   f"{walls[0] / ref:.1f} (ref {ref:.2f} s)", " / ".join(shares),
                   str(evals), _compiles(doc), ("ok: " if ok else "FAILED: ") + text,
                   " ".join(loads))
            rows.append(row)
            print(" | ".join(row), flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    lines = ["# Time to an answer (benchmarks/time_to_answer.py)", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} cores; "
             f"CLI wall clock per command in a fresh process; cold: an empty persistent "
             f"compilation cache, warm: the second run with that cache; load average "
             f"(1 min) before/after each run in the last column.", "",
             "Where the time went (cold / warm): import, compile (trace + lower + XLA, "
             "summed over threads), cache (reading the persistent cache), runs (jaxwear's "
             "compiled programs running, N top-level calls), host (the rest); see the "
             "script's docstring.", "",
             "| answer (CLI wall, defaults) | before: issue 19 / issue 26 (cold, evaluations) "
             "| target | cold | warm | cold / ref | where (cold / warm) | model evaluations | "
             "compiles | check | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


def write_one_experiment_rig(root: Path) -> list[str]:
    """A one-experiment rig study at 64 x 72 (adaptive integrator), data by `jaxwear synth`
    (truth at finer numerics, interrupted counts, 0.3 µm noise); the predict arguments:
    trained until its second-to-last count, forecast at its last."""
    root.mkdir(parents=True, exist_ok=True)
    cond = root / "conditions.toml"
    cond.write_text('[model]\npreset = "rig"\n[model.parameters]\nK_d_per_Pa = 1.0e-13\n'
                    '[numerics]\nnodes = 64\nsteps_per_rev = 72\n[fit]\n'
                    'clearance_tolerance_um = 5\n[[experiment]]\nname = "n276"\n'
                    'speed_rpm = 276\nclearance_mm = 0.05\nrevolutions = 10000\n')
    run(["synth", "--conditions", str(cond), "--noise-um", "0.3", "--seed", "2", "--out",
         str(root / "s")],
        None, None)
    sys.path.insert(0, str(ROOT))
    from jaxwear._study.study import load_study

    st = load_study(root / "s" / "study.toml")
    pts = st.experiments[0].snapshot_points
    return [str(root / "s" / "study.toml"), "--train-until", f"{pts[-2]:g}", "--at",
            f"{pts[-1]:g}"]


if __name__ == "__main__":
    raise SystemExit(main())
