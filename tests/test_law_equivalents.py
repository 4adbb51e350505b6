"""Laws the data do not tell apart (issue 48, recovery): the equivalents of the answer, where
their rates part, the peer fitted after a law at the noise, and their JSON and sentence.
Pure functions on fitted-law stand-ins (no model run)."""

import dataclasses
import math

import numpy as np
import pytest

from jaxwear._analyses.diagnose.law.equivalent import equivalents, loo_band, separation
from jaxwear._analyses.diagnose.law.search import (
    LawFit,
    LawResult,
    law_sentence,
    peer_pick,
    rank,
    undetermined,
)
from jaxwear._physics.effects.law import LawSpec, Term, constants

POWER_H = LawSpec("factor", (Term("power", "worn_depth_um", 2.0, a=1.9),), 0.19)
EXP_H = LawSpec("factor", (Term("exp", "worn_depth_um", 2.0, b=0.5),), 0.3)
HINGE_H = LawSpec("factor", (Term("hinge", "worn_depth_um", 2.0, x0=0.5, a=2.0),), 0.4)
POWER_P = LawSpec("factor", (Term("power", "pressure_MPa", 1.5, a=2.0),), 1.0)
POWER_V = LawSpec("factor", (Term("power", "sliding_speed_m_per_s", 0.05, a=5.0),), 0.4)
SE2 = {"law_gain": 0.02, "law_a_1": 0.1, "law_b_1": 0.05}
SE3 = {"law_gain": 0.02, "law_a_1": 0.1, "law_x0_1": 0.05}
# five experiments' left-out errors [µm]: the mean of their squares has a standard error
# of 0.00453 µm² (sd 0.01013 / √5), i.e. 0.0071 µm on the RMSE 0.3195 (÷ 2 RMSE)
PER = {"a": 0.30, "b": 0.34, "c": 0.31, "d": 0.33, "e": 0.32}


def _fit(law, loo, se, per=None, at_noise=False, rmse=0.314, ev=10.0):
    return LawFit(law, rmse, loo, ev, "converged", 5, constants(law, se), 1.0,
                  at_noise=at_noise, undetermined=undetermined(law, se),
                  loo_per_experiment=per or {})


def test_the_one_standard_error_band_from_the_experiments_spread():
    f = _fit(POWER_H, 0.3195, SE2, PER)
    m = np.square(list(PER.values()))
    want = np.std(m, ddof=1) / math.sqrt(5) / (2 * 0.3195)
    assert abs(loo_band(f) - want) < 1e-12 and 0.0070 < want < 0.0072
    # no spread known: the least band, 1 % of the left-out RMSE
    assert abs(loo_band(_fit(POWER_H, 0.3, SE2)) - 0.003) < 1e-12


def test_equivalents_are_other_structures_within_one_standard_error_of_the_answer():
    power = _fit(POWER_H, 0.3195, SE2, PER, ev=12.0)
    exp = _fit(EXP_H, 0.3250, SE2, PER)  # +0.0055, within the 0.0071 band
    hinge = _fit(HINGE_H, 0.3400, SE3, PER)  # +0.02: beyond it
    again = _fit(dataclasses.replace(POWER_H, strength=0.2), 0.3200, SE2, PER)  # same structure
    ranked = rank([hinge, exp, again, power])
    assert ranked[0] is power  # the simplest within one SE; ties of complexity by evidence
    eq = equivalents(ranked)
    assert [f.law.label for f in eq] == [EXP_H.label]
    # the answer times a term it does not need (nested): the same law, not an equivalent;
    # the answer nested in a product it ties with: neither
    prod = LawSpec("factor", POWER_H.terms + (Term("exp", "load_turn_rate_deg_per_s", 36.0,
                                                    b=-0.002),), 0.19)
    nested = _fit(prod, 0.3196, {**SE2, "law_b_2": 0.003}, PER)
    assert [f.law.label for f in equivalents([power, nested, exp])] == [EXP_H.label]
    assert equivalents([nested, power]) == []
    # a sharper answer: the exponential now 0.0055 above a band of 1 % (0.0032): none
    sharp = [dataclasses.replace(f, loo_per_experiment={}) for f in ranked]
    assert equivalents(sharp) == []


