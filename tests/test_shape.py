"""The shape of the missing wear (`diagnose --shape`, design.md §7, issues 20 and 25).

Unit tests check the pieces against hand calculations and closed forms; the integration
test runs the worked example of docs/effects.md on physics the library does not have,
made by an independent generator at finer numerics (`benchmarks/hidden_physics.py`).
"""

import math
import runpy
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.diagnose import Model
from jaxwear._analyses.diagnose.shape import linear as lin
from jaxwear._analyses.diagnose.shape.analysis import choose_best
from jaxwear._analyses.diagnose.shape.design import make_basis
from jaxwear._physics.effects.shape import (
    DEPOSIT_VARIABLES,
    VARIABLES,
    ShapeVariable,
    basis_dot,
    state_variables,
    swept_kernel,
)

ROOT = Path(__file__).resolve().parents[1]
SMALL = dict(nodes=48, steps_per_rev=48, revolutions_per_update=500)
_K = {"pressure_MPa": tuple(np.linspace(0.1, 4.0, 33)),
      "sliding_speed_m_per_s": tuple(np.linspace(0.005, 0.08, 33)),
      "sliding_distance_m": tuple(np.linspace(0.0, 200.0, 33)),
      "load_turn_rate_deg_per_s": tuple(np.geomspace(1.0, 1e4, 33)),
      "load_turn_deg_per_deg": tuple(np.geomspace(1e-3, 10.0, 33)),
      "load_N": tuple(np.linspace(0.0, 300.0, 33)),
      "worn_depth_um": tuple(np.linspace(0.0, 20.0, 33))}
KNOTS = {"factor": _K, "deposit": _K}


def test_basis_is_a_partition_of_unity_and_the_penalty_spares_constants():
    """A constant correction needs coefficients all equal (what the sum-zero constraint
    removes from a factor: a change of K_d), and the roughness penalty costs nothing for it;
    the clamped basis also reproduces straight lines in its coordinate."""
    basis = make_basis(KNOTS)
    assert {v.label for v in basis.variables} == set(VARIABLES) | {
        f"deposit:{n}" for n in DEPOSIT_VARIABLES}
    for var in basis.variables:
        z = (np.linspace(0.0, 359.9, 97) if var.periodic else
             np.linspace(var.lo - 1.0, var.hi * 1.1, 97))
        B = np.asarray(var.basis(jnp.asarray(z)))
        np.testing.assert_allclose(B.sum(axis=1), 1.0, atol=1e-12)
        R = var.roughness()
        np.testing.assert_allclose(R @ np.ones(var.size), 0.0, atol=1e-12)
        if not var.periodic:
            line = np.arange(var.size, dtype=float)
            np.testing.assert_allclose(R @ line, 0.0, atol=1e-9)
    Z = lin.sum_zero(12)
    np.testing.assert_allclose(Z.T @ Z, np.eye(11), atol=1e-12)
    np.testing.assert_allclose(np.ones(12) @ Z, 0.0, atol=1e-12)


def test_basis_dot_rule_is_the_derivative_of_the_spline():
    """The hand-written JVP of B(z) @ c (`basis_dot`, what keeps the design Jacobian's cost
    at columns + size per state) against central differences in z and c, inside the data's
    range, beyond it (clamped: flat) and on the circle; batched tangents as jacfwd sends."""
    import jax

    rng = np.random.default_rng(3)
    for var in (ShapeVariable("pressure_MPa", 10, _K["pressure_MPa"]),
                ShapeVariable("bore_angle_deg", 10)):
        lo, hi = (0.0, 360.0) if var.periodic else (var.lo - 0.5, var.hi + 0.5)
        z = jnp.asarray(rng.uniform(lo, hi, (6, 7)))
        c = jnp.asarray(rng.normal(size=10))
        dz = jnp.asarray(rng.normal(size=(6, 7)))
        dc = jnp.asarray(rng.normal(size=10))
        f = lambda zz, cc: basis_dot(var, zz, cc)  # noqa: E731
        _, t = jax.jvp(f, (z, c), (dz, dc))
        h = 1e-6
        fd = (f(z + h * dz, c + h * dc) - f(z - h * dz, c - h * dc)) / (2 * h)
        np.testing.assert_allclose(np.asarray(t), np.asarray(fd), rtol=1e-6, atol=1e-8)
        J = jax.jacfwd(f, argnums=1)(z, c)
        np.testing.assert_allclose(np.asarray(J), np.asarray(var.basis(z)), atol=1e-14)


