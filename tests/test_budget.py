"""Work that cannot finish is refused up front (`jaxwear._study.budget`), exit 2 before any work.

The estimate is checked against the schedule the wear loop really builds (an upper bound,
tight to the snapshot count) and against hand counts; the refusals name the key to change.
"""

import importlib
import math

import pytest

from jaxwear import InputError, load_study
from jaxwear._physics.wear import build_schedule
from jaxwear._study.budget import check_work, estimate_work, wear_updates
from jaxwear.cli import main

CRANK = """\
[model]
preset = "rig"
[numerics]
nodes = {nodes}
steps_per_rev = {steps}
revolutions_per_update = {M}
[[experiment]]
name = "a"
revolutions = {revs}
clearance_mm = 0.05
{data}
"""
BOOM = """\
[model]
preset = "boom"
duty_cycle = [{{amplitude_deg = 30, duration_h = 0.5}}, {{amplitude_deg = 10, duration_h = 1.0}}]
[numerics]
nodes = 48
steps_per_rev = 48
revolutions_per_update = {M}
[[experiment]]
name = "b"
hours = {hours}
"""


def _write(tmp_path, text, data=None):
    if data is not None:
        (tmp_path / "p.csv").write_text(data)
    p = tmp_path / "study.toml"
    p.write_text(text)
    return p


def _crank(tmp_path, nodes=48, M=100, revs=1000, data=None, steps=48):
    line = 'profile = "p.csv"' if data else ""
    return _write(tmp_path, CRANK.format(nodes=nodes, M=M, revs=revs, data=line, steps=steps),
                  data)


def test_hand_count(tmp_path):
    study = load_study(_crank(tmp_path, nodes=48, M=100, revs=1000))
    est = estimate_work(study)
    assert est.updates == 10  # 1000 rev / 100 per update, no snapshot
    assert est.node_steps == 10 * 48 * 48


@pytest.mark.parametrize("M,revs,snaps", [(100, 1000, (1000,)), (70, 1000, (100, 333, 1000)),
                                          (1, 50, (7, 50)), (1e6, 1000, (500, 1000))])
def test_upper_bound_of_the_real_crank_schedule(tmp_path, M, revs, snaps):
    data = "angle_deg,depth_um,revolutions\n" + "".join(f"10,1,{s}\n" for s in snaps)
    study = load_study(_crank(tmp_path, M=M, revs=revs, data=data))
    exp = study.experiments[0]
    real = build_schedule(study.params(exp), study.config, revolutions=revs,
                          snapshots=exp.snapshot_points, M=M, pad=False).updates
    _, est = wear_updates(study, exp)
    assert real <= est <= real + len(snaps) + 1


@pytest.mark.parametrize("M,hours", [(100, 4.0), (1e9, 3.2), (3000, 0.7)])
def test_upper_bound_of_the_real_duty_cycle_schedule(tmp_path, M, hours):
    study = load_study(_write(tmp_path, BOOM.format(M=M, hours=hours)))
    exp = study.experiments[0]
    real = build_schedule(study.params(exp), study.config, hours=hours, M=M,
                          pad=False).updates
    cycles, est = wear_updates(study, exp)
    assert cycles == pytest.approx(hours * 3600 / float(study.params(exp).swing_period))
    segments = math.ceil(hours / 1.5) * 2  # the two blocks repeat every 1.5 h
    assert real <= est <= real + segments


@pytest.fixture
def forbid_work(monkeypatch):
    import jaxwear.cli.calibrate as cal
    dia = importlib.import_module("jaxwear._analyses.diagnose")
    import jaxwear._analyses.sensitivity as sen
    import jaxwear._analyses.sweep as swe
    import jaxwear.cli.simulate as sim

    def no_work(*a, **k):
        raise AssertionError("work started before the estimate refused it")

    for mod, name in ((sim, "simulate_study"), (cal, "build_problem"), (dia, "diagnose"),
                      (dia, "Model"), (swe, "sweep"), (sen, "study_sensitivities")):
        monkeypatch.setattr(mod, name, no_work)


VERBS = [["simulate"], ["calibrate"], ["diagnose"], ["sensitivity"],
         ["sweep", "--clearance-mm", "0.05:0.1:2"]]


@pytest.mark.parametrize("verb", VERBS, ids=[v[0] for v in VERBS])
def test_revolutions_1e11_is_refused_with_the_estimate(tmp_path, forbid_work, capsys, verb):
    # (1e15, this test's value before issue 29, is now refused as implausible: > 1e12)
    study = _crank(tmp_path, revs="1e11", data="angle_deg,depth_um\n10,1\n")
    rc = main([verb[0], str(study), "--out", str(tmp_path / "out"), *verb[1:]])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert "\n" not in err and "study.toml" in err
    assert "1e+09 wear updates" in err  # 1e11 rev / 100 per update
    for key in ("`revolutions`", "revolutions_per_update", "JAXWEAR_MAX_WORK"):
        assert key in err


def test_nodes_and_steps_1e5_are_refused_for_memory(tmp_path, forbid_work, capsys):
    # 1e5 x 1e5 (12 arrays of 80 GB): the most the plausible ranges allow (nodes = 1e8,
    # this test's value before issue 29, is refused as implausible)
    rc = main(["simulate", str(_crank(tmp_path, nodes=100_000, steps=100_000)), "--out",
               str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "numerics.nodes" in err and "GB of memory" in err and "JAXWEAR_MAX_MEMORY_GB" in err


def test_synth_refuses_impossible_conditions(tmp_path, forbid_work, capsys, monkeypatch):
    study = _crank(tmp_path, revs="1e11")
    monkeypatch.chdir(tmp_path)
    rc = main(["synth", "--hidden", "creep", "--conditions", str(study), "--out", "new"])
    assert rc == 2
    assert "JAXWEAR_MAX_WORK" in capsys.readouterr().err


def test_the_limits_can_be_raised(tmp_path, monkeypatch):
    study = load_study(_crank(tmp_path, nodes=100_000, steps=100_000))
    with pytest.raises(InputError):
        check_work(study)
    monkeypatch.setenv("JAXWEAR_MAX_WORK", "1e13")
    monkeypatch.setenv("JAXWEAR_MAX_MEMORY_GB", "1e5")
    est = check_work(study)
    assert est.node_steps == 10 * 1e5 * 1e5
    monkeypatch.setenv("JAXWEAR_MAX_WORK", "lots")
    with pytest.raises(InputError, match="JAXWEAR_MAX_WORK"):
        check_work(study)


def test_a_paper_scale_study_passes(tmp_path):
    # the paper's longest run, 10^5 revolutions at M = 100 on 360 x 360, must not be refused
    text = CRANK.format(nodes=360, M=100, revs=100000, data="", steps=48).replace(
        "steps_per_rev = 48", "steps_per_rev = 360")
    est = check_work(load_study(_write(tmp_path, text)), tangents=8)
    assert math.isfinite(est.seconds) and est.updates == 1000
