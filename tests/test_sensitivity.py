"""Normalised sensitivities by autodiff against central finite differences of `simulate`.

d ln y / d ln θ from `jax.jacfwd` through the whole wear loop must equal
(ln y(θ e^h) - ln y(θ e^-h)) / 2h of independent forward runs. With h = 1e-5 the truncation
error (~h² y''') and the round-off (~1e-12 relative contact tolerance / h) are both far below
the 1e-6 tolerance. Same small grid as tests/test_calibrate.py, so the single-run loop's
compilation is shared.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.sensitivity import relevant_keys, sensitivities
from jaxwear.cli import main

NODES, STEPS, M, REVS = 64, 72, 100, 3000
SNAPS = (1000.0, 2000.0, 3000.0)
CFG = jw.ModelConfig(nodes=NODES, steps_per_rev=STEPS)
P = jw.preset("rig", K_d_per_Pa=2e-13)


def ln_outputs(p):
    r = jw.simulate(p, CFG, revolutions=REVS, snapshots=SNAPS, M=M)
    return np.log([float(np.max(r.depth)), float(r.worn_volume)])


@pytest.fixture(scope="module")
def sens():
    return sensitivities(P, CFG, revolutions=REVS, M=M)


def test_relevant_parameters(sens):
    keys = set(sens.keys)
    # the rig's crank-slider and single layer: no oscillating-joint or backing parameters,
    # no crank mass (constant crank speed) and no pin elasticity (rigid pin)
    assert {"speed_rpm", "clearance_mm", "K_d_per_Pa", "crank_length_mm", "slider_mass_kg",
            "spring_N_per_m", "layer_E_GPa", "layer_thickness_mm", "width_mm",
            "bore_diameter_mm", "layer_poisson_ratio"} <= keys
    assert not keys & {"load_N", "swing_period_s", "backing_E_GPa", "crank_mass_kg",
                       "pin_E_GPa"}
    boom = relevant_keys(jw.preset("boom"), jw.ModelConfig(driver="oscillating",
                                                            double_layer=True))
    assert {"load_N", "swing_period_s", "backing_E_GPa"} <= set(boom)
    assert "speed_rpm" not in boom and "spring_N_per_m" not in boom


def test_against_central_differences(sens):
    base = ln_outputs(P)
    assert sens.peak_depth_um == pytest.approx(np.exp(base[0]) * 1e6, rel=1e-12)
    assert sens.worn_volume_mm3 == pytest.approx(np.exp(base[1]) * 1e9, rel=1e-12)
    h = 1e-5
    for k, a, b in zip(sens.keys, sens.peak, sens.volume):
        v = float(P.get(k))
        fd = (ln_outputs(P.with_values({k: v * np.exp(h)}))
              - ln_outputs(P.with_values({k: v * np.exp(-h)}))) / (2 * h)
        assert a == pytest.approx(fd[0], abs=1e-6), k
        assert b == pytest.approx(fd[1], abs=1e-6), k


def test_cli_table_and_chart(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("JAXWEAR_NO_CACHE", "1")
    study = tmp_path / "s.toml"
    study.write_text('[model]\npreset = "rig"\n[model.parameters]\nK_d_per_Pa = 2e-13\n'
                     f'[numerics]\nnodes = {NODES}\nsteps_per_rev = {STEPS}\n'
                     f'revolutions_per_update = {M}\n'
                     f'[[experiment]]\nname = "e"\nrevolutions = {REVS}\n')
    out = tmp_path / "out"
    assert main(["sensitivity", str(study), "--out", str(out)]) == 0
    rows = np.genfromtxt(out / "sensitivity.csv", delimiter=",", names=True, dtype=None,
                         encoding="utf-8")
    assert "K_d_per_Pa" in rows["parameter"].tolist()
    assert (out / "sensitivity.png").stat().st_size > 0
    assert "K_d_per_Pa" in capsys.readouterr().out
    doc = json.loads((out / "sensitivity.json").read_text())
    assert doc["e"]["integration"]["integrator"] == "paper"
    assert doc["e"]["integration"]["steps"] == REVS / M
    # the default (adaptive) integrator: its error estimate within the tolerance
    study.write_text("\n".join(ln for ln in study.read_text().splitlines()
                               if not ln.startswith("revolutions_per_update")))
    assert main(["sensitivity", str(study), "--out", str(tmp_path / "ad")]) == 0
    integ = json.loads((tmp_path / "ad" / "sensitivity.json").read_text())["e"]["integration"]
    assert integ["integrator"] == "adaptive" and integ["steps"] > 0
    assert 0 < integ["error_estimate_um"] <= integ["tolerance_um"]


def test_oscillating_joint_scaling_identities():
    """Exact scaling laws of the model, which autodiff must reproduce to round-off:
    - a run of fixed hours has hours·3600/T_s cycles and wear enters as K_d × cycles, so
      S(T_s) = -S(K_d);
    - contact and wear see the load only as W/B (A_j ∝ B), so S_peak(B) = -S_peak(W), and
      the volume Σ h_j A_j ∝ B h gives S_vol(B) = 1 - S_vol(W);
    - the backing enters only as L_st/E_st: S(L_st) = -S(E_st);
    - a load direction fixed in the ground frame only rotates the worn bore: S(θ_W0) = 0.
    """
    cfg = jw.ModelConfig(driver="oscillating", double_layer=True, nodes=NODES,
                         steps_per_rev=STEPS)
    s = sensitivities(jw.preset("boom"), cfg, hours=10, M=M)
    assert {"swing_period_s", "load_N", "backing_thickness_mm"} <= set(s.keys)
    S = {k: np.array([a, b]) for k, a, b in zip(s.keys, s.peak, s.volume)}
    np.testing.assert_allclose(S["swing_period_s"], -S["K_d_per_Pa"], atol=1e-10)
    np.testing.assert_allclose(S["width_mm"], [0, 1] - S["load_N"], atol=1e-10)
    np.testing.assert_allclose(S["backing_thickness_mm"], -S["backing_E_GPa"], atol=1e-10)
    np.testing.assert_allclose(S["load_angle_deg"], 0.0, atol=1e-10)
    assert S["K_d_per_Pa"][1] > 0.9  # and the derivatives are not trivially zero


def test_auto_mode_by_the_runs_length():
    """`mode="auto"` takes reverse mode from `REV_WORK` node-steps of cycle evaluations on
    (its first call is then faster: the module docstring's crossings), forward mode below."""
    from jaxwear._analyses.sensitivity import REV_WORK, auto_mode
    from jaxwear._physics.config import boom_config
    from jaxwear._physics.wear import build_schedule

    short = build_schedule(P, CFG, revolutions=REVS, M=M)  # 30 updates of 64 x 72
    assert auto_mode(short, CFG) == "fwd"
    assert short.updates * NODES * STEPS < REV_WORK
    boom, cfg = jw.preset("boom", K_d_per_Pa=3.8e-13), boom_config(nodes=180, steps_per_rev=144)
    long = build_schedule(boom, cfg, hours=25)  # adaptive: 3 cycles an attempt
    assert long.adaptive and 3 * long.attempts * 180 * 144 >= REV_WORK
    assert auto_mode(long, cfg) == "rev"
    # a traced attempt count (the fits' forward-mode path): reverse mode cannot run it
    assert auto_mode(long.with_dynamic_attempts(), cfg) == "fwd"


def test_reverse_mode_agrees_with_forward_mode(sens):
    rev = sensitivities(P, CFG, revolutions=REVS, M=M, mode="rev")
    assert sens.mode == "fwd" and rev.mode == "rev"
    scale = np.max(np.abs(sens.peak))
    np.testing.assert_allclose(rev.peak, sens.peak, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(rev.volume, sens.volume, rtol=0,
                               atol=1e-9 * np.max(np.abs(sens.volume)))