def _samples(h):
    return {"factor": {"worn_depth_um": h, "pressure_MPa": np.full_like(h, 1.5),
                       "sliding_speed_m_per_s": np.full_like(h, 0.05)}}


def test_where_two_laws_part_by_hand():
    """Rates 1 (A = 0) and 1 + h/2 µm (A = 1, a power of exponent 1 at h_ref = 2 µm) over
    h met uniformly on 1-3 µm: normalised to their means there (1 and 2), the second over
    the first is (1 + h/2)/2: 0.75 at h = 1 and 1.25 at h = 3 within the range met (the
    larger |log|: 0.75); over the range extended twofold (0.5-6 µm), 2.0 at h = 6 µm
    (|log 2| > |log 0.625| at 0.5)."""
    flat = _fit(LawSpec("factor", (Term("power", "worn_depth_um", 2.0, a=1.0),), 0.0), 0.32,
                SE2)
    line = _fit(LawSpec("factor", (Term("power", "worn_depth_um", 2.0, a=1.0),), 1.0), 0.32,
                SE2)
    h = np.linspace(1.0, 3.0, 2001)
    sep = separation(flat, line, _samples(h), {"factor": {"worn_depth_um": (1.0, 3.0)}},
                     "study.toml")
    assert sep["variable"] == "worn_depth_um" and sep["beyond_range"]
    assert abs(sep["at"] - 6.0) < 1e-9 and abs(sep["ratio"] - 2.0) < 1e-9
    assert abs(sep["ratio_in_range"] - 0.75) < 1e-9
    assert sep["command"] is None  # one variable: the shape cannot separate it from itself


def test_laws_of_distinct_shape_variables_name_the_design_that_separates_them():
    p, v = _fit(POWER_P, 0.32, SE2), _fit(POWER_V, 0.32, SE2)
    rng = np.random.default_rng(0)
    Z = {"factor": {"pressure_MPa": rng.uniform(0.5, 3.0, 500),
                    "sliding_speed_m_per_s": rng.uniform(0.01, 0.1, 500),
                    "worn_depth_um": np.zeros(500)}}
    ranges = {"factor": {"pressure_MPa": (0.5, 3.0), "sliding_speed_m_per_s": (0.01, 0.1)}}
    sep = separation(p, v, Z, ranges, "st.toml")
    assert sep["command"] == ("jaxwear design st.toml --goal separate --between "
                              "shape:pressure_MPa,shape:sliding_speed_m_per_s")
    assert sep["variable"] in ("pressure_MPa", "sliding_speed_m_per_s")


def test_one_peer_of_the_same_complexity_after_a_law_at_the_noise():
    power = _fit(POWER_H, 0.3195, SE2, PER, at_noise=True)
    screened = [(500.0, POWER_H), (400.0, HINGE_H), (300.0, EXP_H), (100.0, POWER_P)]
    pk = peer_pick(screened, [power], 2880)
    assert pk is not None and pk[1].label == EXP_H.label  # 2 constants, the best such left
    assert peer_pick(screened, [dataclasses.replace(power, at_noise=False)], 2880) is None
    assert peer_pick(screened[:2], [power], 2880) is None  # only other complexities left


def test_equivalents_in_the_json_and_the_sentence():
    power = _fit(POWER_H, 0.3195, SE2, PER)
    exp = _fit(EXP_H, 0.3250, SE2, PER)
    sep = {"variable": "worn_depth_um", "unit": "µm", "at": 12.0, "ratio": 1.3,
           "ratio_in_range": 1.02, "range_met": [0.0, 6.0], "beyond_range": True,
           "command": None}
    res = LawResult(power, (power, exp), 100, 0.30, 0.39, 0.40, 1.0, shape_rmse_um=0.314,
                    equivalents=(exp,), separations=(sep,))
    res = dataclasses.replace(res, sentence=law_sentence(res))
    doc = res.to_json()
    (e,) = doc["equivalents"]
    assert e["formula"] == exp.formula and e["loo_rmse_um"] == 0.325
    assert e["constants"]["A"] == {"value": 0.3, "stderr": 0.02, "unit": "-"}
    assert e["separation"]["at"] == 12.0
    assert "do not tell" in res.sentence and "h = 12 µm" in res.sentence
    assert doc["status"] in ("found", "lead")  # the found/lead rule is the answer's alone
    solo = LawResult(power, (power,), 100, 0.30, 0.39, 0.40, 1.0, shape_rmse_um=0.314)
    assert solo.to_json()["equivalents"] == [] and solo.status == res.status


