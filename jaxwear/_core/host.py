"""Host values onto the device without a compilation.

`jnp.asarray` of a NumPy array or a Python list, with or without a dtype, compiles a small
program for every new shape and dtype (jax 0.10: `jit(stage)` or
`jit(convert_element_type)`, 10-40 ms each on the 2-core CPU host), and building a fit's
model made ~40 of them per answer (schedules, padding, stacking, the measured rows).
`jax.device_put` of a NumPy array is a plain copy: the same values, dtype and (strong)
type, no compilation. Here only for values known on the host; a traced value goes through
`jnp.asarray` as before.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def to_device(x, dtype=None) -> jax.Array:
    """`jnp.asarray(x, dtype)` of a host value (NumPy array or scalar, Python number or
    nested list) by `jax.device_put`: no compilation. The result is not weakly typed, as
    `jnp.asarray` with a dtype or of a NumPy array (a Python scalar without a dtype would
    be weakly typed there: give the dtype). A JAX array or tracer goes to `jnp.asarray`."""
    if isinstance(x, jax.Array) or isinstance(x, jax.core.Tracer):
        return jnp.asarray(x, dtype)
    return jax.device_put(np.asarray(x, dtype))


def stack(xs) -> jax.Array:
    """`jnp.stack(xs)` of concrete, strongly typed arrays on the host (no compilation);
    weakly typed or traced ones through `jnp.stack` (its result's type)."""
    if all(isinstance(x, np.ndarray | np.number)
           or (isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer)
               and not getattr(x, "weak_type", False)) for x in xs):
        return jax.device_put(np.stack([np.asarray(x) for x in xs]))
    return jnp.stack(xs)