def test_state_variables_by_hand():
    """Phase, speed, turn rate (per second and per degree of the cycle), load and bore angle
    of a hand-made cycle."""
    steps, nodes = 8, 4
    pressure = jnp.full((steps, nodes), 2e6)
    dt = jnp.full(steps, 0.5)
    slide = jnp.full(steps, 0.01)
    angle = jnp.asarray(np.radians([0, 10, 20, 30, 40, 200, 210, 220]))
    load = jnp.arange(steps) * 10.0
    z = state_variables(pressure, slide, dt, 3.0, angle, load)
    np.testing.assert_allclose(np.asarray(z["cycle_phase_deg"])[:, 0], np.arange(8) * 45.0)
    np.testing.assert_allclose(np.asarray(z["pressure_MPa"]), 2.0)
    np.testing.assert_allclose(np.asarray(z["sliding_speed_m_per_s"]), 0.02)
    np.testing.assert_allclose(np.asarray(z["sliding_distance_m"]), 3.0)
    np.testing.assert_allclose(np.asarray(z["bore_angle_deg"])[0], [0, 90, 180, 270])
    np.testing.assert_allclose(np.asarray(z["load_N"])[:, 0], np.arange(8) * 10.0)
    # central difference over two steps (1 s): |θ_{i+1} - θ_{i-1}| wrapped to ≤ 180°
    w = np.asarray(z["load_turn_rate_deg_per_s"])[:, 0]
    np.testing.assert_allclose(w[[1, 2, 3, 6]], 20.0)
    np.testing.assert_allclose(w[[4, 5]], 170.0)  # 30° -> 200°, 40° -> 210°
    np.testing.assert_allclose(w[[7, 0]], 150.0)  # 210° -> 360°, 220° -> 10°: the short way
    # per degree of the cycle: two steps are 90° of it, whatever the speed
    np.testing.assert_allclose(np.asarray(z["load_turn_deg_per_deg"])[:, 0], w * 1.0 / 90.0)
    assert set(z) == set(VARIABLES)
    # the surface's own state: the profile the cycle wears on, per node, in µm; unworn
    # without one
    np.testing.assert_allclose(np.asarray(z["worn_depth_um"]), 0.0)
    h = jnp.asarray([0.0, 1e-6, 2.5e-6, 4e-6])
    zw = state_variables(pressure, slide, dt, 3.0, angle, load, h)
    np.testing.assert_allclose(np.asarray(zw["worn_depth_um"]), [[0.0, 1.0, 2.5, 4.0]])


def test_a_user_law_sees_the_depth_already_worn():
    """`RateContext.worn_depth` is the profile the cycle wears on: an effect whose rate
    doubles per µm worn (a soft sublayer) multiplies each node's Archard rate by exactly
    1 + h_j/1 µm (one cycle's rates with and without it, same contact solution)."""
    from jaxwear._physics.config import ModelConfig
    from jaxwear._physics.cycle import cycle_rates, run_history
    from jaxwear.effects import Effect, EffectParameter, register_effect, unregister_effect

    class _Soft(Effect):
        name = "soft_sublayer_test"
        parameters = {"soft_gain": EffectParameter(1.0, 1.0, 0.0, 0.0, 5.0, "g [-]")}

        def local_rate(self, p, rate, ctx):
            return rate * (1 + p.effect_params["soft_gain"] * ctx.worn_depth[None, :] / 1e-6)

    try:
        register_effect(_Soft())
        p = jw.preset("rig", soft_gain=1.0)
        cfg = ModelConfig(nodes=16, steps_per_rev=24)
        hist = run_history(p, cfg)
        h = jnp.linspace(0.0, 3e-6, 16)
        base = cycle_rates(p, cfg, hist, 0, h, jnp.asarray(0.0))[0]
        soft = cycle_rates(p, cfg.replace(effects=("soft_sublayer_test",)), hist, 0, h,
                           jnp.asarray(0.0))[0]
    finally:
        unregister_effect("soft_sublayer_test")
    assert float(jnp.max(base)) > 0
    np.testing.assert_allclose(np.asarray(soft), np.asarray(base) * (1 + np.asarray(h) / 1e-6),
                               rtol=1e-12)