def test_a_lead_best_law_gives_its_determined_neighbours_to_fit():
    from jaxwear._analyses.diagnose.law.search import pruned

    # the rich design's g_power_p (seed 1): exp(ω)·hinge(p) at the shape's RMSE with ω's
    # rate and the hinge's threshold undetermined: the power of p alone is its neighbour,
    # starting at the exponent the lead fitted
    lead = LawSpec("factor", (Term("exp", "load_turn_rate_deg_per_s", 39.0, b=5e-4),
                              Term("hinge", "pressure_MPa", 1.08, x0=0.17, a=1.88)), 0.62)
    se = {"law_gain": 0.28, "law_b_2": 1.0, "law_b_1": 1.0, "law_x0_2": 0.33,
          "law_a_2": 0.38}
    f = _fit(lead, 0.3109, se)
    assert set(f.undetermined) >= {"omega_e", "p0"}
    got = pruned([f])
    assert [g.label for g in got] == ["factor: power(pressure_MPa)"]
    assert got[0].terms[0].a == 1.88 and got[0].terms[0].ref == 1.08
    # already fitted (its label done): nothing left to try
    assert pruned([f], done={"factor: power(pressure_MPa)"}) == []
    # a determined best law, or a lead whose every term is undetermined: nothing
    assert pruned([_fit(POWER_P, 0.31, {"law_gain": 0.05, "law_a_1": 0.1})]) == []
    bad = _fit(POWER_P, 0.31, {"law_gain": 0.05, "law_a_1": 3.0})
    assert bad.undetermined == ("a1",) and pruned([bad]) == []
    # a product whose one term is undetermined: the other alone
    two = LawSpec("factor", (Term("step", "pressure_MPa", 1.5, x0=1.06, w=0.09),
                             Term("step", "load_turn_rate_deg_per_s", 100.0, x0=0.02,
                                  w=1.1)), 2.4)
    se2 = {"law_gain": 0.2, "law_x0_1": 0.02, "law_w_1": 0.01, "law_x0_2": 0.16,
           "law_w_2": 0.3}
    g = pruned([_fit(two, 0.3126, se2)])
    assert [x.label for x in g] == ["factor: step(pressure_MPa)"]


def _dep(kind, var, ref, strength=0.003, **kw):
    return LawSpec("deposit", (Term(kind, var, ref, **kw),), strength)


def test_a_pick_simpler_than_a_law_at_the_noise_is_fitted_too():
    """The rich design's deposit ∝ (W/150 N)² (seed 2): the screen's picks hinge(W),
    power(W), step(W); the hinge (3 constants) fitted to the noise first, and the power
    (2), which would win a tie, was skipped as "a law already fits to noise" while the
    step (3) was fitted as its peer. The power is fitted; the step as the one peer; a
    product of 4 and a second peer are not; a law with memory is not; before any law fits
    to noise, everything is."""
    from jaxwear._analyses.diagnose.law.search import after_noise

    hinge = _dep("hinge", "load_N", 150.0, x0=0.4, a=1.0)
    power_w = _dep("power", "load_N", 150.0, a=2.0)
    step = _dep("step", "load_N", 150.0, x0=1.0, w=0.1)
    prod = LawSpec("deposit", (Term("power", "load_N", 150.0, a=2.0),
                               Term("step", "pressure_MPa", 1.5, x0=1.0, w=0.1)), 0.003)
    se = {"law_deposit": 1e-4, "law_x0_1": 0.02, "law_a_1": 0.1}
    at = [_fit(hinge, 0.3145, se, at_noise=True)]
    assert after_noise(power_w, "screen", at, 0) == (True, False)
    assert after_noise(step, "screen", at, 0) == (True, True)
    assert after_noise(step, "screen", at, 1) == (False, False)  # PEERS = 1 spent
    assert after_noise(prod, "screen", at, 0) == (False, False)
    assert after_noise(step, "memory", at, 0) == (False, False)
    not_at = [dataclasses.replace(at[0], at_noise=False)]
    assert after_noise(prod, "screen", not_at, 0) == (True, False)


