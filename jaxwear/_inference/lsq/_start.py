"""The robust start: bring the scale parameter (ln K_d) to the data before iterating."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from jaxwear._core.errors import TrialFailed
from jaxwear._inference.lsq._point import Point


def _elasticity(pt: Point, k: int) -> float:
    """β = d ln(depth) / d ln K_d from the point's Jacobian (least squares over the rows),
    within [0.25, 2]; 1 where the Jacobian does not say (a column not computed, or β not
    positive). Why: wear widens the contact, so depth grows more slowly than K_d, and a
    rescale by the factor a alone falls short (the boom from the study's K_d: x14.9, then
    x1.64, x1.04, three evaluations; with β, 0.74 there: x37.8, then x0.676, two)."""
    d = np.asarray(pt.predicted, np.float64)
    Jk = np.asarray(pt.J, np.float64)[:, k] if np.ndim(pt.J) == 2 else np.zeros(0)
    dd = float(d @ d)
    if Jk.shape != d.shape or not dd > 0:
        return 1.0
    beta = float(d @ Jk) / dd
    # a column not computed (zero) or not positive says nothing about the scale
    if not (math.isfinite(beta) and beta > 0.05):
        return 1.0
    return min(max(beta, 0.25), 2.0)


def robust_start(evaluate: Callable[[np.ndarray], Point], u, scale_index: int | None, *,
                 measured: np.ndarray, log: Callable[[str], None] | None = None,
                 max_reductions: int = 8, rescales: int = 3):
    """Depth is nearly proportional to K_d, so a start far off is first brought in line:

    1. while the model is not usable (worn through, not finite), ln K_d -= ln 10;
    2. K_d times the least-squares factor a = Σ m·d / Σ d·d between measured m and
       predicted d, to the power 1/β (β: depth's elasticity in K_d from the Jacobian,
       `_elasticity`), repeated while |ln a| > 2 %, at most `rescales` times.

    `scale_index`: the index of ln K_d in u (None: step 1 and 2 are skipped).
    Returns (u, point, evaluations, why) with `why` None on success, else the reason the
    model cannot be evaluated at any reduced start (its cause included). An evaluation that
    raises `TrialFailed` counts as not usable (its point is then None where the last one
    raised); the rescale's trials, as a fit's, are rejected when they fail.
    """
    u = np.array(u, np.float64)

    def attempt(v):
        try:
            p = evaluate(v)
            return p, (None if p.usable else p.why or "worn through or not finite")
        except TrialFailed as e:
            return None, str(e) or type(e).__name__

    pt, cause = attempt(u)
    evals = 1
    tries = 0
    while cause is not None:
        if scale_index is None or tries >= max_reductions:
            why = "the model is not usable at the start values"
            if scale_index is not None:
                why += f" even with K_d reduced {10 ** max_reductions:.0e}-fold"
            return u, pt, evals, f"{why} ({cause})"
        u[scale_index] -= math.log(10.0)
        tries += 1
        if log:
            log(f"  start: not usable ({cause}); K_d / 10")
        pt, cause = attempt(u)
        evals += 1
    if scale_index is None:
        return u, pt, evals, None
    meas = np.asarray(measured, np.float64)
    for _ in range(rescales):
        d = pt.predicted
        dd = float(d @ d)
        if not dd > 0:
            break
        a = float(d @ meas) / dd
        if not (a > 0 and math.isfinite(a)) or abs(math.log(a)) < 0.02:
            break
        trial = u.copy()
        trial[scale_index] += math.log(a) / _elasticity(pt, scale_index)
        a = math.exp(trial[scale_index] - u[scale_index])
        pt_t, cause = attempt(trial)
        evals += 1
        if cause is not None:
            if log:
                log(f"  start: K_d x{a:.3g} not usable ({cause}); kept")
            break
        u, pt = trial, pt_t
        if log:
            log(f"  start: K_d rescaled x{a:.3g} to the data")
    return u, pt, evals, None
