"""The one parser of numbers given on the command line (every verb's options, sweep ranges).

Every failure is an `InputError` (exit 2) naming the option and what was expected. Nothing
is computed from a value before it is known to be finite, so no numpy RuntimeWarning
(`100:inf:3` once printed "invalid value encountered in multiply" before its error).
"""

from __future__ import annotations

import math

import numpy as np

from jaxwear._core.errors import InputError

MAX_POINTS = 100_000  # values of one sweep axis (and grid points of one sweep)


def number(option: str, text, *, positive: bool = False, nonneg: bool = False,
           integer: bool = False, lo: float | None = None, hi: float | None = None):
    """`text` as a finite number (None stays None): `positive` > 0, `nonneg` >= 0, `integer`
    whole (returned as int), `lo`/`hi` open bounds."""
    if text is None:
        return None
    try:
        v = float(str(text).strip())
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{option}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{option}: expected a finite number, got {text!r}")
    if positive and not v > 0:
        raise InputError(f"{option}: expected a number > 0, got {text!r}")
    if nonneg and not v >= 0:
        raise InputError(f"{option}: expected a number >= 0, got {text!r}")
    if integer and v != int(v):
        raise InputError(f"{option}: expected a whole number, got {text!r}")
    if (lo is not None and not v > lo) or (hi is not None and not v < hi):
        raise InputError(f"{option}: expected a number in ({-math.inf if lo is None else lo:g}"
                         f", {math.inf if hi is None else hi:g}), got {text!r}")
    return int(v) if integer else v


def number_list(option: str, text, **checks) -> list:
    """A comma-separated list of numbers, each checked as by `number`."""
    items = [s.strip() for s in str(text).split(",") if s.strip()]
    if not items:
        raise InputError(f"{option}: expected a comma-separated list of numbers, got "
                         f"{text!r}")
    return [number(option, s, **checks) for s in items]


def parse_range(option: str, text: str) -> np.ndarray:
    """`START:STOP:COUNT` (inclusive, evenly spaced), `A,B,C` or a single value, in the
    option's unit. Negative values are fine here (`-0.05:0.1:3`); the physical checks
    (a clearance > 0) belong to the study."""
    text = str(text).strip()
    expected = (f"{option} {text!r}: expected START:STOP:COUNT (e.g. 100:300:21), a "
                f"comma-separated list or one value")
    if ":" in text:
        parts = text.split(":")
        if len(parts) != 3:
            raise InputError(expected)
        n = parts[2].strip()
        if not n.isdigit() or str(int(n)) != n:
            raise InputError(expected)
        count = int(n)
        if count < 1:
            raise InputError(expected)
        a, b = (_finite(option, text, s, expected) for s in parts[:2])
        if count > MAX_POINTS:
            raise InputError(f"{option} {text!r}: {count} values; at most {MAX_POINTS} per "
                             f"sweep")
        with np.errstate(all="ignore"):  # 1e308:-1e308:3 overflows: refused below
            vals = np.linspace(a, b, count)
        if not np.all(np.isfinite(vals)):
            raise InputError(f"{option} {text!r}: values must be finite")
        return vals
    items = text.split(",")
    if len(items) > MAX_POINTS:
        raise InputError(f"{option} {text!r}: {len(items)} values; at most {MAX_POINTS} per "
                         f"sweep")
    return np.array([_finite(option, text, s, expected) for s in items])


def _finite(option: str, text: str, item: str, expected: str) -> float:
    try:
        v = float(item.strip())
    except (ValueError, OverflowError):
        raise InputError(expected) from None
    if not math.isfinite(v):
        raise InputError(f"{option} {text!r}: values must be finite")
    return v
