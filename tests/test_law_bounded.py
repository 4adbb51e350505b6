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


@pytest.fixture(scope="module")
def exp_fit(tmp_path_factory):
    """The independent generator's exponential of the worn depth (K_d (1 + 0.5 exp((h −
    5 µm)/6 µm))) at 72 x 108, M = 100, the paper's five experiments, 0.3 µm noise; the
    study at 36 x 54: its base fit, the states met, and the grammar's exponential of h
    fitted through the loop (3 evaluations: the check needs a law model at an answer,
    not a converged one)."""
    import sys
    from pathlib import Path

    from jaxwear._analyses.diagnose import Model, fit_masked
    from jaxwear._analyses.diagnose.law.search import fit_law, states_met

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import hidden_physics as hp

    gen = hp.generate(hp.Law("g_exp_h", 0.5), hp.PAPER, seed=3,
                      num=hp.Numerics(nodes=72, steps=108, M=100.0))
    path = hp.write(tmp_path_factory.mktemp("exp"), gen, hp.PAPER, study_numerics=(36, 54))
    model = Model(jw.load_study(path), candidates=[])
    base = fit_masked(model, model.base_mask, np.zeros(len(model.names)), noise_um=0.3)
    _, ranges, tops = states_met(model, base, ("factor",))
    start = LawSpec("factor", (Term("exp", "worn_depth_um", 3.0, b=0.5),), 0.4)
    with searching():
        found, f, lm = fit_law(model, base, start, 0.3, np.inf, max_evaluations=3)
    lf = LawFit(found, f.rmse, None, 0.0, f.status, f.evaluations,
                constants(found, dict(zip(lm.names, f.stderr))), math.nan, fit=f, model=lm)
    return model, base, lf, ranges, tops


def test_a_cap_at_the_top_of_the_states_met_leaves_the_fits_rows_unchanged(exp_fit):
    """Through the wear loop (`law.search.rebound`: the law model run with and without
    the cap at the fitted parameters): a cap that the states met reach changes the rows;
    the same cap raised to the deepest state the law's own fit wears (`own_tops`: deeper
    than the base fit's, the law adds wear) leaves every row as it was. The cap is put low
    on purpose: the law's e-fold h_e set to 1 µm (Φ's growth from 3 µm to 6 µm e^3 =
    20-fold, so its tenfold point 3 + ln 10 = 5.3 µm lies within the depths worn, up to
    ~20 µm); the rows are the fit's own (its fitted h_e): the cap is what differs."""
    from types import SimpleNamespace

    from jaxwear._analyses.diagnose.law.search import rebound

    model, base, lf, ranges, tops = exp_fit
    deepest = float(np.nanmax(np.asarray(lf.fit.ev.snaps)))
    assert deepest > tops["factor"]["worn_depth_um"] > 6.0  # the check can fail
    t = lf.law.terms[0]
    steep = dataclasses.replace(lf, law=dataclasses.replace(
        lf.law, terms=(dataclasses.replace(t, b=t.ref / 1.0),), strength=1e6))
    low = {"factor": {"worn_depth_um": (0.0, 3.0)}}
    # the fit with its snapshots hidden: no state of its own raises the cap
    blind = dataclasses.replace(steep, fit=SimpleNamespace(
        values=lf.fit.values, ev=SimpleNamespace(u=lf.fit.ev.u, snaps=None)))
    with searching():
        inside, k1 = rebound(model, base, blind, low, {"factor": {}})
        at_base_top, _ = rebound(model, base, blind, low, tops)
        at_top, k2 = rebound(model, base, steep, low, tops)
    cap_in = inside.bounded[0]["cap"]
    assert cap_in == pytest.approx(3.0 + math.log(EXP_GROWTH), rel=1e-6)
    assert k1 == k2 == 2
    assert inside.bounded[0]["in_sample_change_um"] > 1e-3
    # the base fit's deepest state is not the law's: a cap there still changes rows
    assert at_base_top.bounded[0]["cap"] == pytest.approx(tops["factor"]["worn_depth_um"])
    assert at_base_top.bounded[0]["in_sample_change_um"] > 1e-3
    assert at_top.bounded[0]["cap"] == pytest.approx(deepest)
    assert "the states met end" in at_top.bounded[0]["reason"]
    assert at_top.bounded[0]["in_sample_change_um"] == 0.0
    assert at_top.constants["h_cap"] == (pytest.approx(deepest), 0.0, "µm")
