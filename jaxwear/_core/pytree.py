"""jaxwear's immutable pytrees (`Struct`, `field`) and the filtered jit under its programs
(`filter_jit`): arrays are traced, every other leaf is static.

Why not equinox's `Module` and `filter_jit`, which these replace with the same semantics:
`import equinox` took 0.18-0.31 s of a 1.0-1.2 s `import jaxwear` on the 2-core CI host
(its `nn`, `debug` and `internal` subpackages come with it), for every verb, where a frozen
dataclass registered as a pytree does what jaxwear's classes need (docs/performance.md,
"equinox off the import path"). equinox stays a dependency: optimistix, which the
least-squares core imports when a fit starts, is built on it, and an `eqx.Module` or
`eqx.filter_jit` of a user's works on these classes as on any pytree.

Semantics, as equinox's:
- a `Struct` subclass is a frozen dataclass; its fields are pytree children except those
  declared `field(static=True)` (hashable; part of the tree's structure, so a new value is
  a new compiled program);
- flattening and unflattening never call `__init__` (tracers, `None` or `object()`
  placeholders of JAX's transformations pass through);
- `==` compares structure and leaves; hashing hashes the leaves (an array leaf cannot be
  hashed, as in equinox);
- `filter_jit` traces array leaves (`jax.Array`, NumPy arrays and scalars) of the
  arguments and holds the others static (hashed: a new value compiles again); an output's
  non-array leaves come back as they were returned.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import numpy as np
from jax.tree_util import GetAttrKey


def field(*, static: bool = False, **kwargs) -> Any:
    """A `Struct` field (`dataclasses.field`'s arguments); `static=True`: held in the
    tree's structure, not a child (hashable)."""
    return dataclasses.field(metadata={"static": static}, **kwargs)


def _leaf_equal(a, b) -> bool:
    if a is b:
        return True
    if is_array(a) or is_array(b):
        if not (is_array(a) and is_array(b)):
            return False
        if isinstance(a, jax.core.Tracer) or isinstance(b, jax.core.Tracer):
            return False  # not decidable while tracing: unequal, as a new value would be
        return bool(np.shape(a) == np.shape(b) and np.array_equal(np.asarray(a), np.asarray(b)))
    return bool(a == b)


class Struct:
    """Base of jaxwear's parameter, model and result pytrees: every subclass (a user's
    effect too) becomes a frozen dataclass registered as a pytree (the module's docstring
    says which fields are children)."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        dataclasses.dataclass(frozen=True, eq=False)(cls)
        names = [f.name for f in dataclasses.fields(cls)]
        static = tuple(f.name for f in dataclasses.fields(cls) if f.metadata.get("static"))
        children = tuple(n for n in names if n not in static)
        keys = tuple(GetAttrKey(n) for n in children)

        def flatten_with_keys(x):
            return ([(k, getattr(x, n)) for k, n in zip(keys, children)],
                    tuple(getattr(x, n) for n in static))

        def flatten(x):
            return [getattr(x, n) for n in children], tuple(getattr(x, n) for n in static)

        def unflatten(aux, leaves):
            obj = object.__new__(cls)
            for n, v in zip(children, leaves):
                object.__setattr__(obj, n, v)
            for n, v in zip(static, aux):
                object.__setattr__(obj, n, v)
            return obj

        jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)

    def __eq__(self, other) -> bool:
        if type(self) is not type(other):
            return False
        a, ta = jax.tree.flatten(self)
        b, tb = jax.tree.flatten(other)
        return ta == tb and all(_leaf_equal(x, y) for x, y in zip(a, b))

    def __hash__(self) -> int:
        leaves, treedef = jax.tree.flatten(self)
        return hash((treedef, tuple(leaves)))


def replace(obj, **changes):
    """`obj` with some fields replaced (`dataclasses.replace`)."""
    return dataclasses.replace(obj, **changes)


def is_array(x) -> bool:
    """A leaf `filter_jit` traces: a JAX array (a tracer included), a NumPy array or scalar."""
    return isinstance(x, (jax.Array, np.ndarray, np.generic))


def partition(tree, pred: Callable = is_array):
    """(the leaves where `pred`, the others), each as `tree` with None elsewhere."""
    leaves, treedef = jax.tree.flatten(tree)
    return (treedef.unflatten([x if pred(x) else None for x in leaves]),
            treedef.unflatten([None if pred(x) else x for x in leaves]))


def combine(*trees):
    """The trees of `partition` merged (the first non-None leaf of each position)."""
    def first(*xs):
        return next((x for x in xs if x is not None), None)

    return jax.tree.map(first, *trees, is_leaf=lambda x: x is None)


class _Static:
    """A pytree with no children: carries a hashable value through `jax.jit` as its
    structure (an output's non-array leaves)."""

    def __init__(self, value):
        self.value = value


jax.tree_util.register_pytree_node(_Static, lambda s: ((), s.value),
                                   lambda value, _: _Static(value))


def _split(args):
    """(array leaves, hashable key: the structure, which leaves are arrays, the others)."""
    leaves, treedef = jax.tree.flatten(args)
    mask = tuple(is_array(x) for x in leaves)
    return ([x for x, m in zip(leaves, mask) if m],
            (treedef, mask, tuple(x for x, m in zip(leaves, mask) if not m)))


def _join(dynamic, key):
    treedef, mask, rest = key
    dyn, rest = iter(dynamic), iter(rest)
    return treedef.unflatten([next(dyn) if m else next(rest) for m in mask])


class FilterJit:
    """`jax.jit` of `fun` with array leaves traced and every other leaf static (the module's
    docstring). `lower` gives the `jax.stages.Lowered` whose `compile()` the calls with
    such arguments then use; `_cached` is the underlying `jax.jit` (`_cache_size()`)."""

    def __init__(self, fun: Callable, **jitkwargs):
        self.fun = fun

        def inner(dynamic, key):
            args, kwargs = _join(dynamic, key)
            out = fun(*args, **kwargs)
            dyn_out, out_key = _split(out)
            return dyn_out, _Static(out_key)

        # the program is named after `fun` (JAX names it after the function it jits): the
        # events and logs that say which program compiled read it (`_core.background.
        # lowered("_evaluate_jit")`), as do the persistent cache's keys
        inner.__name__ = getattr(fun, "__name__", "program")
        inner.__qualname__ = getattr(fun, "__qualname__", inner.__name__)
        inner.__module__ = getattr(fun, "__module__", None) or __name__

        self._cached = jax.jit(inner, static_argnums=1, **jitkwargs)
        functools.update_wrapper(self, fun)

    def __call__(self, *args, **kwargs):
        dynamic, key = _split((args, kwargs))
        dyn_out, out_key = self._cached(dynamic, key)
        return _join(dyn_out, out_key.value)

    def lower(self, *args, **kwargs):
        dynamic, key = _split((args, kwargs))
        return self._cached.lower(dynamic, key)


def filter_jit(fun: Callable, **jitkwargs) -> FilterJit:
    """`FilterJit(fun)`: jit with arrays traced, every other leaf static."""
    return FilterJit(fun, **jitkwargs)


def filter_eval_shape(fun: Callable, *args, **kwargs):
    """`jax.eval_shape` of `fun` with the non-array leaves of the arguments held static:
    the output's array leaves as `jax.ShapeDtypeStruct`s."""
    dynamic, key = _split((args, kwargs))

    def f(dynamic):
        a, kw = _join(dynamic, key)
        return fun(*a, **kw)

    return jax.eval_shape(f, dynamic)
