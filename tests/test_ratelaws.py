"""Every built-in effect against its wear-rate law of design.md §5, computed by hand in numpy.

The library's parts that are not the effect (the load history, the contact solve) supply
their outputs: the pressure p_ij of one cycle on a frozen, worn profile, dS_i, Δt_i and the
sliding sense s_i. The expected wear is then written out from design.md §5 in numpy and
compared with what the wear loop's one-cycle increment (`cycle_increment`, the function the
loop accumulates) and the hooks return. Each effect is switched on at a strength well away
from `off`, so a wrong law (exponent, reference value, missing factor, sign) moves the
result by far more than the tolerances, which are round-off (1e-12 relative) except for the
contact equilibrium (the 1e-9 that design.md §3 requires of the solve).

Small grid (48 nodes, 36 steps per revolution): a few seconds, no wear loop compiled except
for running-in's block factor (one short `wear_loop`).
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._physics.config import ModelConfig
from jaxwear._physics.cycle import cycle_increment, node_area
from jaxwear._physics.effects import RateContext, get_effect, registered_effects
from jaxwear._physics.schedule import crank_segments, make_schedule
from jaxwear._physics.wear import wear_loop

SMALL = ModelConfig(nodes=48, steps_per_rev=36)
SPEED_RPM = 230.0
S_START = 5.0  # sliding distance at the start of the cycle [m]
# strengths well away from `off` (the realistic ones, or larger), in the keys' units
STRENGTH = {"speed_dependence": {"speed_exponent": 0.3},
            "pressure_exponent": {"pressure_exponent": 0.3},
            "creep": {"creep_m_per_Pa_s": 1e-15},
            "friction": {"friction_coefficient": 0.2},
            "running_in": {"running_in_amplitude": 0.7, "running_in_distance_m": 5.0}}
V_REF = 0.01  # m/s (design.md §5, speed_dependence)
P_REF = 1.0e6  # Pa (design.md §5, pressure_exponent)


def _np(x):
    return np.asarray(x, dtype=np.float64)


@pytest.fixture(scope="module")
def base():
    """The rig at 230 r/min, one cycle on a worn bore (3 µm scar at 180°, so the contact is
    not the trivial fresh one), base model: (params, history, profile, Δh, pressure)."""
    p = jw.preset("rig", speed_rpm=SPEED_RPM)
    hist = jw.load_history(p, SMALL)
    theta = np.arange(SMALL.nodes) * 360.0 / SMALL.nodes
    h = jnp.asarray(3e-6 * np.exp(-0.5 * ((theta - 180.0) / 20.0) ** 2))
    dh, _, sol = cycle_increment(p, SMALL, hist, 0, h, jnp.asarray(S_START))
    return p, hist, h, _np(dh), _np(sol.pressure)


def _with(p, name):
    return p.with_values({k: v * get_effect(name).parameters[k].to_si
                          for k, v in STRENGTH[name].items()})


def test_every_builtin_effect_has_a_hand_law_here():
    """A built-in effect added without a law test here fails this test."""
    assert set(registered_effects()) == set(STRENGTH)


def test_base_increment_is_archard(base):
    """Δh_j = Σ_i K_d p_ij dS_i (eq 21): the reference the effects modify."""
    p, hist, _, dh, pres = base
    want = float(p.wear_coefficient) * np.sum(pres * _np(hist.slide[0])[:, None], axis=0)
    np.testing.assert_allclose(dh, want, rtol=1e-12, atol=1e-12 * want.max())
    assert want.max() > 0


def _increment(p, name, h):
    dh, _, sol = cycle_increment(p, SMALL.replace(effects=(name,)), jw.load_history(p, SMALL),
                                 0, h, jnp.asarray(S_START))
    return _np(dh), _np(sol.pressure)


def test_speed_dependence_law(base):
    """K_d → K_d (v/v_ref)^q, v = dS_i/Δt_i, v_ref = 0.01 m/s: per step, the effect's rate
    over the base rate is (v_i/v_ref)^q; per cycle Δh_j = Σ_i K_d p_ij dS_i (v_i/v_ref)^q."""
    p0, hist, h, _, pres = base
    q = STRENGTH["speed_dependence"]["speed_exponent"]
    p = _with(p0, "speed_dependence")
    ds, dt = _np(hist.slide[0]), _np(hist.dt[0])
    v = ds / dt
    assert v.max() / V_REF > 5  # the law's reference speed matters here (0.01 vs ~0.07 m/s)
    # per step, through the hook
    rate0 = float(p.wear_coefficient) * pres * ds[:, None]
    ctx = RateContext(jnp.asarray(pres), jnp.asarray(ds), jnp.asarray(dt), jnp.asarray(S_START))
    rate = _np(get_effect("speed_dependence").local_rate(p, jnp.asarray(rate0), ctx))
    on = rate0 > 1e-6 * rate0.max()
    i = np.nonzero(on)[0]
    np.testing.assert_allclose(rate[on] / rate0[on], (v[i] / V_REF) ** q, rtol=1e-12)
    # per cycle, through the wear loop's increment (the pressure is the base model's)
    dh, pres1 = _increment(p, "speed_dependence", h)
    np.testing.assert_array_equal(pres1, pres)
    want = np.sum(float(p.wear_coefficient) * pres * (ds * (v / V_REF) ** q)[:, None], axis=0)
    np.testing.assert_allclose(dh, want, rtol=1e-12, atol=1e-12 * want.max())


def test_pressure_exponent_law(base):
    """dh = K_d p_ref (p/p_ref)^(1+b) dS, p_ref = 1 MPa, node by node from the solved
    pressure."""
    p0, hist, h, dh0, pres = base
    b = STRENGTH["pressure_exponent"]["pressure_exponent"]
    p = _with(p0, "pressure_exponent")
    assert pres.max() > 2 * P_REF  # pressures of several MPa: p_ref and b both matter
    dh, pres1 = _increment(p, "pressure_exponent", h)
    np.testing.assert_array_equal(pres1, pres)
    ds = _np(hist.slide[0])
    want = np.sum(float(p.wear_coefficient) * P_REF * (pres / P_REF) ** (1 + b) * ds[:, None],
                  axis=0)
    np.testing.assert_allclose(dh, want, rtol=1e-12, atol=1e-12 * want.max())
    assert np.max(np.abs(dh - dh0)) > 0.1 * dh0.max()  # far from the base model


def test_creep_law(base):
    """dh_j += C p_j Δt_i per step, independent of sliding: the extra wear over the base
    model is Σ_i C p_ij Δt_i, also on steps where nothing slides."""
    p0, hist, h, dh0, pres = base
    c = STRENGTH["creep"]["creep_m_per_Pa_s"]
    p = _with(p0, "creep")
    dh, pres1 = _increment(p, "creep", h)
    np.testing.assert_array_equal(pres1, pres)
    dt = _np(hist.dt[0])
    extra = np.sum(c * pres * dt[:, None], axis=0)
    assert extra.max() > 0.05 * dh0.max()  # a visible fraction of the wear
    np.testing.assert_allclose(dh - dh0, extra, rtol=1e-9, atol=1e-12 * dh.max())
    np.testing.assert_allclose(dh, dh0 + extra, rtol=1e-12, atol=1e-12 * dh.max())
    # the hook on a step without sliding: creep only
    ds = _np(hist.slide[0])
    ctx = RateContext(jnp.asarray(pres), jnp.zeros_like(jnp.asarray(ds)), jnp.asarray(dt),
                      jnp.asarray(S_START))
    rate = _np(get_effect("creep").local_rate(p, jnp.zeros_like(jnp.asarray(pres)), ctx))
    np.testing.assert_allclose(rate, c * pres * dt[:, None], rtol=1e-12, atol=0)


def test_friction_contact_equilibrium_and_sense(base):
    """Σ_j A_j p_j (n_j + μ s t_j) = W for every step to 1e-9 relative (design.md §3, §5),
    t_j = (-sin θ_j, cos θ_j), s = sign(Φ̇2) = sign(cos Φ1) for the crank-slider (the
    stationary clearance link: Φ̇2 = L1 ω cos Φ1 / (L2 cos Φ2)); the wear stays Archard on
    that pressure. The frictionless equation misses by about μ: the check has teeth."""
    p0, hist, h, _, pres0 = base
    mu = STRENGTH["friction"]["friction_coefficient"]
    p = _with(p0, "friction")
    n, steps = SMALL.nodes, SMALL.steps_per_rev
    phi1 = 2 * np.pi * np.arange(steps) / steps
    sense = _np(hist.sense[0])
    moving = np.abs(np.cos(phi1)) > 1e-9  # Φ̇2 = 0 exactly at the quarter turns
    np.testing.assert_array_equal(sense[moving], np.sign(np.cos(phi1[moving])))
    assert set(sense[moving]) == {-1.0, 1.0}  # both senses occur
    dh, pres = _increment(p, "friction", h)
    th = 2 * np.pi * np.arange(n) / n
    A = float(node_area(p, n))
    load, ang = _np(hist.load[0]), _np(hist.angle[0])
    W = load[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    nrm = np.stack([np.cos(th), np.sin(th)], axis=1)
    tan = np.stack([-np.sin(th), np.cos(th)], axis=1)
    F = A * (pres @ nrm + mu * sense[:, None] * (pres @ tan))
    rel = np.linalg.norm(F - W, axis=1) / load
    assert rel.max() < 1e-9, rel.max()
    frictionless = np.linalg.norm(A * (pres @ nrm) - W, axis=1) / load
    assert np.median(frictionless) > 0.5 * mu
    ds = _np(hist.slide[0])
    want = float(p.wear_coefficient) * np.sum(pres * ds[:, None], axis=0)
    np.testing.assert_allclose(dh, want, rtol=1e-12, atol=1e-12 * want.max())
    assert np.max(np.abs(pres - pres0)) > 0.05 * pres0.max()  # friction moved the pressure


def _mean_factor(a, sr, s0, ds, m):
    """Closed-form mean of 1 + a e^(-S/S_r) over S in [s0, s0 + m ds]:
    1 + a e^(-s0/S_r) S_r (1 - e^(-m ds/S_r)) / (m ds)."""
    x = m * ds / sr
    return 1 + a * np.exp(-s0 / sr) * (-np.expm1(-x)) / x


@pytest.mark.parametrize("s0,m", [(0.0, 100.0), (2.0, 400.0), (30.0, 1000.0), (0.0, 1.0)])
def test_running_in_block_factor_is_the_closed_form_mean(s0, m):
    """K_d → K_d (1 + a e^(-S/S_r)) averaged over a block of m cycles of ds each: against
    the closed form (1e-12), and at m = 0 (the adaptive loop's instantaneous factor) the
    factor itself."""
    a, sr = STRENGTH["running_in"]["running_in_amplitude"], 5.0
    p = jw.preset("rig", running_in_amplitude=a, running_in_distance_m=sr)
    eff, ds = get_effect("running_in"), 0.0107
    f = float(eff.block_factor(p, jnp.asarray(s0), jnp.asarray(ds), jnp.asarray(m)))
    assert f == pytest.approx(_mean_factor(a, sr, s0, ds, m), rel=1e-12)
    f0 = float(eff.block_factor(p, jnp.asarray(s0), jnp.asarray(ds), jnp.asarray(0.0)))
    assert f0 == pytest.approx(1 + a * np.exp(-s0 / sr), rel=1e-14)


def test_running_in_in_the_wear_loop(base):
    """Two eq-23 updates of M cycles each from the worn profile: the first adds
    M · mean factor(0, M) · Δh(h0), with the closed-form mean; and the second starts at
    S = M · S_cycle (the sliding carried along)."""
    p0, hist, h, _, _ = base
    a = STRENGTH["running_in"]["running_in_amplitude"]
    sr = STRENGTH["running_in"]["running_in_distance_m"]
    p = _with(p0, "running_in")
    cfg = SMALL.replace(effects=("running_in",))
    M = 200.0
    sched = make_schedule(crank_segments(2 * M), [M, 2 * M], M)
    res = wear_loop(p, cfg, sched, h)
    s_cyc = float(np.sum(_np(hist.slide[0])))
    dh1, _, _ = cycle_increment(p0, SMALL, hist, 0, h, jnp.asarray(0.0))  # base Δh on h0
    h1 = _np(h) + M * _mean_factor(a, sr, 0.0, s_cyc, M) * _np(dh1)
    np.testing.assert_allclose(_np(res.snapshots[0]), h1, rtol=1e-12, atol=1e-12 * h1.max())
    dh2, _, _ = cycle_increment(p0, SMALL, hist, 0, jnp.asarray(h1), jnp.asarray(M * s_cyc))
    h2 = h1 + M * _mean_factor(a, sr, M * s_cyc, s_cyc, M) * _np(dh2)
    # the second update's contact starts warm from the first: equal to the solve's tolerance
    np.testing.assert_allclose(_np(res.depth), h2, rtol=1e-8, atol=1e-9 * h2.max())
    assert float(res.sliding_distance) == pytest.approx(2 * M * s_cyc, rel=1e-12)
    # the factor is far from 1 here: a law without it would miss by much more
    assert _mean_factor(a, sr, 0.0, s_cyc, M) > 1.3
