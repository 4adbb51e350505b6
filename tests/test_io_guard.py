"""Inputs cannot be lost: the output guard of every verb, and atomic writes (`jaxwear._core.io`).

Each verb must refuse, with exit 2 and before any work, an output (a file under `--out` or
`--json FILE`) that would replace one of its input files. "Before any work" is checked by
replacing the verb's engine with a function that fails the test if it is called: an exit
code of 2 (not 1) and untouched inputs mean the guard refused first.
"""

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxwear import InputError
from jaxwear._core.io import OutputDir, atomic_open, atomic_write
from jaxwear._study.outputs import input_files
from jaxwear.cli import main

STUDY = """\
[model]
preset = "rig"
[numerics]
nodes = 48
steps_per_rev = 48
revolutions_per_update = 100

[[experiment]]
name = "a"
speed_rpm = 276
revolutions = 1000
clearance_mm = 0.05
profile = "{data}"
"""
PROFILE = "angle_deg,depth_um\n0,1.0\n90,0.2\n180,2.4\n270,0.1\n"


def _study(folder: Path, data: str = "measured.csv") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "study.toml").write_text(STUDY.format(data=data))
    (folder / data).write_text(PROFILE)
    return folder / "study.toml"


def _no_work(*a, **k):
    raise AssertionError("the verb started its work before refusing the output")


@pytest.fixture
def forbid_work(monkeypatch):
    import jaxwear.cli.calibrate as cal
    dia = importlib.import_module("jaxwear._analyses.diagnose")
    import jaxwear._analyses.sensitivity as sen
    import jaxwear._analyses.sweep as swe
    import jaxwear.cli.simulate as sim

    monkeypatch.setattr(sim, "simulate_study", _no_work)
    monkeypatch.setattr(cal, "build_problem", _no_work)
    monkeypatch.setattr(dia, "diagnose", _no_work)
    monkeypatch.setattr(dia, "Model", _no_work)  # synth's engine
    monkeypatch.setattr(swe, "sweep", _no_work)
    monkeypatch.setattr(sen, "study_sensitivities", _no_work)


# (verb, data file name that collides with one of the verb's outputs, extra arguments)
COLLISIONS = [
    ("simulate", "profiles.csv", []),
    ("simulate", "pressure_a.png", []),
    ("calibrate", "fit_residuals.csv", []),
    ("calibrate", "fit_a.png", []),
    ("diagnose", "residuals.csv", []),
    ("sweep", "sweep.csv", ["--speed-rpm", "100:200:2"]),
    ("sensitivity", "sensitivity.csv", []),
]


@pytest.mark.parametrize("verb,data,extra", COLLISIONS, ids=[f"{v}-{d}" for v, d, _ in
                                                             COLLISIONS])
def test_out_over_a_data_file_is_refused_before_work(tmp_path, forbid_work, capsys, verb,
                                                     data, extra):
    study = _study(tmp_path, data)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    rc = main([verb, str(study), "--out", str(tmp_path), *extra])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert data in err and "input" in err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