def test_swept_kernel_spreads_a_step_along_the_arc_the_load_turns_through():
    """Unit integral over the bore; a load at rest gives a narrow bump at its direction; a
    step in the middle of a 90° swing (30° per step) spreads over the 30° of arc that is its
    share, centred on its own direction (hand calculation of the mean and the spread of a
    uniform arc of 30° blurred by the bump's width)."""
    nodes = 720
    d = 2 * np.pi / nodes
    angle = jnp.asarray(np.radians([0.0, 0.0, 0.0, 30.0, 60.0, 90.0, 90.0, 90.0]))
    k = np.asarray(swept_kernel(angle, nodes))
    np.testing.assert_allclose(k.sum(axis=1) * d, 1.0, rtol=1e-9)
    theta = np.arange(nodes) * 360.0 / nodes
    rel = (theta + 180.0) % 360.0 - 180.0

    def moments(row, centre):
        x = (theta - centre + 180.0) % 360.0 - 180.0
        m = float(np.sum(row * x) * d)
        return m, math.sqrt(float(np.sum(row * (x - m) ** 2) * d))

    m0, s0 = moments(k[1], 0.0)  # at rest
    assert abs(m0) < 1e-6 and s0 == pytest.approx(5.0, rel=0.01)
    assert np.all(k[1][np.abs(rel) > 30.0] < 1e-4 * k[1].max())
    m4, s4 = moments(k[4], 60.0)  # the swing's middle: from 45° to 75°
    assert abs(m4) < 0.05
    assert s4 == pytest.approx(math.sqrt(5.0 ** 2 + 30.0 ** 2 / 12.0), rel=0.02)


def test_ar1_coefficient_from_second_differences():
    """White noise: no correction (φ = 0); AR(1) noise with φ = 0.5 along the scans: φ read
    from the lag-1 correlation of second differences within 3 of its standard errors, and
    prewhitening makes the noise white again (lag-1 correlation of the transformed rows
    near 0). The standard error is the correlation's (√(1.944/n)) over the slope of the
    closed form ρ(φ), by hand: ρ = (−4 + 7φ − 4φ² + φ³)/(6 − 8φ + 2φ²), −0.55 at φ = 0.5,
    slope 0.19: second differences see φ only weakly (n = 3 500 rows gave ±0.13)."""
    from jaxwear._core.noise import line_residuals

    rng = np.random.default_rng(5)
    x = np.arange(0.0, 360.0, 2.0)
    K = 400  # series (scans)

    def series(phi):
        e = rng.standard_normal(len(x))
        for i in range(1, len(x)):
            e[i] = phi * e[i - 1] + math.sqrt(1 - phi * phi) * e[i]
        return e

    def rho(p):
        return (-4 + 7 * p - 4 * p * p + p ** 3) / (6 - 8 * p + 2 * p * p)

    assert rho(0.0) == pytest.approx(-2 / 3) and rho(0.5) == pytest.approx(-0.55)
    for phi, expect in ((0.0, 0.0), (0.5, 0.5)):
        ys = [series(phi) for _ in range(K)]
        es, mids = [], []
        for k, y in enumerate(ys):
            e, mid = line_residuals(x, y)
            es.append(e)
            mids.append(mid + k * len(x))
        got, _ = lin.ar1_coefficient(np.concatenate(es), np.concatenate(mids))
        n = K * (len(x) - 3)
        slope = (rho(0.5 + 1e-4) - rho(0.5 - 1e-4)) / 2e-4
        se = math.sqrt(1.944 / n) / slope
        assert got == pytest.approx(expect, abs=3 * se), (phi, got, se)
        rows = [(np.arange(len(x)) + k * len(x), x, math.inf) for k in range(K)]
        w = lin.prewhiten(np.concatenate(ys)[:, None], rows, got, K * len(x))[:, 0]
        r = np.mean([np.corrcoef(w[k * len(x) + 1:(k + 1) * len(x) - 1],
                                 w[k * len(x) + 2:(k + 1) * len(x)])[0, 1] for k in range(K)])
        assert abs(r) < 3 * se + 0.01, (phi, r)


