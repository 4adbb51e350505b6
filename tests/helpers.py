"""Small numerical helpers shared by the physics tests (no jaxwear code in here)."""

from __future__ import annotations

import numpy as np

MACHINE_EPS = float(np.finfo(np.float64).eps)


def fd_step(x: float, scale: float | None = None) -> float:
    """Central-difference step eps = sqrt(machine eps) * scale, scale = |x| by default.

    For a function evaluated to relative round-off ~1e-16 the central difference then has a
    truncation error ~eps² f''' and a round-off error ~1e-16 |f| / eps ≈ 1e-8 |f|, both far
    below the 1e-5 relative tolerance of the gradient tests.
    """
    scale = abs(x) if scale is None else abs(scale)
    if scale == 0.0:
        scale = 1.0
    return float(np.sqrt(MACHINE_EPS) * scale)


def central_fd(f, x, i: int | None = None, scale: float | None = None) -> float | np.ndarray:
    """Central finite difference of a scalar function `f` of a float64 vector (or scalar) `x`.

    `i` picks one component (returns a float); `i=None` returns the whole gradient.
    """
    x = np.array(x, dtype=np.float64)
    if x.ndim == 0:
        h = fd_step(float(x), scale)
        return (float(f(x + h)) - float(f(x - h))) / (2 * h)
    idx = range(x.size) if i is None else [i]
    out = []
    for j in idx:
        h = fd_step(float(x[j]), scale)
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        out.append((float(f(xp)) - float(f(xm))) / (2 * h))
    return out[0] if i is not None else np.array(out)


def wrap_deg(a):
    """Angle difference wrapped into [-180, 180) degrees."""
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def wrap_rad(a):
    """Angle wrapped into [-π, π)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def mirror_asymmetry(pressure, j0: int) -> float:
    """max_m |p[j0+m] - p[j0-m]| / max p: 0 for a pressure field symmetric about node j0."""
    p = np.asarray(pressure)
    n = p.shape[-1]
    m = np.arange(1, n // 2)
    top = np.max(p)
    if top == 0:
        return 0.0
    return float(np.max(np.abs(p[(j0 + m) % n] - p[(j0 - m) % n])) / top)


def node_angles(n: int) -> np.ndarray:
    """θ_j = 2πj/N [rad] (design.md §3)."""
    return 2 * np.pi * np.arange(n) / n


def random_profile(rng, nodes: int, peak: float, modes: int = 5) -> np.ndarray:
    """A smooth, random, non-negative wear profile [m] with maximum `peak`."""
    th = node_angles(nodes)
    h = np.zeros(nodes)
    for m in range(1, modes + 1):
        h += rng.normal() * np.cos(m * th + rng.uniform(0, 2 * np.pi)) / m
    h -= h.min()
    return h * (peak / h.max())


def conforming_groove(nodes: int, centre: float, clearance: float, depth: float) -> np.ndarray:
    """Wear groove a pin leaves when pressed `depth` past contact along `centre` [rad]:
    h_j = max(0, (c + depth) cos(θ_j - centre) - c)."""
    th = node_angles(nodes)
    return np.maximum((clearance + depth) * np.cos(th - centre) - clearance, 0.0)


class Loaded(BaseException):
    """Raised by the stand-in engines of `engines_stubbed` (conftest): the verb got past its
    input checks (a BaseException, so that no `except Exception` of a verb catches it)."""


THREE_EXPERIMENTS = ("n276-r10000", "n148-r10000", "n230-r10000-c010")


def paper_three(numerics):
    """The paper's rig matrix cut to three experiments (10⁴ revolutions each: 276 and
    148 r/min at 0.05 mm, 230 r/min at 0.10 mm) as conditions for `synthesize`: speed and
    clearance still vary, at about a third of the fits' cost. `numerics`: nodes,
    steps_per_rev, revolutions_per_update."""
    from jaxwear._analyses.synth import paper_conditions

    st = paper_conditions(numerics)
    return st.with_experiments([e for e in st.experiments if e.name in THREE_EXPERIMENTS])
