"""Products of variables and the choice among confounded ones in the shape (issue 43 item 1):
the surface over the leading pair (`effects.shape.ShapeTensor`, `shape.interaction`) and
the ranking by unique shares and left-out experiments (`shape.choice`).

The linear-system tests build their own columns from closed forms (a row's response is the
correction at its states), so the truth is known exactly: a product g1(z1) g2(z2) of two
independent variables, or a sum g1(z1) + g2(z2)."""

import math
from types import SimpleNamespace as V

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.diagnose import Model
from jaxwear._analyses.diagnose.shape import linear as lin
from jaxwear._analyses.diagnose.shape.choice import left_out_errors, rank_alternatives
from jaxwear._analyses.diagnose.shape.interaction import (
    SURFACE_MATERIAL,
    interaction_test,
    rmse_gain_linearised,
    tensor_system,
)
from jaxwear._analyses.diagnose.shape.text import describe, next_test, next_test_sentence
from jaxwear._physics.effects.shape import (
    ShapeBasis,
    ShapeTensor,
    ShapeVariable,
    tensor_dot,
)

SMALL = dict(nodes=48, steps_per_rev=72, revolutions_per_update=500)
UNIT = tuple(np.linspace(0.0, 1.0, 33))  # knots of a variable on [0, 1]
ALPHA = 1e-3 / 15


def _var(name, size, form="factor"):
    return ShapeVariable(name, size, UNIT, form)


def test_surface_jvp_rule_is_the_derivative_of_the_plain_product():
    """`tensor_dot`'s own JVP (slopes once per state) against autodiff of the plain
    expression Σ_kl c_kl B_k(z_a) B_l(z_b), in the states and the coefficients."""
    t = ShapeTensor(_var("pressure_MPa", 5), _var("sliding_speed_m_per_s", 5))
    rng = np.random.default_rng(0)
    za, zb = jnp.asarray(rng.uniform(0, 1, 40)), jnp.asarray(rng.uniform(0, 1, 40))
    c = jnp.asarray(rng.standard_normal(25))

    def plain(za, zb, c):
        return jnp.einsum("nk,nl,kl->n", t.a.basis(za), t.b.basis(zb), c.reshape(5, 5))

    np.testing.assert_allclose(tensor_dot(t, za, zb, c), plain(za, zb, c), rtol=1e-12)
    tang = (jnp.asarray(rng.standard_normal(40)), jnp.asarray(rng.standard_normal(40)),
            jnp.asarray(rng.standard_normal(25)))
    _, d_rule = jax.jvp(lambda *x: tensor_dot(t, *x), (za, zb, c), tang)
    _, d_plain = jax.jvp(plain, (za, zb, c), tang)
    np.testing.assert_allclose(d_rule, d_plain, rtol=1e-10, atol=1e-12)
    # a surface of one variable alone (equal columns) lies outside the factor's constraint
    assert np.allclose(np.kron(lin.sum_zero(5), lin.sum_zero(5)).T
                       @ np.kron(rng.standard_normal(5), np.ones(5)), 0.0)


