"""Loop carries made ready for forward-mode tangents from the first trace.

Why: JAX differentiates a `lax.scan`/`while_loop`/`fori_loop` by tracing its body's JVP
until the set of carries with a tangent is stable (a fixpoint: a carry that starts at a
constant, e.g. a zero profile, has none until the body gives it one), and `jax.vmap` over
the tangents (a Jacobian by forward mode) does the same for which carries are batched.
Every pass traces the body again, and the passes of nested loops multiply: in the fits'
Jacobian program of a 5-experiment study the cycle's contact solve (a ~400-equation
body) was traced 4 times, the attempt loop's body twice, the crank-slider's load passes
twice (docs/performance.md, "Loop carries ready for tangents").

`ready(x, anchor)` returns `x` exactly (its primal program does not read `anchor`, so the
anchor is dead code there); its tangent is x's plus `0 * anchor`'s, a real (and, under the
vmap over tangents, batched) zero instead of JAX's symbolic one. With an anchor that
carries the tangent of every parameter that moves the loop (the sum of the parameters'
leaves), the carries that would have gained a tangent in the fixpoint have one from the
first pass: the same program in one trace. A carry marked that the loop never gives a
tangent would carry zeros (keep such carries, e.g. stop-gradient caches, unmarked); an
anchor without a live tangent leaves JAX's fixpoint as it was.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


@jax.custom_jvp
def _ready(x, anchor):
    return x


@_ready.defjvp
def _ready_jvp(primals, tangents):
    x, _ = primals
    dx, da = tangents
    return x, dx + jnp.zeros_like(x) * da


def anchor_of(tree) -> jax.Array:
    """A scalar whose tangent is live wherever any floating leaf of `tree` has one (its
    value is never used: `ready`'s primal ignores it)."""
    leaves = [jnp.sum(x) for x in jax.tree.leaves(tree)
              if jnp.issubdtype(jnp.result_type(x), jnp.floating)]
    return sum(leaves, jnp.zeros(()))


def ready(tree, anchor):
    """`tree` with every floating leaf ready for tangents (the module's docstring)."""
    return jax.tree.map(
        lambda x: _ready(x, anchor) if jnp.issubdtype(jnp.result_type(x), jnp.floating)
        else x, tree)