def test_a_lead_with_an_undetermined_term_gives_the_screens_changes_of_that_term():
    """The rich design's step(p)·power(v) (seeds 1, 2): step(p)·step(ω) answered with ω's
    threshold undetermined; the screen's best products that keep step(p) and change the
    other term are fitted (best score first), not those that drop step(p), not the lead's
    own structure, not one fitted already (either term order); a determined lead gives
    none."""
    from jaxwear._analyses.diagnose.law.search import same, swaps

    step_p = Term("step", "pressure_MPa", 1.5, x0=1.0, w=0.07)
    lead = LawSpec("factor", (step_p, Term("step", "load_turn_rate_deg_per_s", 100.0,
                                           x0=0.02, w=1.1)), 2.4)
    se = {"law_gain": 0.2, "law_x0_1": 0.02, "law_w_1": 0.01, "law_x0_2": 3.0,
          "law_w_2": 0.3}
    f = _fit(lead, 0.3126, se)
    assert "omega0" in f.undetermined and "p0" not in f.undetermined
    power_v = LawSpec("factor", (Term("power", "sliding_speed_m_per_s", 0.04, a=1.0),
                                 step_p), 1.0)
    exp_s = LawSpec("factor", (step_p, Term("exp", "sliding_distance_m", 20.0, b=1.0)), 1.0)
    other = LawSpec("factor", (Term("power", "pressure_MPa", 1.5, a=2.0),
                               Term("power", "sliding_speed_m_per_s", 0.04, a=1.0)), 1.0)
    single = LawSpec("factor", (step_p,), 1.0)
    screened = [(7400.0, lead), (7390.0, other), (7380.0, power_v), (7350.0, exp_s),
                (7000.0, single)]
    got = swaps([f], screened, n_rows=2880)
    assert [g[1].label for g in got] == [power_v.label, exp_s.label]
    # step(p)·power(v) fitted already, its terms the other way round
    flipped = LawSpec("factor", power_v.terms[::-1], 1.0)
    assert [g[1].label for g in swaps([f], screened, {same(flipped)}, 2880)] == [exp_s.label]
    # a determined lead: nothing to change
    se_ok = dict(se, law_x0_2=0.005)
    assert swaps([_fit(lead, 0.3126, se_ok)], screened, n_rows=2880) == []


def test_a_swap_skips_the_undetermined_terms_twin_variable():
    """The rich design's step(p)·power(v), seed 3: the lead step(p)·step(turn) with the
    turn's step undetermined. The load's turn per crank degree and per second differ by
    the crank's speed, one constant per experiment, so step(p)·step(ω) is not a change the
    data can tell better; the screen's next structures keeping step(p) are fitted in its
    place (a power of ω, another kind, stays a swap)."""
    from jaxwear._analyses.diagnose.law.search import swaps

    step_p = Term("step", "pressure_MPa", 1.5, x0=1.0, w=0.07)
    lead = LawSpec("factor", (Term("step", "load_turn_deg_per_deg", 0.3, x0=0.1, w=1.0),
                              step_p), 2.0)
    se = {"law_gain": 0.2, "law_x0_1": 3.0, "law_w_1": 3.0, "law_x0_2": 0.02,
          "law_w_2": 0.01}
    f = _fit(lead, 0.3135, se)
    assert {"turn0", "turn_width"} <= set(f.undetermined) and "p0" not in f.undetermined
    twin = LawSpec("factor", (Term("step", "load_turn_rate_deg_per_s", 40.0, x0=0.1,
                                   w=1.0), step_p), 1.0)
    exp_h = LawSpec("factor", (step_p, Term("exp", "worn_depth_um", 5.0, b=1.0)), 1.0)
    power_v = LawSpec("factor", (step_p, Term("power", "sliding_speed_m_per_s", 0.05,
                                              a=1.0)), 1.0)
    power_w = LawSpec("factor", (step_p, Term("power", "load_turn_rate_deg_per_s", 40.0,
                                              a=1.0)), 1.0)
    screened = [(8317.0, lead), (8298.0, twin), (8070.0, exp_h), (8016.0, power_v),
                (8000.0, power_w)]
    got = [g[1].label for g in swaps([f], screened, n_rows=2880)]
    assert got == [exp_h.label, power_v.label, power_w.label]


