"""Fits on data the fit did not make (no inverse crime).

- `synth`'s default data: whole-bore scans, zero-mean noise on every point, truth at 2x the
  study's nodes and steps and a tenth of its revolutions per update;
- a null study whose data come from `benchmarks/numpy_reference.py` (the independent
  plain-NumPy implementation) at finer numerics, plus noise on the whole scan.

Small grids (64 nodes, 72 steps) keep the cost down; the paper-matrix studies share the
compiled model with tests/test_diagnose.py and tests/test_synth.py.
"""

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from jaxwear._analyses.diagnose import diagnose
from jaxwear._analyses.synth import synthesize
from jaxwear._inference.calibrate import calibrate
from jaxwear._study.study import load_study

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import numpy_reference as ref  # noqa: E402
from helpers import paper_three  # noqa: E402

SMALL = dict(nodes=64, steps_per_rev=72, revolutions_per_update=500)
NOISE = 0.3


def _check_base_recovery(fit, truth, kd_rel):
    """K_d within `kd_rel` and every clearance within 3 standard errors plus 1.5 µm (the
    study's 64-node grid is 5.6° per node: its discretisation error, not the noise, bounds
    what a fit can recover)."""
    v = dict(zip(fit.names, fit.values))
    se = dict(zip(fit.names, fit.stderr))
    assert v["K_d_per_Pa"] / truth["K_d_per_Pa"] - 1 == pytest.approx(0, abs=kd_rel)
    for name, c in truth["clearance_mm"].items():
        err_um = abs(v[f"clearance_mm/{name}"] - c) * 1e3
        assert err_um < 3 * se[f"clearance_mm/{name}"] * 1e3 + 1.5, (name, err_um)


def test_registration_offset_is_fitted_and_recovered():
    """Scans registered 3° off, the study saying 0° with a 5° prior: every fitted
    `angle_offset_deg/EXP` comes back within 0.4° (a fourteenth of the node spacing), the
    misfit falls to the noise level, and without the fitted offset it does not."""
    res = synthesize([], paper_three(SMALL), noise_um=NOISE, seed=3, angle_offset_deg=3.0)
    assert res.study.angle_tolerance_deg == 0
    fixed = calibrate(res.study)
    assert not any(n.startswith("angle_offset_deg/") for n in fixed.names)
    f = calibrate(replace(res.study, angle_tolerance_deg=5.0))
    assert f.converged, f.message
    doc = f.to_json()
    offsets = {n: p for n, p in doc["parameters"].items() if n.startswith("angle_offset_deg/")}
    assert set(offsets) == {f"angle_offset_deg/{e.name}" for e in res.study.experiments}
    for name, p in offsets.items():
        assert abs(p["value"] - 3.0) < 0.4, (name, p)
        assert 0 < p["stderr"] < 0.5
    assert doc["units"][next(iter(offsets))] == "deg"
    assert f.rmse_um < 1.1 * NOISE < fixed.rmse_um
    _check_base_recovery(f, res.truth, kd_rel=0.02)


def test_diagnose_honours_the_registration():
    """Null data scanned 3° off: with the study's 5° registration prior, diagnose fits the
    offsets with the base model (calibrate's path) and finds nothing missing; told the
    registration is exact (tolerance 0), the same scans read as systematic misfit (so the
    first half can fail)."""
    from jaxwear._analyses.diagnose import diagnose

    res = synthesize([], paper_three(SMALL), noise_um=NOISE, seed=3, angle_offset_deg=3.0)
    held = diagnose(res.study, auto_shape=False)  # the verdict alone (not the shape)
    assert held.base_tests.systematic, held.summary
    d = diagnose(replace(res.study, angle_tolerance_deg=5.0))
    assert d.status == "adequate", d.summary
    for e in d.study.experiments:  # the diagnosed study holds the fitted registration
        assert abs(e.profile.angle_offset_deg - 3.0) < 0.4, e.profile.angle_offset_deg
    assert d.base.rmse < 1.1 * NOISE < held.base.rmse


def test_angle_offset_jacobian_matches_finite_differences():
    """d(residual)/d(offset) of the differentiable periodic interpolation, against a
    central difference of the residuals themselves."""
    from jaxwear._inference.calibrate import build_problem, parse_fit
    from jaxwear._inference.evaluation import evaluate

    res = synthesize([], "paper", noise_um=NOISE, seed=5, numerics=SMALL, angle_offset_deg=1.3)
    st = replace(res.study, angle_tolerance_deg=5.0)
    pb = build_problem(st, parse_fit(st, "K_d,clearance") + ["angle_offset_deg"])
    i = pb.names.index(f"angle_offset_deg/{st.experiments[0].name}")
    u = np.zeros(len(pb.names))
    u[i] = 0.37  # degrees; off the nodes, so the interpolation is locally linear
    ev = evaluate(pb, u)[0]
    h = 1e-4
    up, um = u.copy(), u.copy()
    up[i] += h
    um[i] -= h
    fd = np.concatenate([evaluate(pb, up)[0].r - evaluate(pb, um)[0].r,
                         evaluate(pb, up)[0].r_prior - evaluate(pb, um)[0].r_prior]) / (2 * h)
    J = np.vstack([ev.J, ev.J_prior])
    np.testing.assert_allclose(J[:, i], fd, rtol=1e-5, atol=1e-7)
    rows = np.asarray(pb.data.exp) == 0
    assert np.any(np.abs(fd[: pb.n_data][rows]) > 0.1)  # the scar's flanks move with it
    assert np.all(fd[: pb.n_data][~rows] == 0)  # other experiments do not