def test_penalty_choice_by_gcv_on_a_hand_made_case():
    """A smooth bump plus white noise on a B-spline basis, 10 noise draws: the penalty
    chosen by GCV gives a fit whose error to the truth is, in the median, within 1.5x of
    the best penalty on the grid (an oracle that knows the truth), and below both ends of
    the grid; pure noise is not significant, the bump is."""
    rng = np.random.default_rng(3)
    var = ShapeVariable("pressure_MPa", 12, tuple(np.linspace(0.0, 1.0, 33)))
    x = np.linspace(0.0, 1.0, 400)
    B = np.asarray(var.basis(jnp.asarray(x)))
    Z = lin.sum_zero(12)
    A = B @ Z
    A = A - A.mean(axis=0)  # the base model's column (a constant) projected off
    S = Z.T @ var.roughness() @ Z
    truth = 0.8 * np.exp(-0.5 * ((x - 0.6) / 0.12) ** 2)
    truth -= truth.mean()
    sm = lin.Smoother(A, S)
    ratios, chosen, ends = [], [], []
    for _ in range(10):
        y = truth + rng.standard_normal(len(x))
        yy = sm.U.T @ y
        i = int(sm.choose(sm.rss_drop(yy), np.asarray(float(y @ y)), len(x) - 1))
        errs = np.array([np.sum((A @ (inv @ (sm.AtU @ yy)) - truth) ** 2) for inv in sm.inv])
        ratios.append(errs[i] / errs.min())
        chosen.append(errs[i])
        ends.append((errs[0], errs[-1]))
    assert np.median(ratios) <= 1.5, ratios
    assert np.median(chosen) < 0.6 * np.min(np.median(ends, axis=0)), (chosen, ends)
    y = truth + rng.standard_normal(len(x))
    p_sig = lin.penalised_fit(A, S, y, len(x) - 1, math.inf, rng, 4000).p
    noise_only = rng.standard_normal(len(x))
    p_null = lin.penalised_fit(A, S, noise_only - noise_only.mean(), len(x) - 1, math.inf,
                               rng, 4000).p
    assert p_sig < 1e-3 < p_null


def test_sequential_null_p_value_agrees_with_the_full_simulation():
    """The null's p-value stops after 2000 draws where 20 or more exceeded T (Besag and
    Clifford): at T = 0 every draw exceeds (p = 1 from the first batch), far beyond the
    null none does (p = 1/(1 + 20000), the full budget), and at the 99th percentile of an
    independent simulation of 40 000 nulls it reads 0.01 within its binomial error."""
    var = ShapeVariable("pressure_MPa", 8, tuple(np.linspace(0.0, 1.0, 33)))
    x = np.linspace(0.0, 1.0, 300)
    Z = lin.sum_zero(8)
    A = np.asarray(var.basis(jnp.asarray(x))) @ Z
    A = A - A.mean(axis=0)
    sm = lin.Smoother(A, Z.T @ var.roughness() @ Z)
    n_res = len(x) - 1
    rng = np.random.default_rng(4)
    assert lin.null_p_value(sm, 0.0, n_res, 500.0, rng, 20000) == 1.0
    assert lin.null_p_value(sm, 1e9, n_res, 500.0, rng, 20000) == pytest.approx(1 / 20001)
    ref = lin._null_statistics(sm, n_res, 500.0, np.random.default_rng(99), 40000)
    T = float(np.quantile(ref, 0.99))
    ps = [lin.null_p_value(sm, T, n_res, 500.0, rng, 20000) for _ in range(5)]
    assert abs(np.mean(ps) - 0.01) < 3 * math.sqrt(0.01 * 0.99 / (5 * 2000)), ps


