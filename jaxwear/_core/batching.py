"""`cond_any`: a `lax.cond` whose batched form still branches (issue 50, batched sweeps).

Under `jax.vmap` a `lax.cond` whose predicate is batched becomes a `select` over both
branches: both run, every time, for every lane. Where one branch is the rare, expensive one
(the contact solve's fallback to a cold start: needed on a regime's first solve and when a
warm solve fails, skipped on every other update) the batched program runs it always: on a
16-lane sweep of the rig (120 x 120, 20 updates) that was more than half of the batched
program's time, and identical lanes ran 3.3x slower than 16 single calls
(benchmarks/RESULTS-kernel.md, 2026-11-29).

`cond_any(pred, true_fun, false_fun, *operands)` is `lax.cond(pred, ...)` unbatched. With
a batched `pred` it branches three ways on the lanes' predicates: none holds, `false_fun`
on all lanes (vmapped); all hold, `true_fun` on all lanes; some hold, each lane's own
branch, one lane after another (`lax.map` of an unbatched `lax.cond`: a rare branch costs
what it costs the lanes that take it, and no more). `sequential=True` runs the all-lanes
case one lane after another too: for a branch whose batched arrays (lanes x steps x
nodes) would not stay in the cache (the cold start at 256 lanes, 120 x 120: ~30 MB per
array). Each lane's answer is the one `lax.cond` gives it.

Restrictions: the operands carry no derivatives in reverse mode (`custom_vmap`, which
implements it, has no transpose rule): use it on `stop_gradient` data, e.g. inside iterative
solves whose derivatives come from the implicit function theorem. What the branches close
over is hoisted into operands first (a `custom_vmap` rule calls Python functions again
inside a later trace, where a closed-over tracer of the first one would be stale).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import lax
from jax.custom_batching import custom_vmap


def _hoisted(fun: Callable, ops: tuple):
    """`fun` as a function of (consts, ops) with nothing traced closed over, and its
    consts: what `fun` closes over, hoisted out of its program."""
    closed, shapes = jax.make_jaxpr(fun, return_shape=True)(*ops)
    tree = jax.tree.structure(shapes)

    def run(consts, ops):
        return jax.tree.unflatten(tree, jax.core.eval_jaxpr(closed.jaxpr, consts,
                                                            *jax.tree.leaves(ops)))

    return run, list(closed.consts)


def cond_any(pred, true_fun: Callable, false_fun: Callable, *operands,
             sequential: bool = False):
    """`lax.cond(pred, true_fun, false_fun, *operands)`; batched, a branch runs on the
    lanes that take it (module docstring). `pred`: a boolean scalar (per lane)."""
    t_fun, t_consts = _hoisted(true_fun, operands)
    f_fun, f_consts = _hoisted(false_fun, operands)
    return _cond_any(jnp.asarray(pred), t_fun, f_fun, (t_consts, f_consts, operands),
                     sequential)


def _cond_any(pred, t_fun, f_fun, args, sequential):
    """`cond_any` of branches `t_fun(consts, ops)`, `f_fun(consts, ops)` that close over
    nothing traced; `args` = (true consts, false consts, ops)."""

    def branches(a):
        return (lambda a: f_fun(a[1], a[2])), (lambda a: t_fun(a[0], a[2]))

    @custom_vmap
    def f(pred, args):
        return lax.cond(pred, *reversed(branches(args)), args)

    @f.def_vmap
    def rule(axis_size, in_batched, pred, args):
        pred_b, args_b = in_batched
        leaves, tree = jax.tree.flatten(args)
        flags = jax.tree.leaves(args_b)
        lanes = [x for x, b in zip(leaves, flags) if b]

        def rebuild(batched):  # args from a list of the batched leaves (whole or one lane's)
            it = iter(batched)
            return jax.tree.unflatten(tree, [next(it) if b else x
                                             for x, b in zip(leaves, flags)])

        def vmapped(which):
            fun = branches(args)[which]
            return lambda: jax.vmap(lambda ls: fun(rebuild(ls)), axis_size=axis_size)(lanes)

        def one_by_one(which=None):
            def lane(x):
                p, ls = x
                a = rebuild(ls)
                if which is not None:
                    return branches(a)[which](a)
                return lax.cond(p, *reversed(branches(a)), a)
            return lambda: lax.map(lane, (jnp.broadcast_to(pred, (axis_size,)), lanes))

        every = one_by_one(1) if sequential else vmapped(1)
        if not pred_b:
            out = lax.cond(pred, every, vmapped(0))
        else:
            case = jnp.where(jnp.all(pred), 2, jnp.where(jnp.any(pred), 1, 0))
            out = lax.switch(case, [vmapped(0), one_by_one(), every])
        return out, jax.tree.map(lambda _: True, out)

    return f(pred, args)


LANES = 16
"""Lanes per chunk of `in_chunks`: a 16-lane rig sweep (120 x 120) ran 1.2x faster per lane
than single calls, 256 lanes at once 0.8x (arrays of lanes x steps x nodes out of the
cache; benchmarks/RESULTS-kernel.md, 2026-11-29)."""


def in_chunks(fun: Callable, *operands, lanes: int = LANES):
    """`fun(*operands)`; batched, the lanes `lanes` at a time (`lax.map` over chunks, each
    chunk vmapped; the last chunk padded with repeats of the last lane), so that the
    batched arrays stay the size of a chunk's however wide the batch. The same
    restrictions as `cond_any` (no reverse-mode derivatives through the operands)."""
    run, consts = _hoisted(fun, operands)

    @custom_vmap
    def f(args):
        return run(*args)

    @f.def_vmap
    def rule(axis_size, in_batched, args):
        (flags,) = in_batched
        leaves, tree = jax.tree.flatten(args)
        flags = jax.tree.leaves(flags)
        if axis_size <= lanes:
            in_axes = jax.tree.unflatten(tree, [0 if b else None for b in flags])
            out = jax.vmap(lambda a: run(*a), in_axes=(in_axes,), axis_size=axis_size)(args)
            return out, jax.tree.map(lambda _: True, out)
        n = -(-axis_size // lanes)
        pad = n * lanes - axis_size

        def chunked(x):  # (B, ...) -> (n, lanes, ...), padded by repeating the last lane
            if pad:
                x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)])
            return x.reshape((n, lanes) + x.shape[1:])

        batched = [chunked(x) for x, b in zip(leaves, flags) if b]

        def chunk(ls):
            it = iter(ls)
            a = jax.tree.unflatten(tree, [next(it) if b else x for x, b in zip(leaves, flags)])
            in_axes = jax.tree.unflatten(tree, [0 if b else None for b in flags])
            return jax.vmap(lambda a: run(*a), in_axes=(in_axes,))(a)

        out = jax.tree.map(lambda x: x.reshape((n * lanes,) + x.shape[2:])[:axis_size],
                           lax.map(chunk, batched))
        return out, jax.tree.map(lambda _: True, out)

    return f((consts, operands))
