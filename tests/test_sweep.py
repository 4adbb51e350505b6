"""Batched sweeps: every grid point must equal a single `simulate` run at that point.

Same small grid as tests/test_calibrate.py (64 nodes, 72 steps, 3000 revolutions, M = 100,
snapshots at 1000/2000/3000 revolutions for the single runs) so the compiled single-run loop
is shared; snapshots only record profiles, they do not change the final one.
"""

from __future__ import annotations

import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.sweep import parse_range, sweep
from jaxwear.cli import main

NODES, STEPS, M, REVS = 64, 72, 100, 3000
SNAPS = (1000.0, 2000.0, 3000.0)
CFG = jw.ModelConfig(nodes=NODES, steps_per_rev=STEPS)
SPEEDS = np.array([150.0, 276.0])
CLEARANCES = np.array([0.05, 0.08, 0.12])


@pytest.fixture(scope="module")
def result():
    # 6 points in one chunk of 6: the chunk size the CLI test below uses too
    return sweep(jw.preset("rig", K_d_per_Pa=2e-13), CFG,
                 {"speed_rpm": SPEEDS, "clearance_mm": CLEARANCES},
                 revolutions=REVS, M=M, chunk=6)


def test_sweep_equals_single_runs(result):
    assert result.shape == (2, 3)
    assert list(result.axes) == ["speed_rpm", "clearance_mm"]
    assert result.peak_depth_um.dtype == np.float64
    area = 7.5e-3 * (2 * np.pi / NODES) * 28e-3  # A_j = R_b (2π/N) B [m²]
    for i, n in enumerate(SPEEDS):
        for j, c in enumerate(CLEARANCES):
            p = jw.preset("rig", K_d_per_Pa=2e-13, speed_rpm=n, clearance_mm=c)
            r = jw.simulate(p, CFG, revolutions=REVS, snapshots=SNAPS, M=M)
            depth = np.asarray(r.depth) * 1e6
            np.testing.assert_allclose(result.depth_um[i, j], depth, rtol=1e-10, atol=1e-12)
            assert result.peak_depth_um[i, j] == pytest.approx(depth.max(), rel=1e-10)
            assert result.peak_angle_deg[i, j] == np.argmax(depth) * 360.0 / NODES
            # worn volume Σ h_j A_j from the profile itself
            assert result.worn_volume_mm3[i, j] == pytest.approx(
                np.sum(depth) * 1e-6 * area * 1e9, rel=1e-10)
    assert result.valid.all()
    pts = result.points()
    assert pts["speed_rpm"].tolist() == [150.0] * 3 + [276.0] * 3
    assert pts["clearance_mm"].tolist() == CLEARANCES.tolist() * 2


def test_chunks_and_padding(result):
    """7 points in chunks of 6 (the second padded): the same numbers at the same points."""
    speeds = np.array([150.0, 180.0, 200.0, 220.0, 240.0, 260.0, 276.0])
    r = sweep(jw.preset("rig", K_d_per_Pa=2e-13), CFG,
              {"speed_rpm": speeds, "clearance_mm": [0.05]}, revolutions=REVS, M=M, chunk=6)
    assert r.shape == (7, 1)
    np.testing.assert_allclose(r.depth_um[[0, -1], 0], result.depth_um[:, 0], rtol=1e-12,
                               atol=1e-14)
    for i in (1, 5):  # points of the padded second chunk too
        p = jw.preset("rig", K_d_per_Pa=2e-13, speed_rpm=speeds[i], clearance_mm=0.05)
        depth = np.asarray(jw.simulate(p, CFG, revolutions=REVS, snapshots=SNAPS, M=M).depth)
        np.testing.assert_allclose(r.depth_um[i, 0], depth * 1e6, rtol=1e-10, atol=1e-12)


def test_parse_range():
    np.testing.assert_allclose(parse_range("--x", "100:300:21"), np.linspace(100, 300, 21))
    np.testing.assert_allclose(parse_range("--x", "0.05,0.1"), [0.05, 0.1])
    for bad in ("1:2", "1:2:0", "a:b:3", "1:2:2.5", "nan"):
        with pytest.raises(jw.InputError):
            parse_range("--x", bad)


def test_bad_grid_is_input_error():
    p = jw.preset("rig")
    with pytest.raises(jw.InputError, match="clearance_mm"):
        sweep(p, CFG, {"clearance_mm": [0.05, 8.0]}, revolutions=REVS)
    with pytest.raises(jw.InputError, match="unknown"):
        sweep(p, CFG, {"bogus_mm": [1.0]}, revolutions=REVS)