@pytest.mark.parametrize("verb", ["calibrate", "diagnose"])
@pytest.mark.parametrize("target", ["study.toml", "measured.csv"])
def test_json_over_an_input_is_refused_before_work(tmp_path, forbid_work, capsys, verb,
                                                   target):
    study = _study(tmp_path)
    before = (tmp_path / target).read_bytes()
    rc = main([verb, str(study), "--out", str(tmp_path / "out"), "--json",
               str(tmp_path / target)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "--json" in err and target in err
    assert (tmp_path / target).read_bytes() == before


def test_json_through_a_symlink_is_refused(tmp_path, forbid_work, capsys):
    study = _study(tmp_path)
    (tmp_path / "link.json").symlink_to(tmp_path / "study.toml")
    rc = main(["calibrate", str(study), "--out", str(tmp_path / "out"), "--json",
               str(tmp_path / "link.json")])
    assert rc == 2, capsys.readouterr().err
    assert (tmp_path / "study.toml").read_text() == STUDY.format(data="measured.csv")


@pytest.mark.parametrize("verb", ["simulate", "calibrate", "diagnose", "sensitivity"])
def test_out_that_is_the_study_file_is_refused(tmp_path, forbid_work, capsys, verb):
    study = _study(tmp_path)
    rc = main([verb, str(study), "--out", str(study)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "folder" in err
    assert study.read_text() == STUDY.format(data="measured.csv")


def test_synth_refuses_to_replace_its_conditions_in_process(tmp_path, forbid_work, capsys,
                                                            monkeypatch):
    _study(tmp_path, "a.csv")  # synth writes <experiment>.csv: a.csv is an input too
    monkeypatch.chdir(tmp_path)
    rc = main(["synth", "--hidden", "creep", "--conditions", "study.toml", "--out", "."])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "study.toml" in err or "a.csv" in err


def test_synth_conditions_out_dot_regression(tmp_path):
    """Issue 12: `jaxwear synth --hidden creep --conditions study.toml --out .` replaced
    the user's study.toml and exited 0. A real subprocess, as the user ran it."""
    study = _study(tmp_path)
    before = study.read_bytes()
    mtime = study.stat().st_mtime_ns
    # PYTHONPATH: the jaxwear of this checkout, whatever is installed in the environment
    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, JAXWEAR_NO_CACHE="1",
               PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
    env.pop("JAXWEAR_DEBUG", None)
    proc = subprocess.run([sys.executable, "-m", "jaxwear", "synth", "--hidden", "creep",
                           "--conditions", "study.toml", "--out", "."], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "study.toml" in proc.stderr and "Traceback" not in proc.stderr
    assert study.read_bytes() == before and study.stat().st_mtime_ns == mtime
    assert sorted(p.name for p in tmp_path.iterdir()) == ["measured.csv", "study.toml"]


def test_synth_library_call_is_guarded_too(tmp_path, forbid_work):
    from jaxwear._analyses.synth import synthesize

    study = _study(tmp_path)
    with pytest.raises(InputError, match="study.toml"):
        synthesize(["creep"], str(study), out=tmp_path)


def test_input_files_are_the_study_and_its_data(tmp_path):
    from jaxwear import load_study

    study = load_study(_study(tmp_path / "s", "data.csv"))
    assert sorted(p.name for p in input_files(study)) == ["data.csv", "study.toml"]


# --------------------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------------------

def test_an_interrupted_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "profiles.csv"
    target.write_text("old\n")

    def rows():
        yield ("a", 1.0)
        raise KeyboardInterrupt  # the user presses Ctrl-C half-way

    out = OutputDir(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        out.write_csv("profiles.csv", ["experiment", "depth_um"], rows())
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["profiles.csv"]


def test_an_interrupted_first_write_leaves_no_file(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_open(tmp_path / "report.html", "w") as f:
            f.write("<html>")
            raise RuntimeError("disk full")
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_replaces_and_follows_the_umask(tmp_path):
    p = tmp_path / "x.json"
    atomic_write(p, "{}")
    atomic_write(p, b"[1]")
    assert p.read_bytes() == b"[1]"
    old = os.umask(0o022)
    os.umask(old)
    assert p.stat().st_mode & 0o777 == 0o666 & ~old


def test_figures_are_written_atomically(tmp_path):
    from jaxwear._report.figures import plt

    pl = plt()
    fig, ax = pl.subplots()
    ax.plot([0, 1], [0, 1])
    p = OutputDir(tmp_path).savefig(fig, "f.png")
    pl.close(fig)
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [q.name for q in tmp_path.iterdir()] == ["f.png"]


# --------------------------------------------------------------------------------------
# The planned names are complete: a run writes only files its guard checked up front
# --------------------------------------------------------------------------------------

def test_synth_writes_exactly_its_planned_files(tmp_path):
    from jaxwear import load_study
    from jaxwear._analyses.synth import synth_outputs

    conditions = _study(tmp_path / "c")
    rc = main(["synth", "--hidden", "creep", "--conditions", str(conditions), "--out",
               str(tmp_path / "new"), "--noise-um", "0.1"])
    assert rc == 0
    written = {p.name for p in (tmp_path / "new").iterdir()}
    assert written == set(synth_outputs(load_study(conditions)))


def test_simulate_writes_only_planned_files(tmp_path):
    from jaxwear import load_study
    from jaxwear.cli.simulate import simulate_outputs

    study = _study(tmp_path / "s")
    assert main(["simulate", str(study), "--out", str(tmp_path / "o")]) == 0
    written = {p.name for p in (tmp_path / "o").iterdir()}
    assert written and written <= set(simulate_outputs(load_study(study)))
    assert "pressure_a.png" in written and not any(n.endswith(".part") for n in written)


# --------------------------------------------------------------------------------------
# Issue 49: a full disk named as such, a killed run's temporaries swept, Ctrl-C at shutdown
# --------------------------------------------------------------------------------------

def _full_disk(*args, **kwargs):
    import errno

    raise OSError(errno.ENOSPC, "No space left on device")


def test_a_full_disk_is_named_with_the_path_and_leaves_no_temporary(tmp_path, monkeypatch):
    from jaxwear._core.errors import NoSpaceError

    out = OutputDir(tmp_path / "o")
    monkeypatch.setattr(os, "fsync", _full_disk)  # the data reach the device at fsync
    with pytest.raises(NoSpaceError) as e:
        out.write_text("report.html", "<html>")
    assert str(tmp_path / "o" / "report.html") in str(e.value)
    assert "no space left on the device" in str(e.value)
    assert list((tmp_path / "o").iterdir()) == []


def test_a_full_disk_ends_the_command_in_one_line_exit_1(tmp_path, monkeypatch, capsys):
    """It read "internal error (OSError: [Errno 28] No space left on device); please report
    it"."""
    import jaxwear.cli.simulate as sim

    def engine(study, out):
        monkeypatch.setattr(os, "fsync", _full_disk)
        out.write_text("profiles.csv", "experiment,angle_deg,depth_um\n")

    monkeypatch.setattr(sim, "simulate_study", engine)
    study = _study(tmp_path)
    rc = main(["simulate", str(study), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1, err
    assert err.startswith(f"jaxwear: {tmp_path / 'o' / 'profiles.csv'}: no space left on the "
                          f"device"), err
    assert "internal error" not in err


def test_the_next_run_sweeps_a_killed_runs_temporaries(tmp_path):
    """A kill -9 during a run left `out/.fit_a.png.*.part`; a live run's are kept (two runs
    may share a folder)."""
    import time

    from jaxwear._core.io import LEGACY_PART_AGE_S, _temporary

    o = tmp_path / "o"
    o.mkdir()
    # a temporary of a process that is gone: a child that made one and was killed
    code = ("import sys; from pathlib import Path; from jaxwear._core.io import _temporary;"
            f"_temporary(Path({str(o / 'fit_a.png')!r})); import os; os._exit(0)")
    subprocess.run([sys.executable, "-c", code], check=True,
                   env=dict(os.environ, PYTHONPATH=str(Path(__file__).parent.parent)))
    dead = [p.name for p in o.iterdir()]
    assert len(dead) == 1 and dead[0].startswith(".fit_a.png.") and dead[0].endswith(".part")
    fd, mine = _temporary(o / "report.html")  # this process's: alive
    os.close(fd)
    old = o / ".summary.json.abcd1234.part"  # an older version's, an hour old
    old.write_text("{")
    stamp = time.time() - LEGACY_PART_AGE_S - 10
    os.utime(old, (stamp, stamp))
    young = o / ".profiles.csv.efgh5678.part"  # an older version's, just written
    young.write_text("x")
    keep = o / "notes.part"  # not a temporary's name
    keep.write_text("mine")
    OutputDir(o)  # the next run opens its outputs
    assert sorted(p.name for p in o.iterdir()) == sorted(
        [Path(mine).name, young.name, keep.name])


def test_ctrl_c_while_shutting_down_is_one_line(tmp_path):
    """A Ctrl-C that lands in JAX's exit hook (4.5 s into a 5 s calibrate) printed the
    hook's traceback. The exit hook here sends the interrupt itself, then waits (without
    the guard: Python's "Exception ignored in atexit callback" and its traceback)."""
    code = ("import atexit, os, signal, time\n"
            "from jaxwear._core.interrupt import shutting_down\n"
            "def hook():\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    time.sleep(5)\n"
            "atexit.register(hook)\n"
            "shutting_down(0)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60,
                       env=dict(os.environ, PYTHONPATH=str(Path(__file__).parent.parent)))
    # the run had ended: its exit status stands
    assert (p.returncode, p.stderr) == (
        0, "jaxwear: interrupted while shutting down (the outputs were written)\n")


def test_the_command_line_ends_with_its_exit_hooks_run_and_its_streams_flushed(tmp_path):
    """The command line's process ends without the interpreter's teardown
    (`interrupt.end_process`) but not without what a program relies on at exit: an exit
    hook registered before the run still runs after it, everything printed reaches the
    pipe (a line left in a buffer, unflushed, and the hook's own line after it), and
    the exit status is the run's (2 for bad input, 0 for argparse's own `--help`, which
    exits on its way and is left to Python)."""
    code = ("import atexit, sys\n"
            "atexit.register(lambda: print('hook ran', flush=False))\n"
            "sys.stdout.write('before the run')\n"
            "sys.argv = ['jaxwear'] + sys.argv[1:]\n"
            "from jaxwear.cli import main\n"
            "main()\n"
            "print('not reached')\n")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parent.parent))
    p = subprocess.run([sys.executable, "-c", code, "calibrate",
                        str(tmp_path / "missing.toml")], capture_output=True, text=True,
                       timeout=120, env=env)
    assert p.returncode == 2, p.stderr
    assert p.stdout == "before the runhook ran\n"
    assert "missing.toml" in p.stderr
    h = subprocess.run([sys.executable, "-c", code, "calibrate", "--help"],
                       capture_output=True, text=True, timeout=120, env=env)
    assert h.returncode == 0, h.stderr
    assert "usage:" in h.stdout and h.stdout.endswith("hook ran\n")


def test_a_full_device_met_elsewhere_is_named_too(tmp_path, monkeypatch, capsys):
    """A full device outside the outputs' own writes (a library writing its own file)."""
    import errno

    import jaxwear.cli.simulate as sim

    def engine(study, out):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "cache.bin"))

    monkeypatch.setattr(sim, "simulate_study", engine)
    rc = main(["simulate", str(_study(tmp_path)), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1 and err == (f"jaxwear: {tmp_path / 'cache.bin'}: no space left on the "
                               f"device (the disk or the quota is full); free some space or "
                               f"choose another output folder, and rerun\n"), err
