"""Periodic linear interpolation on the bore: the one definition (the contact reads a worn
profile at the load's angle, synth reads a fine truth at a scan's angles, a forecast reads a
Jacobian at a finer level's nodes)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np


def interp_periodic(values, angle, *, axis: int = -1):
    """`values` at N equally spaced nodes θ_j = 2πj/N [rad] along `axis`, linearly
    interpolated at `angle` [rad] (any shape; the result has `angle`'s shape in place of the
    node axis). NumPy in, NumPy out; a JAX array (or a trace) in, JAX out."""
    xp = jnp if isinstance(values, jax.Array) or isinstance(angle, jax.Array) else np
    v = xp.moveaxis(xp.asarray(values), axis, -1)
    n = v.shape[-1]
    x = xp.mod(xp.asarray(angle) / (2 * math.pi) * n, n)
    i0 = xp.floor(x).astype(xp.int32) % n
    w = x - xp.floor(x)
    out = (1 - w) * v[..., i0] + w * v[..., (i0 + 1) % n]
    if axis == -1 or xp.ndim(angle) != 1:
        return out
    return xp.moveaxis(out, -1, axis if axis >= 0 else axis + v.ndim)