def test_surface_gradient_through_the_loop_matches_central_differences():
    """d rows / d c of a factor surface over pressure x sliding speed and a deposit surface
    over the load's turn x the load, through the wear loop (forward mode), against central
    finite differences of the rows, at a point with both on."""
    res = jw.synthesize([], "paper", noise_um=0.3, seed=2, numerics=SMALL)
    study = res.study.with_experiments(res.study.experiments[:1])
    k = {"pressure_MPa": tuple(np.linspace(0.1, 4.0, 33)),
         "sliding_speed_m_per_s": tuple(np.linspace(0.005, 0.08, 33)),
         "load_turn_rate_deg_per_s": tuple(np.geomspace(1.0, 1e4, 33)),
         "load_N": tuple(np.linspace(0.0, 300.0, 33))}
    fac = ShapeTensor(ShapeVariable("pressure_MPa", 4, k["pressure_MPa"]),
                      ShapeVariable("sliding_speed_m_per_s", 4, k["sliding_speed_m_per_s"]))
    dep = ShapeTensor(
        ShapeVariable("load_turn_rate_deg_per_s", 4, k["load_turn_rate_deg_per_s"], "deposit"),
        ShapeVariable("load_N", 4, k["load_N"], "deposit"))
    m = Model(study, candidates=[], shape=ShapeBasis((), (fac, dep)))
    rng = np.random.default_rng(3)
    u = np.zeros(len(m.names))
    for key in fac.keys():
        u[m.index[key]] = 0.1 * rng.standard_normal()
    for key in dep.keys():
        u[m.index[key]] = 0.003 * abs(rng.standard_normal())
    ev = m.evaluate(u)
    assert float(ev.worn) < 0
    for name, h in ((fac.keys()[5], 1e-4), (fac.keys()[10], 1e-4), (dep.keys()[9], 1e-6)):
        i = m.index[name]
        up, um = u.copy(), u.copy()
        up[i] += h
        um[i] -= h
        fd = (m.predict(up) - m.predict(um)) / (2 * h)
        assert np.abs(fd).max() > 1e-4, name  # the coefficient moves the model
        np.testing.assert_allclose(ev.J[:, i], fd, rtol=2e-5, atol=1e-7 * np.abs(fd).max())


def _system(truth, seed, n=600):
    """A linear system whose rows respond to the correction at their own states: z1, z2
    independent uniform on [0, 1], ρ = truth(z1, z2)/σ + N(0, 1). Returns the additive
    blocks (A, S) of both variables (sum-zero, 10 B-splines), the surface's (A, S, Z, X),
    ρ and the tensor."""
    rng = np.random.default_rng(seed)
    z1, z2 = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    rho = truth(z1, z2) + rng.standard_normal(n)
    Z = lin.sum_zero(10)
    blocks = []
    for name, z in (("pressure_MPa", z1), ("sliding_speed_m_per_s", z2)):
        v = _var(name, 10)
        blocks.append((np.asarray(v.basis(jnp.asarray(z))) @ Z, Z.T @ v.roughness() @ Z))
    t = ShapeTensor(_var("pressure_MPa", 5), _var("sliding_speed_m_per_s", 5))
    cols = np.asarray(t.basis(jnp.asarray(z1), jnp.asarray(z2)))
    sys_t = tensor_system(t, cols, 1.0, 0, [], 0.0, n, lambda X: X)
    return blocks, sys_t, rho, t, rng


def _test(truth, seed, n=600):
    blocks, (A, S, Z, X), rho, t, rng = _system(truth, seed, n)
    rss0 = float(rho @ rho)
    n = len(rho)
    excess = rss0 - n
    add, _ = lin.joint_fit(blocks, rho, n, math.inf, rng, 200)
    inter = interaction_test(t, A, S, Z, X, [b[0] for b in blocks], rho, n, math.inf, rng,
                             20000, excess, rss0, ALPHA)
    return inter, lin.explained(add.drop, add.dof, excess, rss0)


def test_a_product_of_two_variables_needs_the_surface():
    """Truth g1(z1) g2(z2), each centred: no sum of one-variable corrections holds it (the
    additive fit explains little of it), the surface on top of it is significant and
    explains most of the misfit."""
    inter, additive = _test(lambda a, b: 3.0 * np.cos(np.pi * a) * np.sin(2 * np.pi * b), 1)
    assert inter.significant and inter.p_value < ALPHA, inter
    assert inter.explained_fraction > 0.6, inter
    assert additive < 0.2
    assert inter.variables == ("pressure_MPa", "sliding_speed_m_per_s")
    assert inter.to_json()["dof"] > 2.0


