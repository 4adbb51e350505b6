"""Loop carries ready for forward-mode tangents (`_core.tangents`): the same values and
derivatives, and a loop body differentiated in one pass instead of JAX's fixpoint."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

import jaxwear as jw
from jaxwear._core import tangents


def _chain(x, mark):
    """A loop whose carries start at constants and gain x's tangent one per iteration
    (a -> b -> c): JAX's fixpoint needs a pass per link."""
    init = (jnp.zeros(()), jnp.zeros(3), jnp.zeros(()))
    if mark:
        init = tangents.ready(init, tangents.anchor_of(x))

    def body(i, c):
        a, b, cc = c
        return (a + jnp.sin(x[0]) * 0.5, b + a * x[1:] ** 2, cc + jnp.sum(b) * 0.1)

    a, b, cc = lax.fori_loop(0, 5, body, init)
    return jnp.concatenate([a[None], b, cc[None]])


def test_ready_changes_no_value_and_no_derivative():
    x = jnp.asarray([0.3, 1.2, -0.7, 2.0])
    np.testing.assert_array_equal(_chain(x, True), _chain(x, False))
    for d in (jax.jacfwd, jax.jacrev):
        np.testing.assert_array_equal(d(lambda x: _chain(x, True))(x),
                                      d(lambda x: _chain(x, False))(x))
    # and against central differences (the derivative itself, not only its equality)
    J = jax.jacfwd(lambda x: _chain(x, True))(x)
    eps = 1e-6
    for k in range(4):
        e = jnp.zeros(4).at[k].set(eps)
        fd = (_chain(x + e, True) - _chain(x - e, True)) / (2 * eps)
        np.testing.assert_allclose(J[:, k], fd, rtol=1e-6, atol=1e-9)
    # vmapped primal: the anchor is not read
    xs = jnp.stack([x, 2 * x])
    np.testing.assert_array_equal(jax.vmap(lambda x: _chain(x, True))(xs),
                                  jax.vmap(lambda x: _chain(x, False))(xs))


def _jvp_passes(f, x):
    """The distinct JVP traces of `_chain`'s loop body while tracing jacfwd(f) (JAX's
    internal `ad.jvp_jaxpr`, one call per fixpoint pass)."""
    ad = pytest.importorskip("jax._src.interpreters.ad")
    loops = pytest.importorskip("jax._src.lax.control_flow.loops")
    if not hasattr(ad, "jvp_jaxpr") or getattr(loops, "ad", None) is not ad:
        pytest.skip("JAX's loop JVP internals moved")
    seen = set()
    orig = ad.jvp_jaxpr

    def spy(jaxpr, nonzeros, instantiate):
        if any(e.primitive.name == "sin" for e in jaxpr.jaxpr.eqns):  # the loop's body
            seen.add((id(jaxpr), tuple(nonzeros)))
        return orig(jaxpr, nonzeros, instantiate)

    ad.jvp_jaxpr = spy
    try:
        jax.make_jaxpr(jax.jacfwd(f))(x)
    finally:
        ad.jvp_jaxpr = orig
    return len(seen)


def test_a_loop_body_is_differentiated_in_one_pass():
    x = jnp.asarray([0.3, 1.2, -0.7, 2.0])
    assert _jvp_passes(lambda x: _chain(x, False), x) == 3  # a pass per carry gaining one
    assert _jvp_passes(lambda x: _chain(x, True), x) == 1


def test_the_wear_loops_jacobians_are_those_of_the_unmarked_loops(monkeypatch):
    # the rig's adaptive loop and eq 23 at a coarse grid: forward-mode Jacobians in (K_d,
    # clearance) bit for bit those of the same loops with the marks taken out (JAX's
    # fixpoint), and eq 23's against central differences
    from jaxwear._physics.wear import build_schedule, wear_loop

    p = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=32, steps_per_rev=24)
    x = jnp.asarray([float(p.get("K_d_per_Pa")), float(p.get("clearance_mm"))])
    for kw in ({}, {"M": 500}):
        sched = build_schedule(p, cfg, revolutions=4000, **kw)

        def depth(x, sched=sched):
            q = p.with_values({"K_d_per_Pa": x[0], "clearance_mm": x[1]})
            return wear_loop(q, cfg, sched).depth * 1e6

        J = jax.jacfwd(depth)(x)
        with monkeypatch.context() as m:
            m.setattr(tangents, "ready", lambda tree, anchor: tree)
            # the same operations on the same values; XLA may fuse the first step's
            # tangent additions (a real zero where JAX's was symbolic) otherwise: round-off
            np.testing.assert_allclose(J, jax.jacfwd(depth)(x), rtol=1e-13, atol=0)
        if kw:  # fixed steps: the derivative of the run itself
            for k, eps in ((0, 1e-6 * x[0]), (1, 1e-6 * x[1])):
                e = jnp.zeros(2).at[k].set(eps)
                fd = (depth(x + e) - depth(x - e)) / (2 * eps)
                np.testing.assert_allclose(J[:, k], fd, rtol=1e-5,
                                           atol=1e-5 * float(jnp.max(jnp.abs(fd))))
