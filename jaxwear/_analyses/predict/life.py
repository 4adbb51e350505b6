"""Remaining life: where a forecast and its band cross the depth limit, and the points that
bring each crossing within its tolerance."""

from __future__ import annotations

import math

import numpy as np

from jaxwear._analyses.predict.result import Life, PredictResult
from jaxwear._physics.config import timed
from jaxwear._study.study import Study

# Life crossings are searched on the forecast grid. Maximum depth never decreases in time, so
# each crossing lies inside its grid bracket: the bracket's width bounds the life's numerical
# error (reported). The forecast is refined (as many new points inside each bracket as
# bring it within LIFE_RTOL of its crossing in one round, at most LIFE_REFINE_POINTS, up to
# LIFE_REFINE_ROUNDS times; the sampling methods re-forecast every draw each round) until
# every bracket is within LIFE_RTOL of its crossing. Measured on the boom with the 48-point
# grid alone (5.2 h steps across its 1 h fast / 4 h slow duty blocks): life 39.55 h
# [37.81, 41.42] against 40.54 h [40.13, 40.98] on a 0.1 h grid.
LIFE_RTOL = 0.005


LIFE_REFINE_POINTS = 24


LIFE_REFINE_ROUNDS = 3


LIFE_ROOM_ROUNDS = 2  # refinement rounds the fit's compiled layout holds (a third recompiles)


def crossing(t, y, limit):
    """(t_x, t_before, t_after): the first t at which y reaches `limit` (linear
    interpolation from (0, 0)) and the grid step it lies in; None if never. Non-finite y
    counts as reached at its point (the layer is worn through there)."""
    tt = np.concatenate([[0.0], t])
    yy = np.concatenate([[0.0], y])
    for k in range(1, len(tt)):
        if not np.isfinite(yy[k]):
            return float(tt[k]), float(tt[k - 1]), float(tt[k])
        if yy[k] >= limit:
            y0 = yy[k - 1]
            x = tt[k - 1] + (limit - y0) / (yy[k] - y0) * (tt[k] - tt[k - 1])
            return float(x), float(tt[k - 1]), float(tt[k])
    return None


def life_of(name, t, depth, lower, upper, limit, unit, horizon) -> Life:
    found = [crossing(t, y, limit) for y in (depth, upper, lower)]
    at, lo, hi = (None if c is None else c[0] for c in found)
    brackets = tuple((a, b, x) for x, a, b in filter(None, found))
    reason = None
    if at is None:
        reason = (f"the forecast does not reach {limit:g} µm within {LIFE_HORIZON:g}x the last "
                  f"measured count ({horizon:g} {unit})")
    elif hi is None:
        reason = (f"the lower band does not reach {limit:g} µm within {horizon:g} {unit}: "
                  f"no upper bound")
    return Life(name, float(limit), at, lo, hi, unit, reason,
                max((b - a for a, b, _ in brackets), default=None), brackets)


def _parts(a: float, b: float) -> int:
    """Equal parts of [a, b] each within LIFE_RTOL of any crossing in it (≥ a)."""
    return math.ceil((b - a) / (LIFE_RTOL * max(abs(a), 1e-300)) * (1 - 1e-12))


def _merged(pts: np.ndarray, new: np.ndarray, crank: bool) -> np.ndarray:
    """`pts` with the points `new` (whole revolutions for a crank-slider study), sorted and
    unique."""
    new = np.round(new) if crank else np.round(new, 6)
    return np.unique(np.concatenate([pts, new[new > 0]]))


def refine_count(a: float, b: float) -> int:
    """Points to add inside the bracket [a, b] so that each part is within LIFE_RTOL of any
    crossing in it (≥ a), at most LIFE_REFINE_POINTS: one round where that suffices (each
    round of a sampled forecast runs every draw again: ~185 s on the boom's importance
    posterior, which took three rounds of 8 points)."""
    return int(min(max(_parts(a, b) - 1, 1), LIFE_REFINE_POINTS))


def refined_points(study: Study, res: PredictResult, points: list[np.ndarray]):
    """`points` with `refine_count` more inside every life bracket wider than LIFE_RTOL of
    its crossing (whole revolutions for a crank-slider study); None when none is."""
    crank = not timed(study.config)
    out, more = [], False
    for pts, life in zip(points, res.life):
        new = [np.linspace(a, b, refine_count(a, b) + 2)[1:-1]
               for a, b, x in life.brackets if b - a > LIFE_RTOL * abs(x)]
        merged = _merged(pts, np.concatenate(new) if new else np.zeros(0), crank)
        more |= len(merged) > len(pts)
        out.append(merged)
    return out if more else None


def guided_points(study: Study, res: PredictResult, points: list[np.ndarray]):
    """`points` with a grid every LIFE_RTOL of the crossing over the span of each
    experiment's life brackets in `res` (a Laplace forecast's: the sampled band's crossings
    lie near its), where that takes at most LIFE_ROOM_ROUNDS x 3 x LIFE_REFINE_POINTS points
    (the room the layout keeps for refinements); None where no experiment gets any."""
    crank = not timed(study.config)
    out, more = [], False
    for pts, life in zip(points, res.life):
        if not life.brackets:
            out.append(pts)
            continue
        a, b = min(x[0] for x in life.brackets), max(x[1] for x in life.brackets)
        n = _parts(a, b)
        if not (a > 0 and 1 < n <= LIFE_ROOM_ROUNDS * 3 * LIFE_REFINE_POINTS):
            out.append(pts)
            continue
        merged = _merged(pts, np.linspace(a, b, n + 1)[1:-1], crank)
        more |= len(merged) > len(pts)
        out.append(merged)
    return out if more else None


LIFE_HORIZON = 10.0  # life is searched up to this multiple of the last measured count