def test_explained_fraction_is_not_clipped_and_the_best_is_ranked_by_the_data():
    """Two variables that both 'explain all' of a small misfit: the shares are not clipped
    at 1, and the best is the one the data favour (larger share, then lower AIC), whatever
    the order they come in (it was the order of a dict)."""
    assert lin.explained(30.0, 2.0, 20.0, 500.0) == pytest.approx(1.4)
    assert lin.explained(1.0, 2.0, 20.0, 500.0) == 0.0
    from types import SimpleNamespace as V

    a = V(name="a", form="factor", significant=True, explained_fraction=1.4, aic=100.0)
    b = V(name="b", form="deposit", significant=True, explained_fraction=1.2, aic=90.0)
    c = V(name="c", form="factor", significant=False, explained_fraction=3.0, aic=10.0)
    for order in ([a, b, c], [c, b, a], [b, c, a]):
        assert choose_best(order)[0] is a
    tie = V(name="d", form="factor", significant=True, explained_fraction=1.4, aic=80.0)
    assert choose_best([a, tie])[0] is tie  # equal shares: the lower AIC


@pytest.fixture(scope="module")
def shaped():
    """A small rig study (1 experiment) and its model with every variable's correction in
    both forms."""
    res = jw.synthesize([], "paper", noise_um=0.3, seed=2, numerics=SMALL)
    study = res.study.with_experiments(res.study.experiments[:1])
    return Model(study, candidates=[], shape=make_basis(KNOTS, size=8))


def _correction_on(m, seed: int) -> np.ndarray:
    """u of `m` with every correction coefficient drawn: factors N(0, 0.1²), deposits
    |N(0, 0.003²)| (0.003 per coefficient adds ~10 µm to the base's 8; 1 wore through)."""
    u = np.zeros(len(m.names))
    rng = np.random.default_rng(seed)
    for var in m.ext.cfg.shape.variables:
        for k in var.keys():
            u[m.index[k]] = (0.1 * rng.standard_normal() if var.form == "factor"
                             else 0.003 * abs(rng.standard_normal()))
    return u


def test_correction_gradient_matches_central_differences(shaped):
    """d rows / d c of both forms through the wear loop (forward mode) against central
    finite differences of the rows themselves, at a point with the correction on."""
    m = shaped
    u = _correction_on(m, seed=0)
    ev = m.evaluate(u)
    assert float(ev.worn) < 0, "the test point must not wear through"
    for name in ("shape_pressure_MPa_05", "shape_cycle_phase_deg_03",
                 "shape_worn_depth_um_02",
                 "deposit_load_turn_rate_deg_per_s_06", "deposit_cycle_phase_deg_02"):
        i = m.index[name]
        # a step 3 % of the deposit's own size left O(h²) errors of 5e-5: 3e-4 of it
        # the worn depth feeds back on the rate through the quantile coordinate, which is
        # piecewise linear in z: a step of 1e-4 crossed its kinks (3e-4 off), 1e-5 not
        h = (1e-6 if name.startswith("deposit") else 1e-5 if "worn_depth" in name
             else 1e-4)
        up, um = u.copy(), u.copy()
        up[i] += h
        um[i] -= h
        fd = (m.predict(up) - m.predict(um)) / (2 * h)
        np.testing.assert_allclose(ev.J[:, i], fd, rtol=2e-5, atol=1e-7 * np.abs(fd).max())
        assert np.abs(fd).max() > 1e-4, name  # the coefficient moves the model


