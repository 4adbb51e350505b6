"""jaxwear against the plain-NumPy reference `benchmarks/numpy_reference.py`.

The reference is an independent implementation of design.md §1, §3 and §4 (Python loops over
updates and steps, its own kinematics, force balance and contact Newton; no JAX, no shared
code). Both solve the same discrete equations to a force residual far below 1e-9, so on the
same grid and the same M the wear profiles must agree to round-off of the contact solves,
well within 1e-6 relative, for both contact models.
"""

import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import jaxwear as jw

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import numpy_reference as ref  # noqa: E402

NODES, STEPS, REVS, M = 72, 72, 2000, 100
SPEED, CLEARANCE_MM, K_D, SPRING = 276.0, 0.05, 1e-13, 1009.4


@pytest.fixture(scope="module")
def params():
    return jw.preset("rig", speed_rpm=SPEED, clearance_mm=CLEARANCE_MM, K_d_per_Pa=K_D,
                     spring_N_per_m=SPRING)


def test_load_history_matches(params):
    """Forces, bushing-frame load angle and sliding per step (design.md §1)."""
    cfg = jw.ModelConfig(nodes=NODES, steps_per_rev=STEPS)
    hist = jax.jit(jw.load_history, static_argnums=1)(params, cfg)
    force, theta_w, phi2_d, period = ref.load_history(SPEED, STEPS, CLEARANCE_MM * 1e-3, SPRING,
                                                      cfg.scla_passes, cfg.gamma0_rad)
    scale = np.max(np.hypot(force[:, 0], force[:, 1]))
    np.testing.assert_allclose(np.asarray(hist.fx[0]), force[:, 0], rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(np.asarray(hist.fy[0]), force[:, 1], rtol=0, atol=1e-9 * scale)
    dtheta = np.angle(np.exp(1j * (np.asarray(hist.angle[0]) - theta_w)))
    assert np.max(np.abs(dtheta)) < 1e-9
    ds = (ref.R_B - CLEARANCE_MM * 1e-3) * np.abs(phi2_d) * period / STEPS
    np.testing.assert_allclose(np.asarray(hist.slide[0]), ds, rtol=1e-10)


@pytest.mark.parametrize("contact", ["unsymmetric", "symmetric"])
def test_wear_profile_matches(params, contact):
    """Final profile, worn volume and the Archard volume identity, same grid and M."""
    cfg = jw.ModelConfig(nodes=NODES, steps_per_rev=STEPS, contact=contact)
    res = jw.simulate(params, cfg, revolutions=REVS, M=M)
    out = ref.simulate_rig(speed_rpm=SPEED, revolutions=REVS, M=M, nodes=NODES, steps=STEPS,
                           clearance_m=CLEARANCE_MM * 1e-3, K_d=K_D, spring=SPRING,
                           contact=contact)
    h_jax, h_np = np.asarray(res.depth), out["h"]
    peak = np.max(h_np)
    assert peak > 1e-7  # a real wear scar (µm), not a trivially equal pair of zeros
    assert np.max(np.abs(h_jax - h_np)) <= 1e-6 * peak
    np.testing.assert_allclose(float(res.worn_volume), out["volume_m3"], rtol=1e-6)
    np.testing.assert_allclose(float(res.archard_volume), out["archard_volume_m3"], rtol=1e-6)
