"""`jaxwear simulate STUDY.toml --out DIR` (design.md §6-7), run as a user would: a subprocess.

Good input: exit 0, profiles.csv with experiment,angle_deg,depth_um, one row per node per
experiment, in µm and degrees (checked against the library in SI), plots written.
Bad input: exit 2 and one line on stderr naming the file and the key or line, never a
traceback. The first bad input runs in a subprocess like the good one; the others through
`jaxwear.cli.main` in this process (the same path after the interpreter starts: each
subprocess spent ~3 s importing JAX to read two files, 53 s of the suite's setup).
"""

import contextlib
import csv
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxwear as jw

NODES, STEPS = 64, 72

STUDY = """\
[model]
preset = "rig"
contact = "unsymmetric"
effects = []

[model.parameters]
K_d_per_Pa = 1.0e-13
spring_N_per_m = 1009.4

[numerics]
nodes = 64
steps_per_rev = 72
revolutions_per_update = 100

[[experiment]]
name = "n276-c005"
speed_rpm = 276
revolutions = 2000
clearance_mm = 0.05
profile = "measured.csv"

[[experiment]]
name = "n148-c010"
speed_rpm = 148
revolutions = 2000
clearance_mm = 0.10
"""

PROFILE = "angle_deg,depth_um\n0,1.0\n90,0.2\n178.5,2.4\n270,0.1\n"