def test_packed_coefficients_are_the_same_correction(shaped):
    """The wear loop carries the ~140 coefficients as one array (`effects.shape.PACKED`,
    made by `batched_params`: a scalar each made the design's compilation ~1 s per
    variable); one cycle's rates with the coefficients packed equal those read one key at
    a time (`shape_terms`'s other path), both forms on."""
    import jax

    from jaxwear._core import pytree
    from jaxwear._physics.cycle import cycle_rates, run_history
    from jaxwear._physics.effects.shape import PACKED

    m = shaped
    rng = np.random.default_rng(1)
    u = np.zeros(len(m.names))
    for var in m.ext.cfg.shape.variables:
        for k in var.keys():
            u[m.index[k]] = (0.2 * rng.standard_normal() if var.form == "factor"
                             else 0.01 * abs(rng.standard_normal()))
    p = jax.tree.map(lambda x: x[0], m.ext.batched_params(jnp.asarray(u)))
    cfg = m.ext.cfg
    keys = cfg.shape.keys()
    eff = dict(p.effect_params)
    arr = eff.pop(PACKED)
    assert not any(k in eff for k in keys)  # packed only: no stale per-key values
    per_key = pytree.replace(p, effect_params={**eff, **{k: arr[i] for i, k in
                                                         enumerate(keys)}})
    hist = run_history(p, cfg)
    h = jnp.linspace(0.0, 2e-6, cfg.nodes)
    a = cycle_rates(per_key, cfg, hist, 0, h, jnp.asarray(50.0))[0]
    b = cycle_rates(p, cfg, hist, 0, h, jnp.asarray(50.0))[0]
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-13, atol=0.0)
    assert float(jnp.max(jnp.abs(a))) > 0


def test_batched_params_packs_the_packings_values(shaped):
    """The packed coefficients (one operation for every column, `residual.
    _packed_coefficients`) are the packing's values in SI, read on the host one column at
    a time (`Packing.values_np`), in every experiment; where some keys are held (not
    columns), their own values stay and the columns' are set."""
    from jaxwear._core import pytree
    from jaxwear._inference.residual import _packed_coefficients
    from jaxwear._physics.effects.shape import PACKED

    m = shaped
    u = _correction_on(m, seed=4)
    keys = m.ext.cfg.shape.keys()
    got = np.asarray(m.ext.batched_params(jnp.asarray(u)).effect_params[PACKED])
    vals = m.packing.values_np(u)
    want = np.array([vals[m.index[k]] * m.packing.columns[m.index[k]].to_si for k in keys])
    assert got.shape == (len(m.exp_names), len(keys))
    np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), rtol=1e-15, atol=0)
    assert np.abs(want).max() > 0
    # two keys held at values of their own (per key, as a study sets them), the rest columns
    n_exp = len(m.exp_names)
    held = {keys[0]: jnp.full((n_exp,), 0.25), keys[3]: jnp.full((n_exp,), -0.5)}
    eff = {k: v for k, v in m.ext.params.effect_params.items() if k != PACKED}
    p = pytree.replace(m.ext.params, effect_params={
        **eff, **held, **{k: jnp.zeros(n_exp) for k in keys if k not in held}})
    coefs = [(m.index[k], i) for i, k in enumerate(keys) if k not in held]
    out = _packed_coefficients(p, m.ext.cfg.shape, coefs, jnp.asarray(vals),
                               m.packing.columns, n_exp)
    arr = np.asarray(out.effect_params[PACKED])
    np.testing.assert_array_equal(arr[:, 0], 0.25)
    np.testing.assert_array_equal(arr[:, 3], -0.5)
    cols = [i for i, k in enumerate(keys) if k not in held]
    np.testing.assert_allclose(arr[:, cols], np.broadcast_to(want[cols], (n_exp, len(cols))),
                               rtol=1e-15, atol=0)
    assert not any(k in out.effect_params for k in keys)