def test_calibration_on_synth_default_data():
    """Null data made at finer numerics: K_d within 2 %, clearances within 3 SE + 1.5 µm,
    misfit at the noise level (the residual discretisation error is small next to it)."""
    res = synthesize([], "paper", noise_um=NOISE, seed=17, numerics=SMALL)
    f = calibrate(res.study)
    assert f.converged, f.message
    _check_base_recovery(f, res.truth, kd_rel=0.02)
    assert f.rmse_um < 1.1 * NOISE


# -------------------------------------------- a null study from the NumPy reference

REF_EXPERIMENTS = (  # name, speed [r/min], nominal and true clearance [mm]
    ("n276", 276.0, 0.05, 0.0535),
    ("n148", 148.0, 0.05, 0.0470),
    ("n230-c10", 230.0, 0.10, 0.1040),
)
REF_SNAPSHOTS = (1000, 3000)
REF_KD = 1.15e-13  # the study starts from 1e-13


@pytest.fixture(scope="module")
def reference_study(tmp_path_factory):
    """Profiles from the plain-NumPy implementation at 128 nodes x 144 steps, M = 50 (the
    study states 64 x 72, M = 250), sampled every 3° over the whole bore with 0.3 µm of
    zero-mean noise on every point."""
    out = tmp_path_factory.mktemp("ref")
    rng = np.random.default_rng(2024)
    ang = np.arange(0.0, 360.0, 3.0)
    lines = ['[model]', 'preset = "rig"', '[model.parameters]', 'K_d_per_Pa = 1e-13',
             'spring_N_per_m = 1009.4', '[numerics]', 'nodes = 64', 'steps_per_rev = 72',
             'revolutions_per_update = 250', '[fit]', 'clearance_tolerance_um = 5']
    for name, speed, nominal, true in REF_EXPERIMENTS:
        rows = []
        for revs in REF_SNAPSHOTS:
            h = ref.simulate_rig(speed, revs, M=50, nodes=128, steps=144,
                                 clearance_m=true * 1e-3, K_d=REF_KD)["h"] * 1e6
            d = np.interp(ang, np.arange(129) * 360.0 / 128, np.r_[h, h[0]])
            d = d + NOISE * rng.standard_normal(len(ang))
            rows += [f"{a:g},{y:.4f},{revs}" for a, y in zip(ang, d)]
        (out / f"{name}.csv").write_text("angle_deg,depth_um,revolutions\n"
                                         + "\n".join(rows) + "\n")
        lines += ["", "[[experiment]]", f'name = "{name}"', f"speed_rpm = {speed}",
                  f"clearance_mm = {nominal}", f"revolutions = {max(REF_SNAPSHOTS)}",
                  f'profile = "{name}.csv"']
    (out / "study.toml").write_text("\n".join(lines) + "\n")
    return load_study(out / "study.toml")


def test_null_study_from_the_numpy_reference(reference_study):
    """The base model fits independent data at the noise level, recovers K_d and the
    clearances, and diagnose says `adequate` (nothing is missing)."""
    st = reference_study
    assert sum(np.sum(e.profile.depth < 0) for e in st.experiments) > 50
    f = calibrate(st)
    assert f.converged, f.message
    truth = {"K_d_per_Pa": REF_KD,
             "clearance_mm": {n: true for n, _, _, true in REF_EXPERIMENTS}}
    _check_base_recovery(f, truth, kd_rel=0.03)
    assert f.rmse_um < 1.1 * NOISE
    d = diagnose(st)
    assert d.status == "adequate", d.summary
    assert d.noise_um == pytest.approx(NOISE, rel=4 / math.sqrt(d.model.n))


def test_cli_synth_offset_then_calibrate_fits_it(tmp_path):
    """The CLI round trip: `synth --angle-offset-deg`, the user states a registration prior,
    `calibrate` writes `angle_offset_deg/<experiment>` into calibration.json."""
    import json

    from jaxwear.cli import main

    cond = tmp_path / "cond.toml"
    cond.write_text('[model]\npreset = "rig"\n[model.parameters]\nK_d_per_Pa = 1e-13\n'
                    'spring_N_per_m = 1009.4\n[numerics]\nnodes = 64\nsteps_per_rev = 72\n'
                    'revolutions_per_update = 500\n[fit]\nangle_tolerance_deg = 4\n'
                    '[[experiment]]\nname = "a"\nspeed_rpm = 276\nrevolutions = 5000\n'
                    'clearance_mm = 0.05\n')
    out = tmp_path / "s"
    assert main(["synth", "--conditions", str(cond), "--angle-offset-deg", "-2.5", "--seed",
                 "9", "--out", str(out)]) == 0
    assert json.loads((out / "truth.json").read_text())["angle_offset_deg"] == {"a": -2.5}
    assert "angle_tolerance_deg = 4" in (out / "study.toml").read_text()
    assert main(["calibrate", str(out / "study.toml"), "--out", str(tmp_path / "c")]) == 0
    doc = json.loads((tmp_path / "c" / "calibration.json").read_text())
    p = doc["parameters"]["angle_offset_deg/a"]
    assert abs(p["value"] + 2.5) < 0.5 and p["stderr"] > 0
