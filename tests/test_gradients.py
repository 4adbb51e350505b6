"""Derivatives of the wear prediction (the loop is differentiable end to end).

Reference: central finite differences (helpers.central_fd, step sqrt(machine eps)·|x|) of
the same float64 function; forward mode against reverse mode. The objective is a smooth
peak-weighted depth Σh³/Σh² [µm] of the final profile (it tends to the peak depth).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_fd

import jaxwear as jw
from jaxwear._physics.wear import build_schedule, wear_loop

KEYS = ("K_d_per_Pa", "clearance_mm", "speed_rpm", "spring_N_per_m", "layer_E_GPa")
# SI values of the rig preset: K_d [1/Pa], c [m], ω [rad/s], k [N/m], E [Pa]
X0 = np.array([1e-13, 0.05e-3, 276 * 2 * np.pi / 60, 1009.4, 0.5e9])
CFG_U = jw.ModelConfig(nodes=64, steps_per_rev=72)
CFG_S = jw.ModelConfig(nodes=64, steps_per_rev=72, contact="symmetric")
CFG_BOOM = jw.ModelConfig(driver="oscillating", double_layer=True, nodes=64, steps_per_rev=72)
REL = 1e-5


def peak_weighted_depth(h):
    h = h * 1e6
    return jnp.sum(h**3) / jnp.sum(h**2)


def make_objective(p0, cfg, schedule, keys):
    def f(x):
        p = p0.with_values(dict(zip(keys, x)))
        return peak_weighted_depth(wear_loop(p, cfg, schedule).depth)

    return f


class Problem:
    """value_and_grad compiled once; finite differences reuse it (one compiled shape)."""

    def __init__(self, f):
        self.vg = jax.jit(jax.value_and_grad(f))
        self.f = f

    def value(self, x):
        return float(self.vg(jnp.asarray(x, jnp.float64))[0])

    def grad(self, x):
        return np.asarray(self.vg(jnp.asarray(x, jnp.float64))[1])


@pytest.fixture(scope="module")
def rig_problem():
    p0 = jw.preset("rig")
    sched = build_schedule(p0, CFG_U, revolutions=2000, M=100)
    return Problem(make_objective(p0, CFG_U, sched, KEYS))


@pytest.fixture(scope="module")
def rig_grad(rig_problem):
    return rig_problem.grad(X0)


def test_objective_matches_simulate(rig_problem):
    """The differentiated function is the model: same value as `simulate`."""
    res = jw.simulate(jw.preset("rig"), CFG_U, revolutions=2000, M=100)
    assert rig_problem.value(X0) == pytest.approx(float(peak_weighted_depth(res.depth)),
                                                  rel=1e-12)


@pytest.mark.parametrize("i", range(len(KEYS)), ids=KEYS)
def test_reverse_mode_matches_finite_differences(rig_problem, rig_grad, i):
    fd = central_fd(rig_problem.value, X0, i)
    assert rig_grad[i] != 0.0
    assert rig_grad[i] == pytest.approx(fd, rel=REL)


def test_signs_are_physical(rig_grad):
    """More wear with a larger K_d (∝ K_d at first order: d ln h/d ln K_d ≈ 1) and with a
    stiffer layer (narrower contact, higher peak pressure)."""
    g = dict(zip(KEYS, rig_grad * X0))  # d f / d ln x
    assert g["K_d_per_Pa"] > 0
    assert g["layer_E_GPa"] > 0


def test_forward_mode_equals_reverse_mode(rig_problem, rig_grad):
    fwd = np.asarray(jax.jit(jax.jacfwd(rig_problem.f))(jnp.asarray(X0)))
    assert fwd == pytest.approx(rig_grad, rel=1e-10)


def test_symmetric_contact_gradient():
    p0 = jw.preset("rig")
    sched = build_schedule(p0, CFG_S, revolutions=2000, M=100)
    prob = Problem(make_objective(p0, CFG_S, sched, KEYS))
    g = prob.grad(X0)
    for i in (0, 1, 4):  # K_d, clearance, layer modulus
        assert g[i] == pytest.approx(central_fd(prob.value, X0, i), rel=REL), KEYS[i]


def test_boom_gradient_wrt_kd():
    """Oscillating driver, double-layer bearing, duty cycle (1 h at 20°, 1 h at 1°)."""
    p0 = jw.preset("boom")
    sched = build_schedule(p0, CFG_BOOM, hours=2, M=100)
    x0 = np.array([float(p0.wear_coefficient)])
    prob = Problem(make_objective(p0, CFG_BOOM, sched, ("K_d_per_Pa",)))
    g = prob.grad(x0)
    assert g[0] > 0
    assert g[0] == pytest.approx(central_fd(prob.value, x0, 0), rel=REL)