def test_when_where_bands_jacobian_matches_forward_mode(shaped):
    """The map's marginals differentiated by central differences (`marginal_jacobian`,
    what the bands use) against forward-mode AD of the same function (`jax.jacfwd`), at a
    point with the correction on and a worn profile; held columns are left at 0."""
    import jax

    from jaxwear._analyses.diagnose.shape.map import map_parts, marginal_jacobian

    m = shaped
    u = _correction_on(m, seed=1)
    h = jnp.asarray(m.snapshots(u)[0, -1] * 1e-6)
    ext = m.ext.with_schedule(None)
    cols = [m.index[n] for n in ("K_d_per_Pa", "shape_pressure_MPa_05",
                                 "deposit_cycle_phase_deg_02")]
    Jw, Jr = marginal_jacobian(ext, u, 0, h, cols)
    (Aw, Ar) = jax.jacfwd(lambda v: map_parts(ext, v, 0, h)[0])(jnp.asarray(u))
    for J, A in ((Jw, np.asarray(Aw)), (Jr, np.asarray(Ar))):
        scale = np.max(np.abs(A[:, cols]))
        assert scale > 0
        np.testing.assert_allclose(J[:, cols], A[:, cols], atol=1e-6 * scale)
        held = np.setdiff1d(np.arange(len(u)), cols)
        assert np.all(J[:, held] == 0)


def test_all_coefficients_zero_is_the_model_as_written(shaped):
    """Nesting: with every coefficient 0 the corrected model is the base model exactly."""
    base = Model(shaped.study, candidates=[])
    np.testing.assert_array_equal(base.predict(np.zeros(len(base.names))),
                                  shaped.predict(np.zeros(len(shaped.names))))


@pytest.mark.slow
def test_worked_example_outside_the_library():
    """docs/effects.md's worked path on physics the library does not have (impact wear at
    the force reversals, from the independent generator at finer numerics): the shape says
    a deposit along the load's turn, made at the reversals; `missing_wear.py` loaded and
    calibrated lowers the error; the user's 20-line law does too."""
    ns = runpy.run_path(str(ROOT / "calibration" / "examples" / "shape_to_effect.py"))
    d, fitted, law, omega0 = ns["main"]([])
    s = d.shape
    assert s.form == "deposit", s.sentence
    assert s.best in ("load_turn_rate_deg_per_s", "load_turn_deg_per_deg",
                      "cycle_phase_deg"), s.sentence
    ww = s.when_where
    assert ww is not None and ww.share_at_reversals >= 0.5, ww.to_json()
    assert "missing_wear" in fitted.names[-1] or "missing_wear_gain" in fitted.names
    assert fitted.rmse_um < d.base.rmse - 0.01
    assert law.rmse_um < d.base.rmse - 0.01
    assert omega0 > 300.0  # the reversals: turn rates of thousands of deg/s


def test_joint_fit_survives_a_variable_the_projection_left_null():
    """A variable whose columns the base fit's projection removed (all zero) beside one
    that carries the misfit: the joint fit and each block's unique share are finite (two
    null studies of 124 at auto numerics raised "Singular matrix" here)."""
    rng = np.random.default_rng(5)
    n = 120
    x = np.linspace(0, 1, n)
    S = ShapeVariable("pressure_MPa", 6, tuple(np.linspace(0, 1, 9))).roughness()
    A1 = np.column_stack([np.exp(-((x - c) / 0.15) ** 2) for c in np.linspace(0, 1, 6)])
    rho = A1 @ rng.normal(size=6) * 3 + rng.standard_normal(n)
    fit, unique = lin.joint_fit([(A1, S), (np.zeros((n, 6)), S)], rho, n, math.inf, rng, 50)
    assert np.all(np.isfinite(fit.a)) and np.all(np.isfinite(unique))
    assert unique[1] == pytest.approx(0.0, abs=1e-6)  # the null block adds nothing
    assert unique[0] > 10.0
    # the solve itself, on what np.linalg.solve refuses
    H = np.diag([2.0, 0.0, 0.0])
    np.testing.assert_allclose(lin.psolve(H, np.array([4.0, 1.0, 0.0])), [2.0, 0.0, 0.0])
    np.testing.assert_allclose(lin.psolve(np.zeros((3, 3)), np.ones(3)), 0.0)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.solve(np.zeros((3, 3)), np.ones(3))