def test_a_significant_surface_too_small_to_move_the_refit_is_not_carried():
    """A product g1 g2 of amplitude 0.14 σ on 20 000 rows: ΔRSS ≈ 0.14² n / 4 ≈ 100 σ²,
    far beyond the noise (significant), but net of its ~10 dof it would lower a refit's
    RMSE by (ΔRSS − dof)/(2 n) ≈ 0.2 % (hand calculation; linearised), under the 1 % any
    comparison of the refit resolves: not carried. The large product above is carried."""
    inter, _ = _test(lambda a, b: 0.14 * np.cos(np.pi * a) * np.sin(2 * np.pi * b), 5,
                     n=20000)
    assert inter.significant, inter
    expected = max(inter.statistic - inter.dof, 0.0) / (2 * 20000)
    assert inter.rmse_gain_linearised == pytest.approx(expected, rel=1e-3)
    assert 0.0005 < inter.rmse_gain_linearised < SURFACE_MATERIAL, inter
    assert not inter.carried and inter.to_json()["carried"] is False
    big, _ = _test(lambda a, b: 3.0 * np.cos(np.pi * a) * np.sin(2 * np.pi * b), 1)
    assert big.carried and big.rmse_gain_linearised > 0.1, big


def test_the_sentence_names_a_surface_left_out_of_the_refit_with_its_figure():
    """A significant surface under `SURFACE_MATERIAL` is still named as a product, with why
    the refit leaves it out; a carried one is named without that clause."""
    from jaxwear._analyses.diagnose.shape.interaction import Interaction

    g = np.linspace(0, 1, 50)
    res = [V(name=n, form="factor", explained_fraction=0.8, p_value=1e-6, z=g,
             g=np.sin(6 * g), g_lower=np.sin(6 * g) - 0.1, g_upper=np.sin(6 * g) + 0.1,
             unit="MPa", stand_in_for=None)
           for n in ("pressure_MPa", "sliding_speed_m_per_s")]

    def sentence(gain):
        inter = Interaction(("pressure_MPa", "sliding_speed_m_per_s"), "factor", 0.01, 5e-5,
                            10.0, 52.0, True, gain)
        return describe("pressure_MPa", "factor", res, {}, "base", [],
                        ("pressure_MPa", "sliding_speed_m_per_s"), None, interaction=inter)

    left = sentence(0.0073)
    assert "as a product of pressure_MPa and sliding_speed_m_per_s" in left
    assert "not refitted" in left and "0.7%" in left and "under the 1%" in left
    carried = sentence(0.02)
    assert "as a product of" in carried and "not refitted" not in carried


def test_the_linearised_gain_by_hand_and_its_correlated_noise_allowance():
    """(ΔRSS − dof)⁺/(2 n), and with AR(1) noise of φ = 0.5 prewhitened rows hold as
    little as (1 − φ)/(1 + φ) = 1/3 of a smooth correction's sum of squares: 3 x."""
    assert rmse_gain_linearised(130.0, 10.0, 1000) == pytest.approx(0.06)
    assert rmse_gain_linearised(130.0, 10.0, 1000, phi=0.5) == pytest.approx(0.18)
    assert rmse_gain_linearised(130.0, 10.0, 1000, phi=-0.5) == pytest.approx(0.18)
    assert rmse_gain_linearised(5.0, 10.0, 1000) == 0.0


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_an_additive_truth_leaves_the_surface_insignificant(seed):
    """Truth g1(z1) + g2(z2) (large: the additive fit explains it): the surface over the
    pair adds nothing significant."""
    inter, additive = _test(lambda a, b: 2.0 * np.cos(np.pi * a) + 2.0 * np.sin(2 * np.pi * b),
                            seed)
    assert additive > 0.8
    assert not inter.significant and inter.p_value > 1e-3, inter