def test_a_single_undetermined_term_is_changed_for_the_screens_next_single_laws():
    """The rich design's exponential of the worn depth (seed 3): a hinge in h with its
    threshold undetermined; the screen's next one-term laws (the exponential, the power
    fitted already aside) are fitted, not the products."""
    from jaxwear._analyses.diagnose.law.search import same, swaps

    f = _fit(HINGE_H, 0.3120, {"law_gain": 0.06, "law_a_1": 0.3, "law_x0_1": 0.6})
    assert f.undetermined == ("h0",)
    prod = LawSpec("factor", (HINGE_H.terms[0], Term("exp", "load_turn_deg_per_deg", 0.03,
                                                     b=-0.1)), 0.1)
    screened = [(9064.0, HINGE_H), (9055.0, prod), (9050.0, POWER_H), (9040.0, EXP_H),
                (100.0, POWER_P)]
    got = swaps([f], screened, {same(POWER_H)}, 2880)
    assert [g[1].label for g in got] == [EXP_H.label, POWER_P.label]


def test_an_exponential_factor_is_bounded_by_the_rate_it_gives():
    """A factor's rate is K_d (1 + A Φ): its growth from the top of the states met (h =
    14.42 µm) to twice it is that of 1 + A Φ, not Φ's. By hand, exp((h − h_s)/6 µm) at
    h_s = 3.2 µm: Φ grows e^(14.42/6) = 11.0-fold (more than `EXP_GROWTH`, 10), Φ(14.42) =
    e^1.870 = 6.49 and Φ(28.84) = e^4.273 = 71.7; with A = 0.37 the rate grows (1 + 26.5)
    / (1 + 2.40) = 8.1-fold (left as it is), with A = 100 by 7171 / 650 = 11.0 (bounded
    where 1 + AΦ = 6500: Φ = 64.99, h = 3.2 + 6 ln 64.99 = 28.24 µm); a deposit's rate is
    DΦ, and so is a law not yet fitted (strength 0: Φ's): bounded where Φ has grown
    tenfold, h = 14.42 + 6 ln 10 = 28.24 µm."""
    from jaxwear._analyses.diagnose.law.search import bounded

    ranges = {"worn_depth_um": (0.0, 14.42)}
    term = Term("exp", "worn_depth_um", 3.2, b=3.2 / 6.0)
    kept = LawSpec("factor", (term,), 0.37)
    assert bounded(kept, ranges) == (kept, ())
    law, said = bounded(LawSpec("factor", (term,), 100.0), ranges)
    # the same unrounded: 1 + 100 Φ(h_c) = 10 (1 + 100 Φ(14.42)), Φ(h) = e^((h − 3.2)/6)
    phi_c = (10.0 * (1.0 + 100.0 * np.exp((14.42 - 3.2) / 6.0)) - 1.0) / 100.0
    assert law.terms[0].cap * 3.2 == pytest.approx(3.2 + 6.0 * np.log(phi_c), rel=1e-12)
    assert law.terms[0].cap * 3.2 == pytest.approx(28.24, abs=0.01)
    assert "a rate with an exponential" in said[0]["reason"]
    assert said[0]["growth"] == pytest.approx(7171.0 / 650.0, rel=2e-3)
    assert said[0]["growth_capped"] == pytest.approx(10.0, rel=1e-9)
    for form, a in (("deposit", 0.37), ("factor", 0.0)):
        law, said = bounded(LawSpec(form, (term,), a), ranges)
        assert law.terms[0].cap * 3.2 == pytest.approx(14.42 + 6.0 * np.log(10.0))
        assert "grow 11.1-fold" in said[0]["reason"]
