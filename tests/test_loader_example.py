"""The worked example's multibody computation (calibration/examples/loader_arm/loader_arm.py)
against mechanics it does not use, and its files against the script.

Independent references: the power of the lift cylinders equals the rate of change of the
arm's kinetic plus potential energy (the pin does no work: it does not move), and the pin
load plus the cylinder force equal the rate of change of the arm's momentum plus its weight
(central differences of the masses' positions, not the script's accelerations).
Run time: ~2 s (numpy; the study is only read).
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import jaxwear as jw

HERE = Path(__file__).resolve().parents[1] / "calibration" / "examples" / "loader_arm"


@pytest.fixture(scope="module")
def arm():
    spec = importlib.util.spec_from_file_location("loader_arm", HERE / "loader_arm.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def positions(arm, th):
    """Centre of the boom and the tip (rows, 2) [m] at boom angles th."""
    e = np.stack([np.cos(th), np.sin(th)], 1)
    return 0.5 * arm.L * e, arm.L * e


def test_cylinder_power_is_the_energy_rate(arm):
    """During the lift (payload on, frame at rest): F_c û·v_D = d/dt (T + V), by central
    differences of the energy on a fine time grid."""
    h = 1e-4
    t = np.linspace(2.2, 6.8, 47)
    th, w, a, payload, fa = arm.work_cycle(t)
    _, f_cyl = arm.pin_load(th, w, a, payload, fa)
    e = np.stack([np.cos(th), np.sin(th)], 1)
    n = np.stack([-np.sin(th), np.cos(th)], 1)
    d = arm.D_ALONG * e - arm.D_BELOW * n
    u = (d - arm.C) / np.linalg.norm(d - arm.C, axis=1)[:, None]
    v_d = w[:, None] * np.stack([-d[:, 1], d[:, 0]], 1)
    power = f_cyl * np.sum(u * v_d, axis=1)

    def energy(tt):
        th_, w_, _, pay, _ = arm.work_cycle(tt)
        m_tip = arm.M_BUCKET + pay
        inertia = arm.M_BOOM * arm.L**2 / 3 + m_tip * arm.L**2
        height = (arm.M_BOOM * 0.5 * arm.L + m_tip * arm.L) * np.sin(th_)
        return 0.5 * inertia * w_**2 + arm.G * height

    rate = (energy(t + h) - energy(t - h)) / (2 * h)
    np.testing.assert_allclose(power, rate, rtol=1e-6, atol=1e-6 * np.abs(rate).max())


@pytest.mark.parametrize("cycle", ["work", "carry"])
def test_pin_load_is_the_momentum_balance(arm, cycle):
    """R + F_c û = d(Σ m v)/dt + Σ m g_eff ŷ, the momentum rate by central differences of
    the masses' positions; and the file holds R / 2 turned into the boom's frame."""
    h = 1e-4
    t = np.linspace(0.05, 0.75, 29) if cycle == "carry" else np.linspace(2.1, 11.9, 99)
    motion = arm.carry_cycle if cycle == "carry" else arm.work_cycle
    th, w, a, payload, fa = motion(t)
    reaction, f_cyl = arm.pin_load(th, w, a, payload, fa)
    e = np.stack([np.cos(th), np.sin(th)], 1)
    n = np.stack([-np.sin(th), np.cos(th)], 1)
    d = arm.D_ALONG * e - arm.D_BELOW * n
    u = (d - arm.C) / np.linalg.norm(d - arm.C, axis=1)[:, None]

    def momentum_pos(tt):  # Σ m r, whose second derivative is the momentum rate
        th_ = motion(tt)[0]
        g, p = positions(arm, th_)
        return arm.M_BOOM * g + (arm.M_BUCKET + payload)[:, None] * p

    acc = (momentum_pos(t + h) - 2 * momentum_pos(t) + momentum_pos(t - h)) / h**2
    weight = (arm.M_BOOM + arm.M_BUCKET + payload) * (arm.G + fa)
    lhs = reaction + f_cyl[:, None] * u
    rhs = acc + np.stack([np.zeros_like(t), weight], 1)
    np.testing.assert_allclose(lhs, rhs, atol=2e-4 * np.abs(rhs).max())
    rows = arm.load_file(t, th, reaction)
    back = np.stack([np.cos(th) * rows[:, 1] - np.sin(th) * rows[:, 2],
                     np.sin(th) * rows[:, 1] + np.cos(th) * rows[:, 2]], 1)
    np.testing.assert_allclose(back * arm.ARMS, reaction, rtol=1e-12, atol=1e-9)


def test_committed_files_are_the_scripts_and_the_studies_load(arm, tmp_path):
    arm.main(["--out", str(tmp_path), "--no-plot"])
    for name in ("work.csv", "carry.csv"):
        assert (tmp_path / name).read_text() == (HERE / name).read_text(), name
    for study in ("study.toml", "design.toml"):
        st = jw.load_study(HERE / study)
        assert st.config.driver == "load_history"
        assert [b.load.period for b in st.config.duty_cycle] == pytest.approx([12.0, 0.8])
        assert [b.duration_h for b in st.config.duty_cycle] == [6.0, 2.0]
