"""One compiled program for the shape's surface columns and its refit (issue 50): a gated
shape basis (`effects.shape.ShapeBasis.gated`, terms switched by data) and a Jacobian
computed in parts of one program's width (`evaluation.evaluate`'s `width`).

Each check compares two ways to the same numbers: a term switched off against the model
built without it, and the Jacobian in parts against the same Jacobian in one run (and
that against central differences of the rows)."""

import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.diagnose import Model
from jaxwear._inference.evaluation import _evaluate_columns_jit, chunks, seeds
from jaxwear._physics.effects.shape import ShapeBasis, ShapeTensor, ShapeVariable

SMALL = dict(nodes=48, steps_per_rev=72, revolutions_per_update=500)
P_KNOTS = tuple(np.linspace(0.1, 4.0, 33))
V_KNOTS = tuple(np.linspace(0.005, 0.08, 33))


@pytest.fixture(scope="module")
def study():
    res = jw.synthesize([], "paper", noise_um=0.3, seed=2, numerics=SMALL)
    return res.study.with_experiments(res.study.experiments[:2])


def _terms():
    p = ShapeVariable("pressure_MPa", 6, P_KNOTS)
    v = ShapeVariable("sliding_speed_m_per_s", 6, V_KNOTS)
    t = ShapeTensor(ShapeVariable("pressure_MPa", 4, P_KNOTS),
                    ShapeVariable("sliding_speed_m_per_s", 4, V_KNOTS))
    return p, v, t


def _u(model, rng, keys, scale=0.2):
    u = np.zeros(len(model.names))
    for k in keys:
        u[model.index[k]] = scale * rng.standard_normal()
    return u


def test_terms_switched_off_are_the_model_built_without_them(study):
    """The gated model with the speed variable and the surface off, at coefficients that
    are not zero in them, predicts what the model with the pressure variable alone
    predicts, and its Jacobian in their columns is zero; switched on, they act."""
    p, v, t = _terms()
    gated = Model(study, candidates=[], shape=ShapeBasis((p, v), (t,), gated=(1, 2)))
    plain = Model(study, candidates=[], shape=ShapeBasis((p,)))
    rng = np.random.default_rng(0)
    u = _u(gated, rng, p.keys() + v.keys() + t.keys())
    u_plain = np.zeros(len(plain.names))
    for i, name in enumerate(plain.names):
        u_plain[i] = u[gated.index[name]]
    off = gated.with_terms_on([True, False, False])
    ev_off, ev_plain = off.evaluate(u), plain.evaluate(u_plain)
    np.testing.assert_allclose(ev_off.pred, ev_plain.pred, rtol=1e-13, atol=1e-13)
    for name in plain.names:
        np.testing.assert_allclose(ev_off.J[:, gated.index[name]],
                                   ev_plain.J[:, plain.index[name]], rtol=1e-10,
                                   atol=1e-12 * np.abs(ev_plain.J).max())
    held = [gated.index[k] for k in v.keys() + t.keys()]
    assert np.all(ev_off.J[:, held] == 0.0)
    # every term on (as built): the speed variable and the surface move the rows
    on = gated.evaluate(u)
    assert np.abs(on.pred - ev_off.pred).max() > 1e-3
    assert np.abs(on.J[:, held]).max() > 1e-3
    # a term without a switch cannot be off
    with pytest.raises(ValueError, match="without a switch"):
        gated.with_terms_on([False, True, True])


def test_a_jacobian_in_parts_is_the_jacobian_in_one_run(study):
    """The surface's columns and the carriers' (two column sets of one width, one
    program) in parts of that width equal the full Jacobian's, which equals central
    differences of the rows; the parts run one compiled program."""
    p, v, t = _terms()
    m = Model(study, candidates=[], shape=ShapeBasis((p, v), (t,), gated=(2,)))
    rng = np.random.default_rng(1)
    u = _u(m, rng, p.keys() + v.keys(), 0.1)
    full = m.evaluate(u)
    refit = [m.index[k] for k in ("K_d_per_Pa",) + p.keys() + v.keys()]
    surface = [m.index[k] for k in t.keys()]
    width = seeds(m.packing.columns, refit)[0].shape[1]
    assert len(chunks(m.packing.columns, surface, width)) == 2  # 16 columns, width 13
    before = _evaluate_columns_jit._cached._cache_size()
    for cols in (refit, surface):
        ev = m.with_jacobian_columns(cols, width).evaluate(u)
        np.testing.assert_array_equal(ev.pred, full.pred)
        np.testing.assert_allclose(ev.J[:, cols], full.J[:, cols], rtol=1e-12,
                                   atol=1e-13 * np.abs(full.J[:, cols]).max())
        rest = np.setdiff1d(np.arange(len(m.names)), cols)
        assert np.all(ev.J[:, rest] == 0.0)
    assert _evaluate_columns_jit._cached._cache_size() == before + 1
    # the surface's columns against central differences (one of them)
    i, h = m.index[t.keys()[5]], 1e-4
    up, um = u.copy(), u.copy()
    up[i] += h
    um[i] -= h
    fd = (m.predict(up) - m.predict(um)) / (2 * h)
    assert np.abs(fd).max() > 1e-4
    np.testing.assert_allclose(full.J[:, i], fd, rtol=2e-5, atol=1e-7 * np.abs(fd).max())


def test_chunks_share_tangents_across_experiments_and_respect_the_width(study):
    """Per-experiment columns (the clearances) share a tangent (`seeds`), so a part holds
    as many columns as fit its width in tangents, never more."""
    m = Model(study, candidates=[])
    cols = list(range(len(m.names)))
    for width in (1, 2, 3):
        parts = chunks(m.packing.columns, cols, width)
        assert sorted(j for part in parts for j in part) == cols
        assert all(seeds(m.packing.columns, part)[0].shape[1] <= width for part in parts)