def test_cli_writes_csv_and_heatmaps(tmp_path, capsys, monkeypatch, result):
    monkeypatch.setenv("JAXWEAR_NO_CACHE", "1")
    study = tmp_path / "s.toml"
    study.write_text('[model]\npreset = "rig"\n[model.parameters]\nK_d_per_Pa = 2e-13\n'
                     f'[numerics]\nnodes = {NODES}\nsteps_per_rev = {STEPS}\n'
                     f'revolutions_per_update = {M}\n'
                     f'[[experiment]]\nname = "e"\nrevolutions = {REVS}\nspeed_rpm = 200\n')
    out = tmp_path / "out"
    assert main(["sweep", str(study), "--speed-rpm", "150:276:2", "--clearance-mm",
                 "0.05,0.08,0.12", "--out", str(out)]) == 0
    rows = np.genfromtxt(out / "sweep.csv", delimiter=",", names=True)
    assert rows.dtype.names[:4] == ("speed_rpm", "clearance_mm", "peak_depth_um",
                                    "worn_volume_mm3")
    assert len(rows) == 6
    np.testing.assert_allclose(rows["peak_depth_um"], result.peak_depth_um.ravel(), rtol=1e-8)
    np.testing.assert_allclose(rows["worn_volume_mm3"], result.worn_volume_mm3.ravel(),
                               rtol=1e-8)
    # eq 23 here: Euler's error estimate and the update count per point
    assert np.all(np.isfinite(rows["integration_error_um"]))
    assert np.all(rows["integration_steps"] == REVS / M)
    for name in ("sweep_peak_depth.png", "sweep_worn_volume.png"):
        assert (out / name).stat().st_size > 0
    assert main(["sweep", str(study), "--out", str(out)]) == 2
    assert "--speed-rpm" in capsys.readouterr().err


def test_adaptive_sweep_reruns_points_that_need_more_steps():
    """One static attempt count serves a whole adaptive sweep; a point far stiffer than the
    base (K_d x30 on the bimetal boom) needs more steps than it allows. It must be rerun,
    not returned as a truncated history: its depth equals `simulate` at that point and its
    error estimate is finite and within the tolerance."""
    from jaxwear._physics.config import boom_config
    from jaxwear._physics.wear import build_schedule

    cfg = boom_config(nodes=NODES, steps_per_rev=STEPS)
    p = jw.preset("boom", K_d_per_Pa=1e-13)
    kds = [1e-13, 3e-12]
    res = sweep(p, cfg, {"K_d_per_Pa": kds}, hours=3)
    base_attempts = build_schedule(p, cfg, hours=3).attempts
    assert res.steps[-1] > 2 * base_attempts  # more than the sweep's first try allowed
    assert res.valid.all() and np.all(res.error_estimate_um <= res.tolerance_um)
    for i, kd in enumerate(kds):
        one = jw.simulate(p.with_values({"K_d_per_Pa": kd}), cfg, hours=3)
        np.testing.assert_allclose(res.depth_um[i], np.asarray(one.depth) * 1e6, rtol=1e-9,
                                   atol=1e-9)
        assert res.steps[i] == int(one.steps)


def test_sweep_of_a_study_without_numerics_chooses_its_resolution(tmp_path):
    """A study that leaves nodes and steps open: the sweep picks the coarsest level whose
    peaks at the grid's corners agree with the next finer level's within 0.1 % of the largest
    (design.md §6)
    and says so; the claim is checked here against that finer level run independently."""
    from jaxwear._study.resolution import LEVELS, PEAK_RTOL

    (tmp_path / "s.toml").write_text(
        '[model]\npreset = "rig"\n\n[model.parameters]\nK_d_per_Pa = 2e-13\n\n'
        '[[experiment]]\nname = "a"\nrevolutions = 2000\nclearance_mm = 0.05\n')
    study = jw.load_study(tmp_path / "s.toml")
    assert study.auto_resolution
    grid = {"speed_rpm": [150.0, 276.0]}
    res = sweep(study, grid=grid)
    r = res.resolution
    assert r["auto"] and (r["nodes"], r["steps_per_rev"]) in LEVELS
    assert res.depth_um.shape[-1] == r["nodes"]
    finer = r["checked_against"]
    assert finer is not None and r["within_tolerance"]
    from jaxwear._study.resolution import at_level

    ref = sweep(at_level(study, (finer["nodes"], finer["steps_per_rev"])), grid=grid,
                choose_resolution=False)
    # the tolerance is of the largest peak (as for simulate's experiments)
    diff = np.max(np.abs(res.peak_depth_um - ref.peak_depth_um))
    assert 0 < diff <= PEAK_RTOL * np.max(ref.peak_depth_um)
    assert r["error_estimate_um"] == pytest.approx(
        np.max(np.abs(res.peak_depth_um - ref.peak_depth_um)), rel=1e-9)
