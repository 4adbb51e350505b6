"""Candidate effects: contracts, nesting, 'off' leaves the base model untouched, gradients.

The nesting and 'off' checks run one cycle of the wear loop (`cycle_increment`: contact,
local wear rate, the hooks) eagerly on a small grid, comparing arrays exactly: the loop
only accumulates these increments, so bitwise-equal increments give a bitwise-equal loop.
Gradients are checked on the compiled extended model that `diagnose` uses.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._physics.config import ModelConfig
from jaxwear._physics.contact import equivalent_modulus, stiffness_per_area
from jaxwear._physics.cycle import cycle_increment
from jaxwear._physics.effects import (
    STRUCTURAL,
    STRUCTURAL_CANDIDATES,
    Effect,
    EffectParameter,
    get_effect,
    register_effect,
    registered_effects,
    unregister_effect,
)

BUILTIN = ("running_in", "speed_dependence", "pressure_exponent", "friction", "creep")
SMALL = ModelConfig(nodes=48, steps_per_rev=36)


@pytest.fixture(scope="module")
def cycle_setup():
    p = jw.preset("rig", speed_rpm=230.0)
    hist = jw.load_history(p, SMALL)
    theta = jnp.arange(SMALL.nodes) * 360.0 / SMALL.nodes
    # a worn bore (3 µm scar at 180°) so that the contact is not the trivial fresh one
    h = 3e-6 * jnp.exp(-0.5 * ((theta - 180.0) / 20.0) ** 2)
    base = cycle_increment(p, SMALL, hist, 0, h, jnp.asarray(5.0))
    return p, hist, h, base


def test_builtin_registry_and_parameter_contracts():
    effects = registered_effects()
    for name in BUILTIN:
        assert name in effects
    assert set(STRUCTURAL) == {"unsymmetric", "double_layer"}
    for name, eff in list(effects.items()) + list(STRUCTURAL_CANDIDATES.items()):
        for key, spec in eff.parameters.items():
            assert spec.lower <= spec.off <= spec.upper, key
            assert spec.lower <= spec.default <= spec.upper, key
            assert spec.scale > 0 and spec.to_si > 0, key
            assert spec.doc, key
            if not spec.log:  # strengths: the realistic value synth hides is declared
                assert spec.realistic is not None and spec.realistic != spec.off, key
                assert spec.lower <= spec.realistic <= spec.upper, key
        assert eff.signature
    for name in BUILTIN:
        assert get_effect(name).strength_keys(), name
        assert get_effect(name).__doc__


@pytest.mark.parametrize("name", BUILTIN)
def test_nesting_strength_off_is_bitwise_base(cycle_setup, name):
    """Effect switched on with its strengths at `off`: the same increment, bit for bit."""
    p, hist, h, (dh0, work0, sol0) = cycle_setup
    eff = get_effect(name)
    p_off = p.with_values({k: s.off * s.to_si for k, s in eff.parameters.items()})
    dh1, work1, sol1 = cycle_increment(p_off, SMALL.replace(effects=(name,)), hist, 0, h,
                                       jnp.asarray(5.0))
    assert np.array_equal(np.asarray(dh1), np.asarray(dh0))
    assert np.array_equal(np.asarray(sol1.pressure), np.asarray(sol0.pressure))
    factor = eff.block_factor(p_off, jnp.asarray(3.0), jnp.asarray(0.01), jnp.asarray(100.0))
    assert float(factor) == 1.0


@pytest.mark.parametrize("name", BUILTIN)
def test_off_ignores_the_strength(cycle_setup, name):
    """Effect not switched on: its strength in the parameters has no influence at all."""
    p, hist, h, (dh0, _, _) = cycle_setup
    eff = get_effect(name)
    p_on = p.with_values({k: (s.realistic if s.realistic is not None else s.default) * s.to_si
                          for k, s in eff.parameters.items()})
    dh1, _, _ = cycle_increment(p_on, SMALL, hist, 0, h, jnp.asarray(5.0))
    assert np.array_equal(np.asarray(dh1), np.asarray(dh0))
    # ... and switched on at that strength it does change the wear (the test has teeth)
    if name == "running_in":
        f = eff.block_factor(p_on, jnp.asarray(0.0), jnp.asarray(0.01), jnp.asarray(100.0))
        assert float(f) > 1.5  # a = 1: about twice the wear at the start
    else:
        dh2, _, _ = cycle_increment(p_on, SMALL.replace(effects=(name,)), hist, 0, h,
                                    jnp.asarray(5.0))
        assert not np.allclose(np.asarray(dh2), np.asarray(dh0), rtol=1e-3, atol=0)


def test_running_in_block_average_is_exact():
    """The block factor is the exact mean of 1 + a e^(-S/S_r) over the block's sliding."""
    eff = get_effect("running_in")
    p = jw.preset("rig", running_in_amplitude=0.7, running_in_distance_m=5.0)
    s0, ds, n = 2.0, 0.0107, 400.0
    f = float(eff.block_factor(p, jnp.asarray(s0), jnp.asarray(ds), jnp.asarray(n)))
    s = s0 + ds * (np.arange(400000) + 0.5) / 1000.0  # midpoint rule, 1000 points per cycle
    assert f == pytest.approx(np.mean(1 + 0.7 * np.exp(-s / 5.0)), rel=1e-9)


