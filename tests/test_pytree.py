"""jaxwear's own pytrees and filtered jit (`_core.pytree`), which replaced equinox's on the
import path: the semantics its classes rely on."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._core import pytree


class Box(pytree.Struct):
    a: object
    b: object = None
    tag: str = pytree.field(static=True, default="x")


def test_children_and_static_fields():
    box = Box(jnp.ones(2), 3.0, tag="t")
    leaves, tree = jax.tree.flatten(box)
    assert len(leaves) == 2 and leaves[1] == 3.0
    # the static field is the structure: another value, another tree
    assert tree != jax.tree.structure(Box(jnp.ones(2), 3.0, tag="u"))
    assert tree == jax.tree.structure(Box(jnp.zeros(2), 4.0, tag="t"))
    with pytest.raises(dataclasses.FrozenInstanceError):
        box.a = 1
    # tree paths name the fields
    paths = [jax.tree_util.keystr(k) for k, _ in jax.tree_util.tree_flatten_with_path(box)[0]]
    assert paths == [".a", ".b"]


def test_unflatten_does_not_call_init():
    calls = []

    class Checked(pytree.Struct):
        x: object

        def __post_init__(self):
            calls.append(1)
            if not isinstance(self.x, (float, jax.Array)):
                raise TypeError("x")

    c = Checked(1.0)
    assert calls == [1]
    # vmap's and the tree utilities' placeholders pass through unflattening
    assert jax.tree.map(lambda _: object(), c) is not None
    assert jax.vmap(lambda c: c.x * 2)(Checked(jnp.arange(3.0))).shape == (3,)
    assert calls == [1, 1]


def test_equality_and_replace():
    a, b = Box(np.arange(3.0), 1.0), Box(np.arange(3.0), 1.0)
    assert a == b and a is not b
    assert a != Box(np.arange(3.0), 2.0)
    assert a != Box(np.arange(3.0), 1.0, tag="y")
    assert a != Box(np.arange(4.0), 1.0)
    c = pytree.replace(a, b=5.0)
    assert c.b == 5.0 and a.b == 1.0 and c.tag == "x"


def test_filter_jit_traces_arrays_and_holds_the_rest_static():
    traced = []

    def f(box, k, scale):
        traced.append(1)
        return {"y": box.a * k * scale, "k": k, "name": box.tag}

    g = pytree.filter_jit(f)
    out = g(Box(jnp.ones(3)), 2, np.float64(3.0))
    assert out["k"] == 2 and isinstance(out["k"], int) and out["name"] == "x"
    np.testing.assert_array_equal(out["y"], 6.0)
    # new array values (a NumPy scalar is an array): no new trace
    g(Box(2 * jnp.ones(3)), 2, np.float64(4.0))
    assert len(traced) == 1 and g._cached._cache_size() == 1
    # a new static value, a new static field: new programs
    g(Box(jnp.ones(3)), 3, np.float64(1.0))
    g(Box(jnp.ones(3), tag="z"), 3, np.float64(1.0))
    assert len(traced) == 3 and g._cached._cache_size() == 3


def test_lowered_ahead_is_the_program_calls_use():
    compiled = []

    def listen(event, duration, **kw):
        if event.endswith("backend_compile_duration"):
            compiled.append(event)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        g = pytree.filter_jit(lambda box: jnp.sum(box.a) * 1.5)
        g.lower(Box(np.ones(4))).compile()
        assert len(compiled) == 1
        assert float(g(Box(np.arange(4.0)))) == 9.0
        assert len(compiled) == 1  # the call ran what was compiled ahead
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def test_partition_combine_and_eval_shape():
    tree = {"a": jnp.ones(2), "b": 3, "c": (np.zeros(1), "s")}
    dyn, static = pytree.partition(tree)
    assert jax.tree.leaves(static) == [3, "s"]
    assert pytree.combine(dyn, static)["b"] == 3
    out = pytree.filter_eval_shape(lambda t, n: jnp.tile(t["a"], n), tree, 4)
    assert out.shape == (8,)


def test_a_users_effect_with_a_field_is_a_pytree():
    class Gain(jw.Effect):
        name = "test_pytree_gain"
        factor: float = 2.0

    g = Gain()
    assert jax.tree.leaves(g) == [2.0]
    assert jax.tree.map(lambda x: x * 2, g).factor == 4.0
    assert Gain.name == "test_pytree_gain"


def _lowered_names(f, *args):
    names = []

    def listen(event, duration, **kw):
        if event.endswith("jaxpr_to_mlir_module_duration"):
            names.append(str(kw.get("fun_name")))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        f(*args)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return names


def test_a_program_is_named_after_its_function():
    # what `_core.background.lowered("_evaluate_jit")` and the logs read
    def a_program_name(box):
        return box.a + 1.0

    names = _lowered_names(pytree.filter_jit(a_program_name), Box(np.ones(2)))
    assert names == ["jit(a_program_name)"]


def test_the_background_sees_the_evaluation_program_lowered():
    from jaxwear._core import background
    from jaxwear._core.jit import jit

    @jit
    def _evaluate_jit_probe(box):
        return jnp.sum(box.a)

    ev = background.lowered("_evaluate_jit")
    try:
        _evaluate_jit_probe(Box(np.arange(3.0)))
        assert ev.wait(5.0)
    finally:
        background.forget(ev)