def _confounded(shift, seed=0, jitter=0.02):
    """Three experiments; the misfit follows z1, and z2 = z1 + (a shift per experiment)
    (+ N(0, jitter²)): alone, each explains the misfit within an experiment."""
    rng = np.random.default_rng(seed)
    per = 200
    exps = np.repeat(np.arange(3), per)
    z1 = rng.uniform(0.1, 0.9, 3 * per)
    z2 = np.clip(z1 + np.array(shift)[exps] + jitter * rng.standard_normal(3 * per), 0, 1)
    rho = 2.5 * np.sin(2 * np.pi * z1) + rng.standard_normal(3 * per)
    Z = lin.sum_zero(10)
    blocks, shapes = {}, []
    for name, z in (("pressure_MPa", z1), ("sliding_speed_m_per_s", z2)):
        v = _var(name, 10)
        A = np.asarray(v.basis(jnp.asarray(z))) @ Z
        S = Z.T @ v.roughness() @ Z
        pf = lin.penalised_fit(A, S, rho, len(rho), math.inf, rng, 0)
        blocks[name] = (A, S)
        shapes.append(V(name=name, label=name, form="factor", lam=pf.lam,
                        explained_fraction=lin.explained(pf.drop, pf.dof, len(rho), rho @ rho),
                        aic=-pf.drop + 2 * pf.dof, unique_p_value=0.5))
    return blocks, rho, exps, shapes


def test_left_out_experiments_pick_the_true_variable_of_two_partly_confounded():
    """z2 follows z1 within each experiment but with another offset in each: a correction
    along z2 fitted on two experiments misplaces the third's misfit; along z1 it carries
    over. With neither unique share significant, and the wrong one leading by its alone
    share, the left-out error picks z1, and they are not called confounded."""
    blocks, rho, exps, (true, wrong) = _confounded([0.0, 0.08, -0.08])
    wrong = V(**{**vars(wrong), "explained_fraction": true.explained_fraction + 0.01})
    loo_t = left_out_errors(*blocks["pressure_MPa"], true.lam, rho, exps, len(rho))
    loo_w = left_out_errors(*blocks["sliding_speed_m_per_s"], wrong.lam, rho, exps, len(rho))
    assert loo_t.sum() < loo_w.sum()
    chosen, others, confounded, _ = rank_alternatives(wrong, [true], blocks, rho, exps,
                                                      len(rho), ALPHA)
    assert chosen is true and others == [wrong]
    assert confounded == []
    # a significant unique share decides before the left-out error
    sig = V(**{**vars(wrong), "unique_p_value": 1e-9})
    assert rank_alternatives(true, [sig], blocks, rho, exps, len(rho), ALPHA)[0] is sig


def test_variables_the_experiments_vary_together_are_confounded_and_the_text_says_so():
    """z2 = z1 in every experiment: the left-out errors agree, no unique share is
    significant: `confounded` names both, the sentence points at the design verb in one
    line."""
    blocks, rho, exps, (a, b) = _confounded([0.0, 0.0, 0.0], jitter=0.0)
    chosen, _, confounded, _ = rank_alternatives(a, [b], blocks, rho, exps, len(rho), ALPHA)
    assert chosen is a
    assert sorted(confounded) == ["pressure_MPa", "sliding_speed_m_per_s"]
    g = np.linspace(0, 1, 50)
    res = [V(name=v.name, form="factor", explained_fraction=1.0, p_value=1e-6, z=g,
             g=np.sin(6 * g), g_lower=np.sin(6 * g) - 0.1, g_upper=np.sin(6 * g) + 0.1,
             unit="MPa", stand_in_for=None) for v in (a, b)]
    s = describe("pressure_MPa", "factor", res, {}, "base", ["sliding_speed_m_per_s"],
                 ("pressure_MPa",), None, confounded=confounded)
    line = next(x for x in s.split(". ") if "cannot tell" in x)
    assert "sliding_speed_m_per_s" in line and "AIC within" not in s
    # the next sentence is the command that tells them apart (`shape.next_test`)
    cmd = next_test("s.toml", "pressure_MPa", "factor", res, ["sliding_speed_m_per_s"],
                    confounded)
    assert cmd == ("jaxwear design s.toml --goal separate --between "
                   "shape:pressure_MPa,shape:sliding_speed_m_per_s")
    assert cmd in next_test_sentence(cmd)