@pytest.mark.parametrize("a", [0.0, 0.01, 1.0, 100.0, 1000.0])
def test_running_in_clock_inverts_the_block_factor(a):
    """`cycles_at` inverts the clock τ(n) = n · block_factor(S₀, s, n) (the adaptive loop's
    independent variable) to round-off, over blocks far shorter and far longer than the
    running-in distance, and its derivative in a is the implicit function's,
    dn/da = −(∂τ/∂a) / (∂τ/∂n), ∂τ/∂n the factor at the block's end."""
    import jax

    eff = get_effect("running_in")
    for sr in (1e-3, 0.05, 1.0, 1e5):
        p = jw.preset("boom", running_in_amplitude=a, running_in_distance_m=sr)
        for s0 in (0.0, 0.5, 10.0):
            for n in (1e-3, 0.3, 7.0, 1440.0):
                s0_, ds, n_ = jnp.asarray(s0), jnp.asarray(0.056), jnp.asarray(n)
                tau = n_ * eff.block_factor(p, s0_, ds, n_)
                assert float(eff.cycles_at(p, s0_, ds, tau)) == pytest.approx(n, rel=1e-12)
    p = jw.preset("boom", running_in_amplitude=a, running_in_distance_m=0.3)
    s0, ds, tau = jnp.asarray(0.1), jnp.asarray(0.056), jnp.asarray(20.0)

    def with_a(x):
        return p.with_values({"running_in_amplitude": x})

    n = eff.cycles_at(p, s0, ds, tau)
    dn = jax.grad(lambda x: eff.cycles_at(with_a(x), s0, ds, tau))(jnp.asarray(a))
    dtau_da = jax.grad(lambda x: n * eff.block_factor(with_a(x), s0, ds, n))(jnp.asarray(a))
    rate = eff.block_factor(p, s0 + ds * n, ds, jnp.asarray(0.0))
    assert float(dn) == pytest.approx(-float(dtau_da) / float(rate), rel=1e-9)


def test_double_layer_strength_is_a_series_compliance():
    """C_b maps to a backing thickness such that 1/k = (L - h)/E_w + C_b exactly."""
    cand = STRUCTURAL_CANDIDATES["double_layer"]
    p = jw.preset("rig")
    c_si = 0.8e-12  # 0.8 µm/MPa
    p2 = cand.set_strength(p, {"backing_compliance_um_per_MPa": jnp.asarray(c_si)})
    h = jnp.linspace(0.0, 5e-6, 7)
    k = stiffness_per_area(h, p2, True)
    ew = equivalent_modulus(p.layer_modulus, p.layer_poisson)
    np.testing.assert_allclose(np.asarray(1 / k), np.asarray((p.layer_thickness - h) / ew + c_si),
                               rtol=1e-12)
    # off: C_b = 0 gives the single layer exactly
    p0 = cand.set_strength(p, {"backing_compliance_um_per_MPa": jnp.asarray(0.0)})
    assert np.array_equal(np.asarray(stiffness_per_area(h, p0, True)),
                          np.asarray(stiffness_per_area(h, p, False)))
    assert cand.applies(ModelConfig()) and not cand.applies(ModelConfig(double_layer=True))
    uns = STRUCTURAL_CANDIDATES["unsymmetric"]
    assert uns.applies(ModelConfig(contact="symmetric")) and not uns.applies(ModelConfig())
    assert uns.configure(ModelConfig(contact="symmetric")).contact == "unsymmetric"