def run_cli(args, cwd, timeout=300, extra_env=None):
    env = dict(os.environ, **(extra_env or {}))
    env["JAXWEAR_CACHE_DIR"] = str(cwd / ".jax-cache")  # keep the CLI's cache out of $HOME
    env.pop("JAXWEAR_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "jaxwear", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


# --------------------------------------------------------------------------------------
# Good input
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def good_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("good")
    (d / "study.toml").write_text(STUDY)
    (d / "measured.csv").write_text(PROFILE)
    proc = run_cli(["simulate", "study.toml", "--out", "out"], d)
    return d, proc


def read_profiles(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def test_simulate_exit_code_and_profiles_csv(good_run):
    d, proc = good_run
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    header, rows = read_profiles(d / "out" / "profiles.csv")
    assert header == ["experiment", "angle_deg", "depth_um"]
    assert len(rows) == 2 * NODES
    for name in ("n276-c005", "n148-c010"):
        mine = [r for r in rows if r[0] == name]
        assert len(mine) == NODES
        angles = np.array([float(r[1]) for r in mine])
        depth = np.array([float(r[2]) for r in mine])
        assert angles == pytest.approx(np.arange(NODES) * 360 / NODES, abs=1e-9)
        assert np.all(np.isfinite(depth)) and np.all(depth >= 0) and depth.max() > 0


def test_simulate_units_match_library(good_run):
    """The CSV holds µm at degrees: the same numbers as the library's SI result."""
    d, proc = good_run
    assert proc.returncode == 0, proc.stderr
    _, rows = read_profiles(d / "out" / "profiles.csv")
    cfg = jw.ModelConfig(nodes=NODES, steps_per_rev=STEPS)
    for name, rpm, c in (("n276-c005", 276, 0.05), ("n148-c010", 148, 0.10)):
        p = jw.preset("rig", K_d_per_Pa=1e-13, spring_N_per_m=1009.4, speed_rpm=rpm,
                      clearance_mm=c)
        ref = np.asarray(jw.simulate(p, cfg, revolutions=2000, M=100).depth) * 1e6
        depth = np.array([float(r[2]) for r in rows if r[0] == name])
        assert depth == pytest.approx(ref, rel=1e-6, abs=1e-9 * ref.max())


def test_simulate_compiles_jaxwear_programs_only(tmp_path):
    """Every program a `simulate` compiles is one of jaxwear's (a function of the package,
    compiled through `_core.jit`), none an eager operation on a device array: each of
    those (a `jnp.max` of a result, a product of two rows of the load history) was an XLA
    compilation of its own, 20-90 ms in every process, below the persistent cache's
    threshold (10 of the 13 programs of a cached `simulate` of the rig study,
    docs/performance.md). The names come from JAX's own compile log."""
    (tmp_path / "study.toml").write_text(STUDY)
    (tmp_path / "measured.csv").write_text(PROFILE)
    proc = run_cli(["simulate", "study.toml", "--out", "out"], tmp_path,
                   extra_env={"JAX_LOG_COMPILES": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    names = set(re.findall(r"Compiling jit\(([^)]+)\)", proc.stderr))
    assert "wear_loop" in names  # the log is there to read
    package = Path(jw.__file__).parent
    source = "\n".join(f.read_text() for f in package.rglob("*.py"))
    eager = sorted(n for n in names if not re.search(rf"\bdef {re.escape(n)}\(", source))
    assert eager == [], eager


def test_simulate_writes_plots(good_run):
    d, proc = good_run
    assert proc.returncode == 0, proc.stderr
    pngs = list((d / "out").glob("*.png"))
    assert pngs
    for name in ("n276-c005", "n148-c010"):
        mine = [f for f in pngs if name in f.name]
        assert mine, f"no plot for {name}"
        assert all(f.stat().st_size > 1000 for f in mine)
        assert all(f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for f in mine)


# --------------------------------------------------------------------------------------
# Bad input: (id, study text, data file text or None, tokens the message must contain)
# --------------------------------------------------------------------------------------

def _swap(old, new, text=STUDY):
    assert old in text
    return text.replace(old, new, 1)


GOOD_CSV = PROFILE
BAD = [
    ("unknown-key-parameters", _swap("spring_N_per_m = 1009.4",
                                     "spring_N_per_m = 1009.4\nspring_lbs = 3"),
     GOOD_CSV, ["study.toml", "spring_lbs"]),
    ("unknown-key-experiment", _swap("clearance_mm = 0.10", "clearance_mm = 0.10\nrpm = 3"),
     GOOD_CSV, ["study.toml", "rpm"]),
    ("string-speed", _swap("speed_rpm = 276", 'speed_rpm = "276"'), GOOD_CSV,
     ["study.toml", "speed_rpm"]),
    ("negative-speed", _swap("speed_rpm = 276", "speed_rpm = -276"), GOOD_CSV,
     ["study.toml", "speed_rpm"]),
    ("zero-speed", _swap("speed_rpm = 276", "speed_rpm = 0"), GOOD_CSV,
     ["study.toml", "speed_rpm"]),
    ("zero-clearance", _swap("clearance_mm = 0.05", "clearance_mm = 0.0"), GOOD_CSV,
     ["study.toml", "clearance_mm"]),
    ("clearance-above-bore-radius", _swap("clearance_mm = 0.05", "clearance_mm = 8.0"),
     GOOD_CSV, ["study.toml", "clearance_mm"]),
    ("pin-equals-bore", _swap("clearance_mm = 0.05", "pin_diameter_mm = 15.0"), GOOD_CSV,
     ["study.toml", "clearance"]),
    ("crank-equals-coupler", _swap("K_d_per_Pa = 1.0e-13",
                                   "K_d_per_Pa = 1.0e-13\ncrank_length_mm = 200.0"),
     GOOD_CSV, ["study.toml", "crank_length_mm"]),
    ("missing-data-file", STUDY, None, ["measured.csv"]),
    ("data-nan-row", STUDY, "angle_deg,depth_um\n0,1.0\n90,nan\n", ["measured.csv", "line 3"]),
    ("data-non-numeric", STUDY, "angle_deg,depth_um\n0,1.0\n90,deep\n",
     ["measured.csv", "line 3"]),
    ("data-wrong-columns", STUDY, "angle,depth\n0,1.0\n90,2.0\n", ["measured.csv", "line 1"]),
    ("data-repeated-column", STUDY, "angle_deg,depth_um,depth_um\n0,1.0,1\n",
     ["measured.csv", "line 1"]),
    ("data-depth-um-and-mm", STUDY, "angle_deg,depth_um,depth_mm\n0,1.0,0.001\n",
     ["measured.csv", "line 1"]),
    ("data-angle-360", STUDY, "angle_deg,depth_um\n0,1.0\n360,0.5\n",
     ["measured.csv", "line 3"]),
    ("data-empty-file", STUDY, "", ["measured.csv"]),
    ("toml-syntax-error", _swap("[numerics]", "[numerics"), GOOD_CSV,
     ["study.toml", "line 10"]),
]


@pytest.fixture(scope="module")
def bad_runs(tmp_path_factory):
    """Every bad-input run (each only reads and validates its files)."""
    root = tmp_path_factory.mktemp("bad")

    from jaxwear.cli import main

    def one(case, in_process):
        name, study, data, _ = case
        d = root / name
        d.mkdir()
        (d / "study.toml").write_text(study)
        if data is not None:
            (d / "measured.csv").write_text(data)
        if not in_process:
            return name, run_cli(["simulate", "study.toml", "--out", "out"], d, timeout=120)
        out, err = io.StringIO(), io.StringIO()
        cwd = os.getcwd()
        try:
            os.chdir(d)  # the paths as the user typed them, relative to where they stand
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = main(["simulate", "study.toml", "--out", "out"])
        finally:
            os.chdir(cwd)
        return name, subprocess.CompletedProcess([], code, out.getvalue(), err.getvalue())

    return dict(one(case, i > 0) for i, case in enumerate(BAD))


@pytest.mark.parametrize("case", BAD, ids=[c[0] for c in BAD])
def test_bad_input_exits_2_with_one_line(bad_runs, case):
    name, _, _, tokens = case
    proc = bad_runs[name]
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, err)
    assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout
    assert err and "\n" not in err, err  # exactly one line
    for token in tokens:
        assert token in err, (token, err)


def test_a_second_study_in_one_process_leaves_no_thread_waiting(tmp_path):
    """`simulate` compiles the pressure map's program in a thread that waits for the first
    experiment's wear loop to be lowered. Run twice in one process (a notebook, a script
    calling `jaxwear.cli.main`), the second finds that loop compiled and never lowers it:
    the thread must still end with the study, else the interpreter's exit joins it for
    ever."""
    import threading

    from jaxwear.cli import main

    (tmp_path / "study.toml").write_text(STUDY.replace('profile = "measured.csv"\n', "")
                                         .replace("revolutions = 2000", "revolutions = 200"))
    for k in range(2):
        assert main(["simulate", str(tmp_path / "study.toml"), "--out",
                     str(tmp_path / f"out{k}")]) == 0
        assert (tmp_path / f"out{k}" / "pressure_n276-c005.png").exists()
        left = [t for t in threading.enumerate()
                if t.name == "jaxwear-pressure_program" and t.is_alive()]
        assert left == [], left
