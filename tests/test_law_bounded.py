"""A law bounded where a prediction goes (issue 48: "refuse, or bound it, and say which"):
an exponential that would make the rate grow more than `EXP_GROWTH`-fold beyond the states
met is held flat beyond a cap (`law.search.bounded`). Its numpy and traced forms against
the formula by hand, the cap above every state met (the law unchanged there, through the
cycle's rates), and the cap said in the constants, the formula, the JSON and the
sentence."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.diagnose.law.search import (
    EXP_GROWTH,
    LawFit,
    LawResult,
    bounded,
    law_sentence,
    uncapped,
)
from jaxwear._physics.config import ModelConfig
from jaxwear._physics.cycle import cycle_rates, run_history
from jaxwear._physics.effects.law import (
    LAW_EFFECT,
    LAW_SEARCH,
    LawSpec,
    Term,
    constants,
    formula,
    law_phi,
    law_phi_numpy,
    searching,
)

# exp((h − 4 µm)/2 µm) (b = h_ref/h_e = 2) held flat beyond h_cap = 1.5 h_ref = 6 µm, times
# (p/1.5 MPa)^1.2 (a term without a cap)
CAPPED = LawSpec("factor", (Term("exp", "worn_depth_um", 4.0, b=2.0, cap=1.5),
                            Term("power", "pressure_MPa", 1.5, a=1.2)), 0.3)


def _by_hand(h, p):
    return np.exp((np.minimum(h, 6.0) - 4.0) / 2.0) * (p / 1.5) ** 1.2


def test_the_caps_numpy_and_traced_forms_agree_with_the_formula_by_hand():
    """Φ of the bounded product on depths both sides of the cap: numpy (`law_phi_numpy`)
    and the traced effect's (`law_phi` from the held parameters `LawSpec.values`) equal
    the formula by hand, exp((min(h, 6) − 4)/2) (p/1.5)^1.2; beyond the cap Φ is flat in
    h (its traced derivative 0 there, e^((h − 4)/2)/2 × the power below it)."""
    h = np.linspace(0.0, 12.0, 49)
    p = np.linspace(0.5, 3.0, 49)
    want = _by_hand(h, p)
    z = {"worn_depth_um": h, "pressure_MPa": p}
    np.testing.assert_allclose(law_phi_numpy(CAPPED, z), want, rtol=1e-13)
    e = {k: jnp.asarray(v) for k, v in CAPPED.values().items()}
    full = {"pressure_MPa": jnp.asarray(p), "sliding_speed_m_per_s": jnp.full(49, 0.05),
            "sliding_distance_m": jnp.zeros(49), "load_turn_rate_deg_per_s": jnp.zeros(49),
            "load_turn_deg_per_deg": jnp.zeros(49), "load_N": jnp.full(49, 100.0),
            "worn_depth_um": jnp.asarray(h)}
    np.testing.assert_allclose(np.asarray(law_phi(e, full, (49,))), want, rtol=1e-13)
    # flat beyond the cap, exponential below it: the derivative in h of the traced form

    def phi_at(hh, pp):
        one = {k: v[:1] for k, v in full.items()}
        one.update(worn_depth_um=jnp.atleast_1d(hh), pressure_MPa=jnp.atleast_1d(pp))
        return law_phi(e, one, (1,))[0]

    d = jax.grad(phi_at)
    assert float(d(8.0, 1.5)) == 0.0
    assert float(d(5.0, 1.5)) == pytest.approx(math.exp(0.5) / 2.0, rel=1e-12)
    # without the cap the same law is the plain exponential beyond 6 µm
    free = uncapped(CAPPED)
    np.testing.assert_allclose(law_phi_numpy(free, z), np.exp((h - 4.0) / 2.0)
                               * (p / 1.5) ** 1.2, rtol=1e-13)


def test_the_cap_is_a_held_parameter_that_round_trips():
    """`LawSpec.values` holds the cap as `law_cap_k` (x_c, units of the reference) and
    `with_values` reads it back; a law without one holds the effect's default, which
    reads back as none. 19 parameters: the two caps beside the 17 of before."""
    vals = CAPPED.values()
    assert vals["law_cap_1"] == 1.5
    assert vals["law_cap_2"] == LAW_SEARCH.parameters["law_cap_2"].default
    assert CAPPED.with_values(vals) == CAPPED
    free = uncapped(CAPPED)
    assert free.with_values(free.values()) == free and math.isinf(free.terms[0].cap)
    assert len(LAW_SEARCH.parameters) == 19


def test_an_exponential_within_the_limit_has_no_cap_and_one_beyond_it_is_said():
    """exp((h − h_s)/h_e), a deposit (its rate DΦ), states met up to 10 µm: Φ grows
    e^(10/h_e)-fold to 20 µm. h_e = 5 µm: e^2 = 7.4 (no cap, the law as it was); h_e =
    2 µm: e^5 = 148 (bounded where Φ has grown tenfold, 10 + 2 ln 10 = 14.61 µm). The cap
    is a fixed constant (stderr 0), the formula shows min(h, h_cap)."""
    ranges = {"worn_depth_um": (0.0, 10.0)}
    slow = LawSpec("deposit", (Term("exp", "worn_depth_um", 5.0, b=1.0),), 0.01)
    assert bounded(slow, ranges) == (slow, ())
    assert "h_cap" not in constants(slow) and "min(" not in formula(slow)
    fast = LawSpec("deposit", (Term("exp", "worn_depth_um", 5.0, b=2.5),), 0.01)
    law, said = bounded(fast, ranges, {"worn_depth_um": 10.3})
    assert law.terms[0].cap * 5.0 == pytest.approx(10.0 + 2.0 * math.log(EXP_GROWTH))
    c = constants(law, {"law_b_1": 0.1})
    assert c["h_cap"][0] == pytest.approx(14.605, abs=1e-3) and c["h_cap"][1] == 0.0
    assert c["h_e"][0] == pytest.approx(2.0)
    assert "exp((min(h, h_cap) − h_ref)/h_e)" in formula(law)
    assert said[0]["variable"] == "worn_depth_um" and said[0]["symbol"] == "h_cap"
    assert said[0]["growth"] == pytest.approx(math.exp(5.0))
    assert said[0]["growth_capped"] == pytest.approx(EXP_GROWTH)
    # bounding a bounded law gives it again (the cap is recomputed from an uncapped law)
    assert bounded(law, ranges, {"worn_depth_um": 10.3}) == (law, said)


def test_the_cap_never_falls_on_a_state_met():
    """The states met reach 16 µm beyond the range's upper end (10 µm, a quantile): where
    the tenfold point (14.61 µm) is below that, the cap is raised to the largest state met,
    so that the law is unchanged on every state it was fitted on; the reason says so."""
    ranges = {"worn_depth_um": (0.0, 10.0)}
    fast = LawSpec("deposit", (Term("exp", "worn_depth_um", 5.0, b=2.5),), 0.01)
    law, said = bounded(fast, ranges, {"worn_depth_um": 16.0})
    assert law.terms[0].cap * 5.0 == pytest.approx(16.0)
    assert "the states met end" in said[0]["reason"]
    h = np.linspace(0.0, 16.0, 65)
    np.testing.assert_array_equal(law_phi_numpy(law, {"worn_depth_um": h}),
                                  law_phi_numpy(fast, {"worn_depth_um": h}))


@eqx.filter_jit
def _rates(cfg, p, h):
    hist = run_history(p, cfg)
    return cycle_rates(p, cfg, hist, 0, h, jnp.asarray(40.0))[0]


def test_a_cap_above_the_states_met_leaves_the_wear_loops_rates_unchanged():
    """Through the cycle (the search's effect, its structure held data): nodes worn 0-4
    µm, the exponential exp((h − 2 µm)/1 µm); a cap at 5 µm (above every node) gives the
    rates of the uncapped law bit for bit, a cap at 3 µm (within them) lowers them on
    the nodes beyond 3 µm only (the check can fail)."""
    cfg = ModelConfig(nodes=24, steps_per_rev=36).replace(effects=(LAW_EFFECT,))
    h = jnp.linspace(0.0, 4e-6, 24)
    law = LawSpec("factor", (Term("exp", "worn_depth_um", 2.0, b=2.0),), 0.5)
    with searching():
        def run(lw):
            return np.asarray(_rates(cfg, jw.preset("rig", **lw.values()), h))

        free = run(law)
        above = run(_with_cap(law, 2.5))
        within = run(_with_cap(law, 1.5))
    np.testing.assert_array_equal(above, free)
    deep = np.asarray(h) * 1e6 > 3.0 + 1e-9
    np.testing.assert_array_equal(within[:, ~deep], free[:, ~deep])
    assert np.all(within[:, deep] <= free[:, deep]) and np.any(within[:, deep] < free[:, deep])


def _with_cap(law, cap):
    return dataclasses.replace(law, terms=(dataclasses.replace(law.terms[0], cap=cap),))


def test_the_json_and_the_sentence_say_which_term_is_bounded_and_where():
    """`shape.law.bounded` (added beside the contract's keys, which stay): the variable,
    the cap and the reason; the candidates' JSON carries it too; the sentence says the law
    is bounded and where; a law without a cap says nothing of it."""
    ranges = {"worn_depth_um": (0.0, 10.0)}
    fast = LawSpec("factor", (Term("exp", "worn_depth_um", 5.0, b=2.5),), 0.2)
    law, said = bounded(fast, ranges, {"worn_depth_um": 10.3})
    fit = LawFit(law, 0.31, 0.32, 50.0, "converged", 4,
                 constants(law, {"law_gain": 0.02, "law_b_1": 0.1}), 9.0, bounded=said)
    res = LawResult(fit, (fit,), 191, 0.30, 0.39, 0.40, 12.0)
    doc = res.to_json()
    assert {"formula", "file", "effect", "constants", "rmse_um", "loo_rmse_um"} <= set(doc)
    assert doc["bounded"][0]["variable"] == "worn_depth_um"
    assert doc["bounded"][0]["cap"] == pytest.approx(doc["constants"]["h_cap"]["value"])
    assert doc["constants"]["h_cap"]["stderr"] == 0.0
    assert "held flat beyond h_cap" in doc["bounded"][0]["reason"]
    assert doc["candidates"][0]["bounded"] == doc["bounded"]
    text = law_sentence(res)
    assert "It is bounded:" in text and "h_cap = " in text and "min(h, h_cap)" in text
    plain = LawFit(fast, 0.31, 0.32, 50.0, "converged", 4, constants(fast, {}), 9.0)
    res = LawResult(plain, (plain,), 191, 0.30, 0.39, 0.40, 12.0)
    assert res.to_json()["bounded"] == [] and "bounded" not in law_sentence(res)