def test_strength_gradients_finite_at_off_and_match_finite_differences(small_model):
    """Every candidate's strength column of the extended model's Jacobian at the base
    model (all strengths off) is finite, non-zero, and agrees with central differences."""
    m, u0 = small_model
    ev = m.evaluate(u0)
    for i, c in enumerate(m.columns):
        if not c.strength:
            continue
        col = ev.J[:, i]
        assert np.all(np.isfinite(col)), c.group
        assert np.max(np.abs(col)) > 1e-3, c.group  # µm per typical strength
        h = 1e-3  # in units of the typical strength
        up, dn = u0.copy(), u0.copy()
        up[i] += h
        dn[i] -= h
        fd = (m.evaluate(up).pred - m.evaluate(dn).pred) / (2 * h)
        # the depth is piecewise smooth (contact arcs end at nodes): a few rows next to a
        # kink differ by O(h); the column as a whole must agree
        assert np.linalg.norm(col - fd) < 1e-2 * np.linalg.norm(col), c.group
        assert np.median(np.abs(col - fd)) < 1e-4 * np.max(np.abs(col)), c.group


@pytest.fixture(scope="module")
def small_model():
    """The extended model of a small synthetic rig study (shared compile with the
    diagnose tests), at the true parameters of null data."""
    from jaxwear._analyses.diagnose import Model
    from jaxwear._analyses.synth import synthesize

    res = synthesize([], "paper", noise_um=0.3, seed=3, numerics=dict(
        nodes=64, steps_per_rev=72, revolutions_per_update=500))
    m = Model(res.study)
    return m, np.zeros(len(m.names))


class _Humidity(Effect):
    name = "humidity_test"
    parameters = {"humidity_gain": EffectParameter(1.0, 0.0, 0.0, -0.5, 5.0, "g [-]",
                                                   scale=0.1, realistic=0.2)}
    signature = "uniform extra wear"

    def local_rate(self, p, rate, ctx):
        return rate * (1 + p.effect_params["humidity_gain"])


def test_register_custom_effect_and_contracts():
    from jaxwear._analyses.diagnose import candidate_names

    try:
        register_effect(_Humidity())
        assert "humidity_test" in candidate_names(ModelConfig())
        p = jw.preset("rig", humidity_gain=0.3)
        assert float(p.get("humidity_gain")) == pytest.approx(0.3)
    finally:
        unregister_effect("humidity_test")
    assert "humidity_test" not in registered_effects()

    class NoStrength(_Humidity):
        name = "bad_effect"
        parameters = {"x_m": EffectParameter(1.0, 1.0, 1.0, 0.1, 10.0, "x", log=True)}

    with pytest.raises(ValueError, match="strength"):
        register_effect(NoStrength())

    class OffOutside(_Humidity):
        name = "bad_effect"
        parameters = {"g2": EffectParameter(1.0, 0.5, -1.0, 0.0, 5.0, "g")}

    with pytest.raises(ValueError, match="off value"):
        register_effect(OffOutside())

    class Clash(_Humidity):
        name = "bad_effect"
        parameters = {"friction_coefficient": EffectParameter(1.0, 0.0, 0.0, 0.0, 1.0, "μ")}

    with pytest.raises(ValueError, match="already belongs"):
        register_effect(Clash())
    with pytest.raises(ValueError, match="structural"):
        class Taken(_Humidity):
            name = "double_layer"
        register_effect(Taken())
    assert "bad_effect" not in registered_effects()


def test_scoped_effects_hold_for_their_context_and_the_threads_it_starts():
    """`scoped_effects` (the law search's `searching`): registered for the block's context,
    the threads started through `_core.background` (and `in_context`) included, not for any
    other thread; checked as `register_effect` checks; a nested block's end leaves the
    outer's. Why: a process-wide registration gave models built in other threads the
    search's strengths by the threads' timing (another pytree, programs compiled again)."""
    import threading

    from jaxwear._core.background import Background, in_context
    from jaxwear._physics.effects._base import scoped_effects

    def seen():
        return ("humidity_test" in registered_effects(),
                "humidity_gain" in jw.preset("rig").effect_params)

    plain = {}

    def elsewhere():
        plain["seen"] = seen()

    eff = _Humidity()
    with scoped_effects(eff):
        assert seen() == (True, True)
        assert get_effect("humidity_test") is eff
        t = threading.Thread(target=elsewhere)
        t.start()
        t.join()
        assert plain["seen"] == (False, False)
        assert Background(seen).result() == (True, True)
        t = threading.Thread(target=in_context(elsewhere))
        t.start()
        t.join()
        assert plain["seen"] == (True, True)
        with scoped_effects(eff):  # nested: its end leaves the outer block's
            assert seen() == (True, True)
        assert seen() == (True, True)
    assert seen() == (False, False)

    class Clash(_Humidity):
        name = "bad_effect"
        parameters = {"friction_coefficient": EffectParameter(1.0, 0.0, 0.0, 0.0, 1.0, "μ")}

    with pytest.raises(ValueError, match="already belongs"), scoped_effects(Clash()):
        pass
    assert "bad_effect" not in registered_effects()
