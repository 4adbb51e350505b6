"""Batched model evaluations sharded over devices and processes (`jax.sharding`).

A sweep or a multi-experiment evaluation is a batch of independent points. `sharded_vmap`
splits the batch over a 1-D device mesh (axis `"points"`), one contiguous block of points
per device, and evaluates each block with `jax.vmap` (or `lax.map`) of the point function.
Under `jax.distributed` the mesh spans the devices of every process, so the same call runs
a batch across processes or hosts (docs/scaling.md); there is no job scheduler of our own.

Why `shard_map` and not `jit(vmap(fn))` on sharded inputs: the wear loop is full of
`while_loop`s (Newton iterations) whose stop test, once batched, is "any lane still
working". Partitioned by the compiler, that test is a reduction over the sharded batch axis:
an all-reduce per iteration that keeps every device in lockstep. Inside `shard_map` each
device batches only its own points, so its loops stop when its own points converge, and
no device ever waits for another until the results are gathered.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxwear._core import pytree
from jaxwear._core.jit import jit

AXIS = "points"
METHODS = ("vmap", "map")


def points_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh named `"points"` over `devices` (default: all devices of all processes)."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("points_mesh: devices must not be empty")
    return Mesh(np.asarray(devices), (AXIS,))


def _check_method(method: str):
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def _batch_size(leaves, where: str) -> int:
    if not leaves:
        raise ValueError(f"{where}: batched_args has no arrays to batch over")
    sizes = {np.shape(x)[0] if np.ndim(x) else None for x in leaves}
    if None in sizes or len(sizes) != 1:
        raise ValueError(f"{where}: every batched array needs the same leading (batch) axis; "
                         f"got leading sizes {sorted(s for s in sizes if s is not None)}"
                         + (" and a scalar" if None in sizes else ""))
    (n,) = sizes
    if n == 0:
        raise ValueError(f"{where}: the batch is empty")
    return n


def _local(fn: Callable, method: str) -> Callable:
    """The function one device runs on its block of points."""
    if method == "vmap":
        return jax.vmap(fn)
    return lambda *args: lax.map(lambda a: fn(*a), args)


def sharded_fn(fn: Callable, *, devices: Sequence[jax.Device] | None = None,
               method: str = "vmap") -> Callable:
    """`fn` batched over the leading axis of its arguments and sharded over `devices`.

    Traceable (use it inside `jit`, `jacfwd`, `grad`): the batch is padded to a multiple of
    the device count by repeating its last point, each device evaluates its block with
    `method` (`"vmap"`: one batched computation; `"map"`: `lax.map`, one point after another,
    usually faster on CPU, where batching the contact solver's while loops makes every lane
    wait for the slowest), and the padding is stripped. In a multi-process run the
    arguments must be global arrays (use `sharded_vmap`, which builds them).

    **Arguments:**
    - `fn`: point function, `fn(*args) -> pytree of arrays`.
    - `devices`: devices of the `"points"` mesh (default: all).
    - `method`: `"vmap"` or `"map"`.

    **Returns:** `g(*batched_args)` → `fn`'s outputs stacked on a leading axis of the batch's
    length.
    """
    _check_method(method)
    mesh = points_mesh(devices)
    n_dev = mesh.devices.size
    # check_vma=False: the point function is arbitrary user code (equinox modules, closed-over
    # constants); it uses no collectives, so there is no replication to verify.
    body = jax.shard_map(_local(fn, method), mesh=mesh, in_specs=P(AXIS), out_specs=P(AXIS),
                         check_vma=False)

    def g(*batched_args):
        n = _batch_size(jax.tree.leaves(batched_args), "sharded_fn")
        pad = -n % n_dev
        if pad:
            # Repeat a real point: padded lanes then run valid physics (zeros could be a
            # zero clearance or speed, i.e. NaNs or a worn-through layer) and are dropped.
            batched_args = jax.tree.map(
                lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), batched_args)
        out = body(*batched_args)
        return jax.tree.map(lambda y: y[:n], out) if pad else out

    return g


@functools.lru_cache(maxsize=64)
def _compiled(fn: Callable, devices: tuple, method: str):
    """One compiled, sharded function per (point function, devices, method), reused by
    every chunk of a batch and by later calls with the same `fn`.

    Returns `(call, sharding)`: `call(broadcast_args, batched_args)` evaluates
    `fn(*broadcast_args, *point)` for every point; array leaves of `broadcast_args` are
    traced and replicated (new values do not recompile), other leaves are static.
    """
    mesh = points_mesh(devices)

    @jit
    def call(broadcast_args, batched_args):
        dynamic, static = pytree.partition(broadcast_args, pytree.is_array)

        def local(dynamic, batched):
            fixed = pytree.combine(dynamic, static)
            return _local(lambda *point: fn(*fixed, *point), method)(*batched)

        return jax.shard_map(local, mesh=mesh, in_specs=(P(), P(AXIS)), out_specs=P(AXIS),
                             check_vma=False)(dynamic, batched_args)

    return call, NamedSharding(mesh, P(AXIS))


def _place(x: np.ndarray, sharding: NamedSharding) -> jax.Array:
    """A global array with `sharding`, built from a host array that every process holds in
    full (each process fills only the blocks of its own devices)."""
    return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])


def _replicate(tree, mesh: Mesh):
    """Array leaves of `tree` as global arrays replicated over `mesh`; other leaves as is."""
    replicated = NamedSharding(mesh, P())
    return jax.tree.map(lambda x: _place(np.asarray(x), replicated) if pytree.is_array(x) else x,
                        tree)


def _to_host(y: jax.Array) -> np.ndarray:
    if jax.process_count() > 1 and not y.is_fully_addressable:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(y, tiled=True))
    return np.asarray(y)


def sharded_vmap(fn: Callable, batched_args: tuple, *, broadcast_args: tuple = (),
                 devices: Sequence[jax.Device] | None = None, chunk: int | None = None,
                 method: str = "vmap"):
    """Evaluate `fn` at every point of a batch, sharded over all devices (and processes).

    Like `jax.vmap(fn)(*batched_args)`, but: the batch is padded to a multiple of the device
    count (repeating its last point), placed with a `NamedSharding` over the 1-D `"points"`
    mesh, evaluated by one compiled `shard_map` of `jax.vmap(fn)` (or `lax.map`, see
    `method`), and the padding stripped. With `chunk`, at most `chunk` points per device are
    evaluated per call (bounded memory; every chunk reuses one compilation).

    Under `jax.distributed` every process calls this with the same full host batch; each
    computes the points on its own devices and all processes receive the whole result.

    **Arguments:**
    - `fn`: point function `fn(*args) -> pytree of arrays`. Keep the same function object
      across calls (not a fresh lambda) to reuse its compilation.
    - `batched_args`: tuple of `fn`'s positional arguments, each a pytree of arrays with a
      common leading batch axis of length B.
    - `broadcast_args`: tuple of arguments passed first to `fn` at every point, e.g.
      `(params, cfg, schedule)`: array leaves are replicated on every device and traced (new
      values reuse the compilation); other leaves (a `ModelConfig`, strings, and Python
      numbers, so pass numbers that change between calls as arrays) are static.
    - `devices`: mesh devices (default `jax.devices()`: all devices of all processes).
    - `chunk`: points per device per call (default: the whole batch in one call).
    - `method`: `"vmap"` (default) or `"map"` (`lax.map` per device: on CPU usually faster
      for the wear loop, see `sharded_fn`).

    **Returns:** `fn`'s outputs stacked along a leading axis of length B, as NumPy arrays
    (gathered to the host, on every process).
    """
    _check_method(method)
    if not isinstance(batched_args, tuple):
        raise TypeError("sharded_vmap: batched_args must be a tuple of fn's positional "
                        f"arguments, got {type(batched_args).__name__}")
    if chunk is not None and (not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"sharded_vmap: chunk must be a positive integer, got {chunk!r}")
    if not isinstance(broadcast_args, tuple):
        raise TypeError("sharded_vmap: broadcast_args must be a tuple, got "
                        f"{type(broadcast_args).__name__}")
    devs = tuple(jax.devices() if devices is None else devices)
    call, sharding = _compiled(fn, devs, method)
    fixed = _replicate(broadcast_args, sharding.mesh)
    host = jax.tree.map(np.asarray, batched_args)
    n = _batch_size(jax.tree.leaves(host), "sharded_vmap")
    n_dev = len(devs)
    per_call = n_dev * (chunk if chunk is not None else math.ceil(n / n_dev))
    calls = math.ceil(n / per_call)
    pad = calls * per_call - n
    if pad:
        host = jax.tree.map(lambda x: np.concatenate([x, np.repeat(x[-1:], pad, 0)]), host)
    pieces = []
    for c in range(calls):
        part = jax.tree.map(lambda x: _place(x[c * per_call:(c + 1) * per_call], sharding),
                            host)
        pieces.append(jax.tree.map(_to_host, call(fixed, part)))
    out = pieces[0] if calls == 1 else jax.tree.map(lambda *ys: np.concatenate(ys), *pieces)
    return jax.tree.map(lambda y: y[:n], out) if pad else out
