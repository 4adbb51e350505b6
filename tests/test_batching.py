"""Batched control flow (`jaxwear._core.batching`) and the batched wear loop (issue 50):
under `jax.vmap` every lane gets the answer it gets alone."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

import jaxwear as jw
from jaxwear._core.batching import cond_any, in_chunks
from jaxwear._physics.wear import build_schedule, wear_loop


def _branchy(x, y):
    """A lane function with a data-dependent branch that closes over a traced value."""
    c = jnp.arange(3.0) * y

    def body(carry, k):
        return cond_any(carry > 1.0, lambda k, v: v * 2.0 + c.sum() + k,
                        lambda k, v: v - 0.25, k, carry), None

    return lax.scan(body, x, jnp.arange(3.0))[0]


def _by_hand(x, y):
    """`_branchy` in plain Python floats: the independent expectation."""
    for k in range(3):
        x = x * 2.0 + 3.0 * y + k if x > 1.0 else x - 0.25
    return x


@pytest.mark.parametrize("xs", [[0.0, 0.5, -1.0],  # no lane takes the branch
                                [2.0, 3.0, 1.5],  # every lane
                                [0.0, 2.0, 1.2, -3.0]])  # some
def test_cond_any_each_lane_its_own_branch(xs):
    y = 0.5
    want = [_by_hand(x, y) for x in xs]
    one = jax.jit(_branchy)
    assert [float(one(x, y)) for x in xs] == pytest.approx(want, rel=1e-15)
    got = jax.jit(jax.vmap(_branchy, in_axes=(0, None)))(jnp.asarray(xs), y)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-15)
    # a batched closure value (y per lane) and a vmap of a vmap
    ys = jnp.linspace(0.1, 0.9, len(xs))
    got2 = jax.jit(jax.vmap(jax.vmap(_branchy)))(jnp.asarray([xs, xs[::-1]]),
                                                 jnp.stack([ys, ys]))
    want2 = [[_by_hand(x, float(v)) for x, v in zip(row, ys)] for row in (xs, xs[::-1])]
    np.testing.assert_allclose(np.asarray(got2), want2, rtol=1e-15)


def test_cond_any_sequential():
    """`sequential` (lane by lane when every lane takes the branch) gives the same
    answers, the lanes mixed or not."""
    def f(x):
        return cond_any(x > 0, lambda v: jnp.sqrt(v), lambda v: -v, x, sequential=True)

    for xs, want in (([4.0, -1.0, 9.0], [2.0, 1.0, 3.0]), ([4.0, 16.0], [2.0, 4.0])):
        np.testing.assert_array_equal(np.asarray(jax.jit(jax.vmap(f))(jnp.asarray(xs))),
                                      want)


def test_in_chunks_pads_and_keeps_lanes():
    def f(x, w):
        return in_chunks(lambda x, w: (x * w, jnp.sum(x) + w), x, w, lanes=4)

    xs = jnp.arange(11 * 3, dtype=jnp.float64).reshape(11, 3)
    ws = jnp.arange(11, dtype=jnp.float64)
    a, b = jax.jit(jax.vmap(f))(xs, ws)  # 11 lanes: chunks of 4, the last padded
    np.testing.assert_array_equal(np.asarray(a), np.asarray(xs) * np.asarray(ws)[:, None])
    np.testing.assert_array_equal(np.asarray(b), np.asarray(xs).sum(1) + np.asarray(ws))
    a3, _ = jax.jit(jax.vmap(f, in_axes=(0, None)))(xs[:3], 2.0)  # fewer lanes than a chunk
    np.testing.assert_array_equal(np.asarray(a3), np.asarray(xs[:3]) * 2.0)


def test_vmapped_wear_loop_is_each_points_own():
    """A 20-point speed x clearance sweep under jit(vmap) (two chunks of the contact solve,
    the Newton iterations pooled over lanes; 72 steps, so the pooled second phase runs):
    every point's profile equals its own single call's to round-off and its Newton
    iteration count and residual are its own."""
    p = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=48, steps_per_rev=72)
    sched = build_schedule(p, cfg, revolutions=2000, M=200, pad=False)
    speed, clear = np.meshgrid(np.linspace(148.0, 276.0, 4) * 2 * np.pi / 60,
                               np.linspace(0.05, 0.15, 5) * 1e-3, indexing="ij")

    def point(s, c):
        r = wear_loop(p.with_values({"speed_rpm": s, "clearance_mm": c}), cfg, sched)
        return r.depth, r.max_iterations, r.max_residual

    one = jax.jit(point)
    singles = [one(s, c) for s, c in zip(speed.ravel(), clear.ravel())]
    batch = jax.jit(jax.vmap(point))(jnp.asarray(speed.ravel()), jnp.asarray(clear.ravel()))
    depth = np.stack([np.asarray(r[0]) for r in singles])
    np.testing.assert_allclose(np.asarray(batch[0]), depth, rtol=0,
                               atol=1e-13 * depth.max())
    assert [int(r[1]) for r in singles] == [int(i) for i in batch[1]]
    assert np.all(np.asarray(batch[2]) < 1e-9)
