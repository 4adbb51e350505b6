"""jaxwear benchmarks: speed next to accuracy, against the plain NumPy reference.

    /work/venv/bin/python benchmarks/run.py [--quick] [--json FILE] [--results FILE]

Runs in one process (the command-line timings start the CLI as a subprocess, as a user
would), prints a table and writes `benchmarks/RESULTS.md` (`--quick`: a smaller, faster
set, written to `benchmarks/RESULTS-quick.md` unless `--results` says otherwise).

What is measured (every time after a warm-up call unless it says "cold"; medians of
repeats, interleaved where two things are compared, wall time and process CPU time):
- accuracy vs M: peak depth and whole profile against the M = 1 answer (full size; --quick
  uses a small case), which fixes the M for the rest: the largest M within 0.1 % peak error.
- `forward_s`: one rig prediction (276 r/min, 10 000 rev, 360 nodes, 360 steps/rev) with
  `jaxwear.simulate` at that M.
- `numpy_speedup`: the same prediction by `benchmarks/numpy_reference.py`, same M.
- `adaptive_rig_s` / `adaptive_boom_s`: the default (adaptive) integrator, no M, through
  `jaxwear.simulate`: the rig case above and the boom (25 h of the paper's duty cycle at
  K_d 3.8e-13, 360 x 360), with their errors against eq 23 at M = 1 and the integrator's
  own estimate; `*_fusion_s` the same on XLA:CPU's fusion emitters with the reassociation
  jaxwear asks for there, interleaved with the legacy emitters (`jaxwear._core.jit`);
  `adaptive_grad_over_forward`: `jax.grad` of a scalar loss of (K_d, clearance) through it.
- `grad_over_forward`: `jax.grad` of a 5-experiment calibration loss over its forward time.
- `sweep_speedup`: a 16x16 speed x clearance sweep, `jit(vmap(wear_loop))` vs 256 calls of
  the same compiled single-point function (also `lax.map` and `sharded_vmap`);
  `sweep_user_speedup`: the same 256 calls vs `jaxwear.sweep` on the same grid, the path
  users run (its CPU default `lax.map` over chunks of 16 points; its schedule padded to a
  bucket as `simulate`'s).
- `calibrate_s`: `jaxwear calibrate --fit K_d,clearance` on the paper's rig matrix with
  synthetic data, cold (fresh compilation cache), as a subprocess.
- `simulate_cold_s` / `simulate_cached_s`: `jaxwear simulate calibration/rig/study.toml`
  with an empty and with a filled persistent compilation cache.

The machine is named in the output (CPU model, cores, versions, load average): timings from
a shared or loaded machine are noisy, so CPU times are reported next to wall times.

This process never calls `jaxwear.configure_xla()` and leaves `XLA_FLAGS` as it finds them:
the figures are a library user's (`import jaxwear`, XLA's defaults in the process; jaxwear's
own programs compiled with the per-program options of `jaxwear._core.jit`). Every program
timed here is compiled through that wrapper.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxwear as jw
from jaxwear._core import jit as jwjit
from jaxwear._physics.wear import build_schedule, wear_loop

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
import numpy_reference  # noqa: E402

RIG_MATRIX = [  # design.md §6: (name, speed r/min, revolutions, nominal clearance mm)
    ("n276-r10000", 276.0, 10000, 0.05), ("n276-r15000", 276.0, 15000, 0.05),
    ("n148-r10000", 148.0, 10000, 0.05), ("n230-r10000-c010", 230.0, 10000, 0.10),
    ("n230-r10000-c015", 230.0, 10000, 0.15)]
TRUE_K_D = 1.3e-13  # synthetic truth; the study starts the fit from 1e-13
TRUE_DC_UM = (3.0, -2.0, 4.0, -3.0, 2.0)  # true clearance minus nominal, µm
NOISE_UM = 0.3

TARGETS = {  # key: (target, "<=" or ">=", unit)
    "forward_s": (0.05, "<=", "s"), "numpy_speedup": (100, ">=", "x"),
    "grad_over_forward": (3, "<=", "x"), "sweep_speedup": (5, ">=", "x"),
    "calibrate_s": (10, "<=", "s"), "simulate_cold_s": (10, "<=", "s"),
    "simulate_cached_s": (3, "<=", "s"),
    # the default (adaptive) integrator, issues 9 and 50: within 0.01 % (rig) / 0.1 % (boom)
    # of M = 1; each emitter family of XLA:CPU (jaxwear's programs ask for the legacy ones)
    "adaptive_rig_s": (0.05, "<=", "s"), "adaptive_boom_s": (1.0, "<=", "s"),
    "adaptive_rig_fusion_s": (0.05, "<=", "s"), "adaptive_boom_fusion_s": (1.0, "<=", "s"),
    "adaptive_grad_over_forward": (3, "<=", "x")}
TARGETS["sweep_speedup"] = (1, ">=", "x")  # issue 50: batched at least as fast as singles
TARGETS["sweep_user_speedup"] = (1, ">=", "x")  # the same for `jaxwear.sweep`, the users' path

# XLA:CPU's emitter families, compared in one process, each with jaxwear's per-program
# options for it (`jaxwear._core.jit`): the legacy emitters at LLVM's O1, and the fusion
# emitters (jaxlib >= 0.11 has no other) with reassociation at O1. On a jaxlib without the
# legacy emitters both columns run the fusion emitters. Both without YNNPACK fusions, as
# jaxwear's defaults (`jwjit.NO_YNN`). `python -c` with `jwjit.options(None)` gives XLA's
# plain defaults (fusion emitters, no reassociation, O2, YNNPACK fusions).
FAMILIES = {"legacy": {**jwjit.LEGACY_EMITTERS, **jwjit.FAST_COMPILE, **jwjit.NO_YNN},
            "fusion": {**jwjit.FUSION_REASSOC, **jwjit.FAST_COMPILE, **jwjit.NO_YNN}}


def log(msg):
    print(msg, file=sys.stderr, flush=True)


def loadavg() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


class Timer:
    """Collects repeated (wall, cpu) measurements under names; medians for reporting."""

    def __init__(self):
        self.samples: dict[str, list[tuple[float, float]]] = {}

    def run(self, name, f, *args):
        t0, c0 = time.perf_counter(), time.process_time()
        out = jax.block_until_ready(f(*args))
        self.samples.setdefault(name, []).append(
            (time.perf_counter() - t0, time.process_time() - c0))
        return out

    def add(self, name, wall, cpu):
        self.samples.setdefault(name, []).append((wall, cpu))

    def wall(self, name):
        return statistics.median(s[0] for s in self.samples[name])

    def cpu(self, name):
        return statistics.median(s[1] for s in self.samples[name])

    def spread(self, name):
        w = [s[0] for s in self.samples[name]]
        return min(w), max(w), len(w)


def machine() -> dict:
    model = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {"cpu": model, "cores": os.cpu_count(), "usable_cores": usable,
            "platform": platform.platform(), "python": platform.python_version(),
            "jax": jax.__version__, "jaxlib": jax.lib.__version__ if hasattr(jax, "lib")
            else "n/a", "numpy": np.__version__, "backend": jax.default_backend(),
            "devices": jax.device_count(), "jaxwear": jw.__version__,
            "XLA_FLAGS": os.environ.get("XLA_FLAGS", "(unset)"),
            "jaxwear per-program options": jwjit.current_options(),
            "date": time.strftime("%Y-%m-%d %H:%M %Z"), "load_start": loadavg(),
            "git": _git()}


def _git() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                              capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "jaxwear"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "n/a"
    return head + (" (jaxwear/ has uncommitted changes)" if dirty else "")


# ---------------------------------------------------------------------------------------
# accuracy vs M, forward, NumPy reference

ACC_DEPTH: dict = {}  # M -> final depth of the accuracy table's case (M = 1: a reference)


def accuracy(T: Timer, nodes, steps, revolutions, Ms) -> list[dict]:
    """Peak-depth and profile error of each M against M = 1 (Ms[0] must be 1)."""
    p = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=nodes, steps_per_rev=steps)
    depth = {}
    for M in Ms:
        t0 = time.perf_counter()
        res = jw.simulate(p, cfg, revolutions=revolutions, M=M)
        first = time.perf_counter() - t0
        res = T.run(f"acc M={M}", lambda: jw.simulate(p, cfg, revolutions=revolutions, M=M))
        depth[M] = np.asarray(res.depth)
        ACC_DEPTH[M] = depth[M]
        log(f"  M={M}: peak {depth[M].max() * 1e6:.4f} µm, first call {first:.1f} s, "
            f"then {T.wall(f'acc M={M}'):.3f} s")
    ref = depth[Ms[0]]
    peak = ref.max()
    rows = []
    for M in Ms:
        rows.append({"M": M, "updates": int(np.ceil(revolutions / M)),
                     "peak_um": float(depth[M].max() * 1e6),
                     "peak_error": float(abs(depth[M].max() - peak) / peak),
                     "profile_error": float(np.max(np.abs(depth[M] - ref)) / peak),
                     "wall_s": T.wall(f"acc M={M}"), "cpu_s": T.cpu(f"acc M={M}")})
    return rows


def forward_and_numpy(T: Timer, M, repeats, np_repeats):
    """jaxwear.simulate vs the NumPy reference at the same M, interleaved."""
    p = jw.preset("rig")
    cfg = jw.ModelConfig()
    run = lambda: jw.simulate(p, cfg, revolutions=10000, M=M)
    sched = build_schedule(p, cfg, revolutions=10000, M=M, pad=False)
    loop = jwjit.jit(lambda p, s: wear_loop(p, cfg, s).depth)
    jax.clear_caches()  # the accuracy table compiled this shape already: measure a cold call
    t0, c0 = time.perf_counter(), time.process_time()
    h_jax = np.asarray(run().depth)
    T.add("forward first call (compile + run)", time.perf_counter() - t0,
          time.process_time() - c0)
    loop(p, sched).block_until_ready()
    per_np = max(1, repeats // max(np_repeats, 1))
    h_np = None
    for i in range(max(repeats, np_repeats * per_np)):
        if i % per_np == 0 and len(T.samples.get("numpy", [])) < np_repeats:
            out = T.run("numpy", lambda: numpy_reference.simulate_rig(
                speed_rpm=276.0, revolutions=10000, M=M, nodes=360, steps=360,
                clearance_m=0.05e-3, K_d=1e-13, spring=1009.4, contact="unsymmetric"))
            h_np = out["h"]
            log(f"  numpy reference: {T.samples['numpy'][-1][0]:.2f} s")
        T.run("forward", lambda: run().depth)
        T.run("wear_loop (no padding)", loop, p, sched)
        with jwjit.options(FAMILIES["fusion"]):
            T.run("forward [fusion emitters]", lambda: run().depth)
    diff = float(np.max(np.abs(h_np - h_jax)) / np.max(h_jax))
    return {"relative_difference_numpy_vs_jax": diff}


def adaptive(T: Timer, nodes, steps, revolutions, hours, repeats, rig_ref=None):
    """The default integrator (no M): rig and boom forward times, their error against eq 23
    at M = 1 and the integrator's own estimate; gradient / forward on the rig for a scalar
    loss of (K_d, clearance), as `benchmarks/integrator_diffrax.py`."""
    from jaxwear._physics.config import boom_config

    out = {}
    cases = {"rig": (jw.preset("rig"), jw.ModelConfig(nodes=nodes, steps_per_rev=steps),
                     {"revolutions": revolutions}),
             # issue 9's boom: its fitted K_d, the paper's duty cycle
             "boom": (jw.preset("boom", K_d_per_Pa=3.8e-13),
                      boom_config(nodes=nodes, steps_per_rev=steps), {"hours": hours})}
    for name, (p, cfg, run) in cases.items():
        if name == "rig" and rig_ref is not None:
            ref = rig_ref
        else:
            t0 = time.perf_counter()
            ref = np.asarray(jw.simulate(p, cfg, M=1, **run).depth)
            log(f"  {name}: M = 1 reference {time.perf_counter() - t0:.1f} s")
        first, res = {}, {}
        for fam, opts in FAMILIES.items():  # compile each family's program (+ one run)
            with jwjit.options(opts):
                t0 = time.perf_counter()
                res[fam] = jax.block_until_ready(jw.simulate(p, cfg, **run))
                first[fam] = time.perf_counter() - t0
        r = res["legacy"]
        sched = build_schedule(p, cfg, **run)  # the rig's gradient below
        if not np.isfinite(float(r.error_estimate)):  # `simulate` raised the attempts
            sched = sched.more_attempts()
        for _ in range(repeats):
            for fam, opts in FAMILIES.items():
                with jwjit.options(opts):
                    T.run(f"adaptive {name} [{fam}]", lambda: jw.simulate(p, cfg, **run).depth)
        h = np.asarray(r.depth)
        out[name] = {"steps": int(r.steps), "rejected": int(r.rejected_steps),
                     "estimate_um": float(r.error_estimate) * 1e6,
                     "error": float(np.max(np.abs(h - ref)) / ref.max()),
                     "peak_um": float(h.max()) * 1e6, "first_s": first}
        log(f"  {name}: " + ", ".join(f"{fam} {T.wall(f'adaptive {name} [{fam}]'):.3f} s"
                                      for fam in FAMILIES) + f", {out[name]}")
        if name == "rig":
            x0 = jnp.asarray([float(p.get("K_d_per_Pa")), float(p.get("clearance_mm"))])

            def loss(x, p=p, cfg=cfg, sched=sched):
                q = p.with_values({"K_d_per_Pa": x[0], "clearance_mm": x[1]})
                hh = wear_loop(q, cfg, sched).depth * 1e6
                return jnp.sum(hh ** 3) / jnp.sum(hh ** 2)

            f = jwjit.jit(loss)
            g = jwjit.jit(jax.grad(loss))
            f(x0).block_until_ready()
            g(x0).block_until_ready()
            for _ in range(repeats):
                T.run("adaptive rig loss forward", f, x0)
                T.run("adaptive rig loss grad", g, x0)
    return out


# ---------------------------------------------------------------------------------------
# synthetic study (calibration loss, calibrate CLI)

def write_synthetic_study(folder: Path, nodes, steps, M) -> Path:
    """The rig matrix with profiles from the model at known K_d and clearances, plus noise."""
    rng = np.random.default_rng(0)
    cfg = jw.ModelConfig(nodes=nodes, steps_per_rev=steps)
    every = max(1, nodes // 120)  # about 120 measured points per profile
    lines = [f"# synthetic: rig matrix, K_d = {TRUE_K_D:.3g} (true), clearances nominal + "
             f"{list(TRUE_DC_UM)} um, noise {NOISE_UM:.2f} um",
             "[model]", 'preset = "rig"', 'contact = "unsymmetric"', "effects = []",
             "[model.parameters]", "K_d_per_Pa = 1.0e-13", "spring_N_per_m = 1009.4",
             "[numerics]", f"nodes = {nodes}", f"steps_per_rev = {steps}",
             f"revolutions_per_update = {M}"]
    for (name, speed, revs, c_mm), dc in zip(RIG_MATRIX, TRUE_DC_UM):
        p = jw.preset("rig", speed_rpm=speed, clearance_mm=c_mm + dc * 1e-3,
                      K_d_per_Pa=TRUE_K_D)
        h_um = np.asarray(jw.simulate(p, cfg, revolutions=revs, M=M).depth) * 1e6
        idx = np.arange(0, nodes, every)
        meas = np.maximum(h_um[idx] + rng.normal(0.0, NOISE_UM, idx.size), 0.0)
        rows = ["angle_deg,depth_um"] + [f"{a:.6f},{d:.6f}" for a, d in
                                         zip(idx * 360.0 / nodes, meas)]
        (folder / f"{name}.csv").write_text("\n".join(rows) + "\n")
        lines += ["[[experiment]]", f'name = "{name}"', f"speed_rpm = {speed}",
                  f"revolutions = {revs}", f"clearance_mm = {c_mm}", f'profile = "{name}.csv"']
    path = folder / "study.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def grad_vs_forward(T: Timer, study_path: Path, repeats):
    """Reverse-mode gradient of Σ residuals² over its forward evaluation."""
    from jaxwear._inference.calibrate import build_problem, parse_fit
    from jaxwear._study.study import load_study

    study = load_study(study_path)
    prob = build_problem(study, parse_fit(study, "K_d,clearance"))
    loss = lambda pr, u: jnp.sum(((pr.predict(u) - pr.data.depth_um) / NOISE_UM) ** 2)
    fwd = jwjit.jit(loss)
    grad = jwjit.jit(lambda pr, u: jax.grad(lambda v: loss(pr, v))(u))
    u = jnp.zeros(len(prob.names))
    t0, c0 = time.perf_counter(), time.process_time()
    fwd(prob, u).block_until_ready()
    T.add("loss first call (compile + run)", time.perf_counter() - t0, time.process_time() - c0)
    t0, c0 = time.perf_counter(), time.process_time()
    g = grad(prob, u).block_until_ready()
    T.add("grad first call (compile + run)", time.perf_counter() - t0, time.process_time() - c0)
    for _ in range(repeats):
        T.run("loss forward", fwd, prob, u)
        T.run("loss grad", grad, prob, u)
    # A one-sided check that the gradient is the loss's: along g, the loss falls at rate |g|².
    eps = 1e-6 / float(jnp.linalg.norm(g))
    fd = (float(fwd(prob, u)) - float(fwd(prob, u - eps * g))) / eps
    return {"parameters": len(prob.names), "grad_fd_check": fd / float(g @ g)}


# ---------------------------------------------------------------------------------------
# sweep

def sweep(T: Timer, n_side, nodes, steps, revolutions, M, repeats):
    from jaxwear._core.parallel import sharded_vmap

    p = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=nodes, steps_per_rev=steps)
    sched = build_schedule(p, cfg, revolutions=revolutions, M=M, pad=False)
    speed, clear = np.meshgrid(np.linspace(148.0, 276.0, n_side) * 2 * np.pi / 60,
                               np.linspace(0.05, 0.15, n_side) * 1e-3, indexing="ij")
    speed, clear = jnp.asarray(speed.ravel()), jnp.asarray(clear.ravel())

    def point(s, c):
        return wear_loop(p.with_values({"speed_rpm": s, "clearance_mm": c}), cfg, sched).depth

    single = jwjit.jit(point)
    batched = jwjit.jit(jax.vmap(point))
    mapped = jwjit.jit(lambda s, c: jax.lax.map(lambda a: point(*a), (s, c)))
    singles = lambda: [single(s, c) for s, c in zip(speed, clear)]
    axes = {"speed_rpm": np.linspace(148.0, 276.0, n_side),
            "clearance_mm": np.linspace(0.05, 0.15, n_side)}

    def user():  # the path users run: jaxwear.sweep, its defaults (CPU: lax.map, chunks)
        return jw.sweep(p, cfg, axes, revolutions=revolutions, M=M).depth_um.reshape(
            n_side * n_side, -1) * 1e-6

    ways = {"sweep singles": singles, "sweep vmap": lambda: batched(speed, clear),
            "sweep lax.map": lambda: mapped(speed, clear),
            "sweep sharded_vmap(map)": lambda: sharded_vmap(point, (speed, clear),
                                                            method="map"),
            "sweep jaxwear.sweep": user}
    compile_s = {}
    for name, f in ways.items():
        t0 = time.perf_counter()
        jax.block_until_ready(f())
        compile_s[name] = time.perf_counter() - t0
        log(f"  {name}: first call {compile_s[name]:.1f} s")
    ref = np.stack(singles())
    for _ in range(repeats):
        for name, f in ways.items():
            out = T.run(name, f)
            err = np.max(np.abs(np.asarray(jnp.stack(out) if isinstance(out, list) else out)
                                - ref))
            assert err <= 1e-12 * np.max(ref), f"{name} differs from singles by {err}"
        log("  sweep repeat: " + ", ".join(f"{n} {T.samples[n][-1][0]:.2f} s" for n in ways))
    return {"points": n_side * n_side, "nodes": nodes, "steps": steps,
            "revolutions": revolutions, "M": M, "updates": sched.updates,
            "first_call_s": compile_s}


# ---------------------------------------------------------------------------------------
# command line (subprocesses)

def run_cli(T: Timer, name, args, env_extra, cwd):
    """Run `jaxwear ARGS` as a subprocess; wall and CPU (user + system of the child)."""
    env = dict(os.environ)
    env.update(env_extra)
    cmd = [sys.executable, "-m", "jaxwear", *args]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    T.add(name, wall, cpu)
    log(f"  {name}: {wall:.1f} s wall, {cpu:.1f} s cpu")
    return proc


def cli_startup(T: Timer, study: Path, reps, tmp: Path):
    """`jaxwear simulate` with an empty, then a filled, persistent compilation cache."""
    for r in range(reps):
        cache = tmp / f"cache-sim-{r}"
        env = {"JAXWEAR_CACHE_DIR": str(cache)}
        run_cli(T, "simulate cold", ["simulate", str(study), "--out", str(tmp / "sim")],
                env, tmp)
        run_cli(T, "simulate cached", ["simulate", str(study), "--out", str(tmp / "sim")],
                env, tmp)
    # as an installed package imports: with its bytecode written. An environment that sets
    # PYTHONDONTWRITEBYTECODE (this project's sandbox does) compiles jaxwear's sources in
    # every process: 1.28-2.23 s against 1.10-1.63 s, 8 interleaved runs (2026-11-30)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    subprocess.run([sys.executable, "-c", "import jaxwear"], check=True, env=env)
    for _ in range(reps):
        for name in ("jax", "jaxwear"):  # jax alone beside it: what jaxwear adds
            t0 = time.perf_counter()
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            subprocess.run([sys.executable, "-c", f"import {name}"], check=True, env=env)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            T.add(f"import {name}", time.perf_counter() - t0,
                  after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)


def calibrate_cli(T: Timer, study: Path, tmp: Path, reps):
    out = {}
    for r in range(reps):
        env = {"JAXWEAR_CACHE_DIR": str(tmp / f"cache-cal-{r}")}
        for kind in ("cold", "cached"):
            js = tmp / f"cal-{kind}-{r}.json"
            args = ["calibrate", str(study), "--fit", "K_d,clearance", "--out",
                    str(tmp / "cal"), "--json", str(js)]
            proc = run_cli(T, f"calibrate {kind}", args, env, tmp)
            out = json.loads(js.read_text())
            fit_s = [float(line.split("fit took")[1].split()[0])
                     for line in proc.stderr.splitlines() if "fit took" in line]
            if fit_s:  # the CLI's own timing of fit(): the rest is start-up and compilation
                T.add(f"calibrate {kind}: fit() alone", fit_s[0], float("nan"))
    par = out["parameters"]
    k = par["K_d_per_Pa"]
    rec = {"K_d_fitted": k["value"], "K_d_stderr": k["stderr"], "K_d_true": TRUE_K_D,
           "rmse_um": out.get("rmse_um")}
    for (name, _, _, c_mm), dc in zip(RIG_MATRIX, TRUE_DC_UM):
        v = par[f"clearance_mm/{name}"]
        rec[f"clearance_error_um/{name}"] = (v["value"] - (c_mm + dc * 1e-3)) * 1e3
    return rec


def small_copy(study: Path, folder: Path, nodes, steps) -> Path:
    """The rig study with coarser numerics (--quick)."""
    text = study.read_text()
    text = text.replace("nodes = 360", f"nodes = {nodes}").replace(
        "steps_per_rev = 360", f"steps_per_rev = {steps}")
    path = folder / "study-small.toml"
    path.write_text(text)
    return path


# ---------------------------------------------------------------------------------------
# report

def verdict(key, value):
    target, op, unit = TARGETS[key]
    ok = value <= target if op == "<=" else value >= target
    return f"{op} {target:g} {unit}", "met" if ok else "MISSED"


def fmt(v, unit="s"):
    if v != v:
        return "n/a"
    if unit == "x":
        return f"{v:.3g}x"
    return f"{v:.3g} s" if v >= 0.01 else f"{v * 1e3:.3g} ms"


def report(info, T: Timer, acc, extra, keys, quick) -> str:
    L = []
    L.append("# jaxwear benchmark results" + (" (--quick)" if quick else ""))
    L.append("")
    L.append("Written by `python benchmarks/run.py" + (" --quick" if quick else "") + "`. "
             "Times are medians of repeats after a warm-up call (except where marked cold), "
             "wall clock and process CPU time (all threads; children for the CLI).")
    L.append("")
    L.append("## Machine")
    L.append("")
    for k in ("cpu", "cores", "usable_cores", "platform", "python", "jax", "jaxlib", "numpy",
              "backend", "devices", "jaxwear", "XLA_FLAGS", "jaxwear per-program options",
              "git", "date", "load_start", "load_end"):
        L.append(f"- {k}: {info.get(k)}")
    L.append("")
    L.append("## Targets")
    L.append("")
    L.append("| metric | value | target | | how |")
    L.append("|---|---|---|---|---|")
    how = extra["how"]
    for key in TARGETS:
        if key not in keys:
            L.append(f"| `{key}` | not measured | {verdict(key, 0)[0]} | | {how.get(key, '')} |")
            continue
        tgt, ok = verdict(key, keys[key])
        unit = TARGETS[key][2]
        L.append(f"| `{key}` | {fmt(keys[key], unit)} | {tgt} | {ok} | {how.get(key, '')} |")
    L.append("")
    L.append("## Accuracy against M = 1 (" + extra["accuracy_case"] + ")")
    L.append("")
    L.append("Peak error: |max h(M) - max h(1)| / max h(1). Profile error: max_j |h_j(M) - "
             "h_j(1)| / max h(1), the worst node (a stricter measure).")
    L.append("")
    L.append("| M | updates | peak depth [µm] | peak error | profile error | wall | cpu |")
    L.append("|---|---|---|---|---|---|---|")
    for r in acc:
        L.append(f"| {r['M']:g} | {r['updates']} | {r['peak_um']:.4f} | "
                 f"{r['peak_error'] * 100:.4f} % | {r['profile_error'] * 100:.4f} % | "
                 f"{fmt(r['wall_s'])} | {fmt(r['cpu_s'])} |")
    L.append("")
    L.append(f"M used below: {extra['M']} ({extra['M_why']}).")
    L.append("")
    L.append("## All timings")
    L.append("")
    L.append("| measurement | wall (median) | cpu (median) | wall min..max | n |")
    L.append("|---|---|---|---|---|")
    for name in T.samples:
        lo, hi, n = T.spread(name)
        L.append(f"| {name} | {fmt(T.wall(name))} | {fmt(T.cpu(name))} | "
                 f"{fmt(lo)}..{fmt(hi)} | {n} |")
    L.append("")
    L.append("## Ratios (wall and CPU)")
    L.append("")
    for line in extra["ratios"]:
        L.append(f"- {line}")
    L.append("")
    if "profile" in extra:
        rows, pnotes = extra["profile"]
        L.append("## Where the time of one forward run goes (`benchmarks/profile_forward.py`)")
        L.append("")
        L.append("| piece | wall | cpu | note |")
        L.append("|---|---|---|---|")
        for name, w, c, note in rows:
            L.append(f"| {name.strip()} | {fmt(w)} | {fmt(c)} | {note} |")
        L.append("")
        L += [f"- {n}" for n in pnotes]
        L.append("")
    L.append("## Checks and notes")
    L.append("")
    for line in extra["notes"]:
        L.append(f"- {line}")
    L.append("")
    return "\n".join(L)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller, faster set (CI smoke)")
    ap.add_argument("--json", default=None, help="write the headline numbers to this file")
    ap.add_argument("--results", default=None,
                    help="markdown report (default benchmarks/RESULTS.md, "
                         "RESULTS-quick.md with --quick)")
    ap.add_argument("--skip", default="", help="comma-separated sections to skip: accuracy, "
                    "forward, adaptive, grad, sweep, calibrate, simulate, profile (for "
                    "development)")
    args = ap.parse_args(argv)
    quick = args.quick
    skip = set(filter(None, args.skip.split(",")))
    results = Path(args.results) if args.results else HERE / (
        "RESULTS-quick.md" if quick else "RESULTS.md")
    info = machine()
    log(f"machine: {info['cpu']}, {info['cores']} cores, jax {info['jax']}, "
        f"load {info['load_start']}")
    T = Timer()
    keys: dict = {}
    extra = {"how": {}, "ratios": [], "notes": []}
    notes = extra["notes"]
    tmp = Path(tempfile.mkdtemp(prefix="jaxwear-bench-"))

    # 1. accuracy vs M: fixes M for the forward comparison.
    acc = []
    M = 500
    extra["M_why"] = "default: the lead's measured table (0.079 % at M = 500)"
    if quick:
        extra["accuracy_case"] = "--quick: 72 nodes, 72 steps/rev, 2000 revolutions"
        if "accuracy" not in skip:
            log("accuracy vs M (small case)")
            acc = accuracy(T, 72, 72, 2000, (1, 10, 100, 250))
    else:
        extra["accuracy_case"] = "rig, 276 r/min, 10 000 rev, 360 nodes, 360 steps/rev"
        if "accuracy" not in skip:
            log("accuracy vs M (full size; M = 1 takes a minute or two)")
            acc = accuracy(T, 360, 360, 10000, (1, 10, 100, 250, 500, 1000))
            ok = [r["M"] for r in acc if r["peak_error"] <= 1e-3]
            M = max(ok)
            extra["M_why"] = "the largest M in the table within 0.1 % peak error"
            keys["accuracy_peak_error"] = {str(r["M"]): r["peak_error"] for r in acc}
            keys["accuracy_profile_error"] = {str(r["M"]): r["profile_error"] for r in acc}
    extra["M"] = M

    # 2. forward and the NumPy reference.
    if "forward" not in skip:
        log(f"forward (M = {M}) and NumPy reference, interleaved")
        chk = forward_and_numpy(T, M, repeats=5 if quick else 15, np_repeats=1 if quick else 3)
        keys["forward_s"] = T.wall("forward")
        keys["numpy_s"] = T.wall("numpy")
        keys["numpy_speedup"] = T.wall("numpy") / T.wall("forward")
        extra["how"]["forward_s"] = (f"`jw.simulate`, 276 r/min, 10 000 rev, 360x360, M = {M}; "
                                     f"cpu {fmt(T.cpu('forward'))}")
        extra["how"]["numpy_speedup"] = (f"numpy_reference.simulate_rig, same case and M; "
                                         f"{fmt(T.wall('numpy'))} vs {fmt(T.wall('forward'))}")
        extra["ratios"].append(f"numpy / forward: wall {keys['numpy_speedup']:.1f}x, cpu "
                               f"{T.cpu('numpy') / T.cpu('forward'):.1f}x")
        keys["forward_fusion_s"] = T.wall("forward [fusion emitters]")
        fus = T.wall("forward [fusion emitters]")
        extra["ratios"].append(
            f"forward, fusion / legacy emitters: wall {fus / T.wall('forward'):.2f}x; numpy / "
            f"forward with the fusion emitters {T.wall('numpy') / fus:.1f}x")
        extra["ratios"].append(
            f"numpy / wear_loop without schedule padding: wall "
            f"{T.wall('numpy') / T.wall('wear_loop (no padding)'):.1f}x, cpu "
            f"{T.cpu('numpy') / T.cpu('wear_loop (no padding)'):.1f}x")
        notes.append(f"NumPy reference vs jaxwear, same M: max |Δh| / max h = "
                     f"{chk['relative_difference_numpy_vs_jax']:.2e}")
        keys["numpy_vs_jax_relative_difference"] = chk["relative_difference_numpy_vs_jax"]

    # 2b. the default adaptive integrator (issue 9's targets)
    if "adaptive" not in skip:
        a_nodes, a_rev, a_hours = (72, 2000, 5.0) if quick else (360, 10000, 25.0)
        log(f"adaptive integrator: rig {a_rev} rev and boom {a_hours:g} h at "
            f"{a_nodes}x{a_nodes}, against M = 1")
        ad = adaptive(T, a_nodes, a_nodes, a_rev, a_hours, repeats=3 if quick else 5,
                      rig_ref=ACC_DEPTH.get(1) if (a_nodes, a_rev) == (
                          (72, 2000) if quick else (360, 10000)) else None)
        keys["adaptive_rig_s"] = T.wall("adaptive rig [legacy]")
        keys["adaptive_boom_s"] = T.wall("adaptive boom [legacy]")
        keys["adaptive_rig_fusion_s"] = T.wall("adaptive rig [fusion]")
        keys["adaptive_boom_fusion_s"] = T.wall("adaptive boom [fusion]")
        for name in ("rig", "boom"):
            fu, le = f"adaptive {name} [fusion]", f"adaptive {name} [legacy]"
            extra["ratios"].append(
                f"adaptive {name}, fusion / legacy emitters: wall {T.wall(fu) / T.wall(le):.2f}"
                f"x, cpu {T.cpu(fu) / T.cpu(le):.2f}x; first call (compile + run) "
                f"{ad[name]['first_s']['legacy']:.1f} s vs {ad[name]['first_s']['fusion']:.1f} s")
        keys["adaptive_grad_over_forward"] = (T.wall("adaptive rig loss grad")
                                              / T.wall("adaptive rig loss forward"))
        keys["adaptive"] = ad
        for name, what in (("rig", f"{a_rev} rev"), ("boom", f"{a_hours:g} h, K_d 3.8e-13")):
            d = ad[name]
            extra["how"][f"adaptive_{name}_s"] = (
                f"`jw.simulate` default integrator, {name} {what}, {a_nodes}x{a_nodes}, "
                f"legacy emitters (per program): "
                f"{d['steps']} (+{d['rejected']}) steps, {d['error'] * 100:.2g} % of peak vs "
                f"M = 1 (estimate {d['estimate_um']:.2g} µm); cpu "
                f"{fmt(T.cpu(f'adaptive {name} [legacy]'))}")
            extra["how"][f"adaptive_{name}_fusion_s"] = (
                f"the same, XLA:CPU's fusion emitters with reassociation, interleaved; cpu "
                f"{fmt(T.cpu(f'adaptive {name} [fusion]'))}")
        extra["how"]["adaptive_grad_over_forward"] = (
            f"Σh³/Σh² of the rig run in (K_d, clearance): grad "
            f"{fmt(T.wall('adaptive rig loss grad'))} / forward "
            f"{fmt(T.wall('adaptive rig loss forward'))}")

    # 3. gradient of a 5-experiment calibration loss; the study also feeds `calibrate`.
    nodes = 72 if quick else 360
    study = write_synthetic_study(tmp, nodes, nodes, M)
    notes.append(f"synthetic study: the rig matrix at {nodes} nodes x {nodes} steps/rev, M = "
                 f"{M}, true K_d {TRUE_K_D:g} (start 1e-13), clearances nominal + "
                 f"{list(TRUE_DC_UM)} µm, noise {NOISE_UM} µm, one point per "
                 f"{360 / (nodes // max(1, nodes // 120)):.0f}°")
    if "grad" not in skip:
        log("calibration loss: forward and jax.grad")
        g = grad_vs_forward(T, study, repeats=3 if quick else 7)
        keys["grad_over_forward"] = T.wall("loss grad") / T.wall("loss forward")
        extra["how"]["grad_over_forward"] = (
            f"Σ residuals² of 5 experiments ({g['parameters']} parameters), {nodes}x{nodes}, "
            f"M = {M}; grad {fmt(T.wall('loss grad'))} / forward {fmt(T.wall('loss forward'))}")
        extra["ratios"].append(f"grad / forward: wall {keys['grad_over_forward']:.2f}x, cpu "
                               f"{T.cpu('loss grad') / T.cpu('loss forward'):.2f}x")
        notes.append(f"gradient check: directional finite difference / |g|² = "
                     f"{g['grad_fd_check']:.6f} (1 expected)")

    # 4. sweep
    if "sweep" not in skip:
        size = (8, 72, 72, 2000, 100) if quick else (16, 120, 120, 10000, M)
        log(f"sweep {size[0]}x{size[0]}, {size[1]} nodes x {size[2]} steps, {size[3]} rev, "
            f"M = {size[4]}")
        sw = sweep(T, *size, repeats=2 if quick else 3)
        keys["sweep_speedup"] = T.wall("sweep singles") / T.wall("sweep vmap")
        keys["sweep_map_speedup"] = T.wall("sweep singles") / T.wall("sweep lax.map")
        keys["sweep_user_speedup"] = T.wall("sweep singles") / T.wall("sweep jaxwear.sweep")
        extra["how"]["sweep_speedup"] = (
            f"{sw['points']} points, {sw['nodes']} nodes x {sw['steps']} steps, "
            f"{sw['revolutions']} rev, M = {sw['M']}: singles {fmt(T.wall('sweep singles'))}, "
            f"raw jit(vmap) of all {sw['points']} {fmt(T.wall('sweep vmap'))} (cpu "
            f"{T.cpu('sweep singles') / T.cpu('sweep vmap'):.2f}x); `jaxwear.sweep` (what "
            f"users run) {fmt(T.wall('sweep jaxwear.sweep'))}: "
            f"{keys['sweep_user_speedup']:.2f}x (cpu "
            f"{T.cpu('sweep singles') / T.cpu('sweep jaxwear.sweep'):.2f}x)")
        extra["how"]["sweep_user_speedup"] = (
            f"`jaxwear.sweep` on the same grid, its defaults ({jw.sweep.__module__}: CPU "
            f"lax.map in chunks of 16): {fmt(T.wall('sweep jaxwear.sweep'))} vs singles")
        for way in ("sweep vmap", "sweep lax.map", "sweep sharded_vmap(map)",
                    "sweep jaxwear.sweep"):
            extra["ratios"].append(
                f"singles / {way.split(' ', 1)[1]}: wall "
                f"{T.wall('sweep singles') / T.wall(way):.2f}x, cpu "
                f"{T.cpu('sweep singles') / T.cpu(way):.2f}x")
        notes.append("sweep first calls (compile + run): " + ", ".join(
            f"{k} {v:.1f} s" for k, v in sw["first_call_s"].items()))
        if not quick:
            log("sweep_devices.py: 1 vs 2 forced host devices (subprocesses)")
            for n_dev in (1, 2, 1, 2):
                env = dict(os.environ,
                           XLA_FLAGS=f"--xla_force_host_platform_device_count={n_dev}")
                line = subprocess.run([sys.executable, str(HERE / "sweep_devices.py")],
                                      env=env, capture_output=True, text=True,
                                      check=True).stdout.strip().splitlines()[-1]
                log(f"  {line}")
                notes.append(f"`sweep_devices.py` (64 points, 72x72, 2000 rev, M = 100, "
                             f"sharded_vmap map): {line}")

    # 5. the command line: calibrate (cold and cached) and simulate start-up.
    if "calibrate" not in skip:
        log("jaxwear calibrate (subprocess; cold, then cached)")
        rec = calibrate_cli(T, study, tmp, reps=1 if quick else 2)
        keys["calibrate_s"] = T.wall("calibrate cold")
        keys["calibrate_cached_s"] = T.wall("calibrate cached")
        extra["how"]["calibrate_s"] = (
            f"`jaxwear calibrate --fit K_d,clearance`, synthetic rig matrix ({nodes}x{nodes}, "
            f"M = {M}), empty compilation cache; cached: {fmt(T.wall('calibrate cached'))}")
        notes.append(f"calibrate recovered K_d = {rec['K_d_fitted']:.4g} ± "
                     f"{rec['K_d_stderr']:.2g} (true {TRUE_K_D:g}), rmse {rec['rmse_um']:.3f} µm "
                     f"(noise {NOISE_UM}); clearance errors [µm]: " + ", ".join(
                         f"{v:+.2f}" for k, v in rec.items() if k.startswith("clearance_error")))
    if "simulate" not in skip:
        rig = ROOT / "calibration" / "rig" / "study.toml"
        if quick:
            rig = small_copy(rig, tmp, 72, 72)
        log(f"jaxwear simulate {rig.name} (subprocess; cold, then cached)")
        cli_startup(T, rig, reps=1 if quick else 2, tmp=tmp)
        keys["simulate_cold_s"] = T.wall("simulate cold")
        keys["simulate_cached_s"] = T.wall("simulate cached")
        what = "calibration/rig/study.toml" + (" at 72x72 (--quick)" if quick else "")
        extra["how"]["simulate_cold_s"] = f"`jaxwear simulate {what}`, empty cache"
        extra["how"]["simulate_cached_s"] = (f"same, second run on the filled cache; "
                                             f"`import jaxwear` alone "
                                             f"{fmt(T.wall('import jaxwear'))} "
                                             f"(`import jax` {fmt(T.wall('import jax'))})")

    if "profile" not in skip and not quick:
        import contextlib

        import profile_forward

        log(f"profile of one forward run (M = {M})")
        with contextlib.redirect_stdout(sys.stderr):
            extra["profile"] = profile_forward.main(["--M", str(M)])

    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    info["load_end"] = loadavg()
    keys["machine"] = {k: info[k] for k in ("cpu", "cores", "jax", "backend")}
    keys["M"] = M
    md = report(info, T, acc, extra, keys, quick)
    results.write_text(md)
    print(md)
    log(f"wrote {results}")
    if args.json:
        Path(args.json).write_text(json.dumps(keys, indent=2))
        log(f"wrote {args.json}")
    return keys


if __name__ == "__main__":
    main()