def test_the_effect_file_computes_the_surface_as_the_model_does():
    """`missing_wear.py` holds a refitted surface beside a variable's spline: its
    `correction(z)` is the model's Σ terms (`ShapeVariable.basis`, `ShapeTensor.basis`) at
    the same states, the surface over a periodic and a clamped variable."""
    from jaxwear._report.effect_file import effect_file_source

    rng = np.random.default_rng(7)
    v = _var("pressure_MPa", 10)
    t = ShapeTensor(ShapeVariable("cycle_phase_deg", 5, (), "factor"),
                    _var("sliding_speed_m_per_s", 4))
    cv, ct = rng.standard_normal(10), rng.standard_normal(20)
    corr = {"form": "factor",
            "variables": [{"name": v.name, "form": "factor", "size": 10,
                           "knots": list(v.knots), "coefficients": list(cv)}],
            "tensors": [{"variables": [t.a.name, t.b.name], "form": "factor", "size": [5, 4],
                         "knots": [[], list(t.b.knots)], "coefficients": list(ct)}]}
    src = effect_file_source(V(correction=corr, sentence="a test"), "study.toml")
    ns = {}
    exec(compile(src, "missing_wear.py", "exec"), ns)
    z = {"pressure_MPa": jnp.asarray(rng.uniform(0, 1, 30)),
         "cycle_phase_deg": jnp.asarray(rng.uniform(0, 360, 30)),
         "sliding_speed_m_per_s": jnp.asarray(rng.uniform(0, 1, 30))}
    want = (np.asarray(v.basis(z["pressure_MPa"])) @ cv
            + np.asarray(t.basis(z["cycle_phase_deg"], z["sliding_speed_m_per_s"])) @ ct)
    np.testing.assert_allclose(np.asarray(ns["correction"](z)), want, rtol=1e-9, atol=1e-12)
    assert "cycle_phase_deg x sliding_speed_m_per_s" in src


def test_the_refits_sum_rows_hold_exactly_the_surfaces_of_no_single_variable():
    """The refit's prior rows on a factor surface (each row's and each column's sum of its
    coefficient grid at zero) vanish exactly on the analysis's constrained coefficients
    (Z_a ⊗ Z_b) and on nothing else: their null space has the dimension (5−1)(4−1)."""
    from jaxwear._analyses.diagnose.shape.refit import _sums

    t = ShapeTensor(_var("pressure_MPa", 5), _var("sliding_speed_m_per_s", 4))
    M = _sums(t)
    Z = np.kron(lin.sum_zero(5), lin.sum_zero(4))
    np.testing.assert_allclose(M @ Z, 0.0, atol=1e-12)
    assert t.size - np.linalg.matrix_rank(M) == Z.shape[1] == 12
    assert _sums(_var("load_N", 6)).shape == (1, 6)


def test_the_pair_is_the_leader_and_a_carrier_else_the_two_leading_variables():
    """A stand-in (significant alone, no unique share) is passed over for a carrier that
    explains less alone; where no other variable carries, the two that explain most
    alone (the leader need not carry itself: the joint fit may give its share to
    another)."""
    from jaxwear._analyses.diagnose.shape.interaction import leading_pair

    def v(name, share, carries, form="factor", significant=True):
        return V(name=name, form=form, explained_fraction=share, carries=carries,
                 significant=significant)

    res = [v("sliding_speed_m_per_s", 0.77, True), v("load_N", 0.70, False),
           v("pressure_MPa", 0.40, True), v("bore_angle_deg", 0.9, False, significant=False),
           v("load_N", 0.95, True, form="deposit")]
    assert leading_pair(res, "factor") == ("sliding_speed_m_per_s", "pressure_MPa")
    res[0] = v("sliding_speed_m_per_s", 0.77, False)
    assert leading_pair(res, "factor") == ("sliding_speed_m_per_s", "pressure_MPa")
    res[2] = v("pressure_MPa", 0.40, False)
    assert leading_pair(res, "factor") == ("sliding_speed_m_per_s", "load_N")
    assert leading_pair(res, "deposit") is None
