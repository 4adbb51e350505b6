"""Numbers in JSON: the one helper that turns a float that is not finite into what JSON can hold."""

from __future__ import annotations

import math

import numpy as np


def _fmt(x):
    if type(x) is float:  # the common cell first: a 300 000-row table has millions
        return f"{x:.10g}"
    if isinstance(x, (float, np.floating)):
        return f"{float(x):.10g}"
    return x


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(type(o))


def json_float(x):
    """A number for JSON: float(x), or None for None, NaN and ±inf (JSON has no such
    numbers)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None
