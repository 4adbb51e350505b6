"""The Gauss-Newton covariance, with the directions the data leave undetermined flagged."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# An eigenvalue of the whitened JᵀJ below this fraction of the largest is a null direction:
# a parameter with a component along it has no standard error (a pseudo-inverse alone would
# give it a zero variance, i.e. claim it is known exactly).
NULL_RTOL = 1e-10


@dataclass(frozen=True)
class Covariance:
    """`cov` (k, k): covariance of the free u (inverse of the whitened JᵀJ on its range);
    `undetermined` (k,): u along a null direction of JᵀJ; `se` (k,): standard errors of u
    (inf where undetermined); `null_directions` (k, d): an orthonormal basis of the null
    space."""

    cov: np.ndarray
    undetermined: np.ndarray
    se: np.ndarray
    null_directions: np.ndarray


def covariance(Jw: np.ndarray) -> Covariance:
    """Covariance of u from the whitened Jacobian `Jw` (rows, k): data rows divided by the
    noise level, prior rows in units of their standard deviation."""
    Jw = np.asarray(Jw, np.float64)
    k = Jw.shape[1]
    if not np.all(np.isfinite(Jw)):
        return Covariance(np.full((k, k), np.nan), np.ones(k, bool), np.full(k, np.inf),
                          np.eye(k))
    A = Jw.T @ Jw
    w, V = np.linalg.eigh(A)
    null = w <= NULL_RTOL * max(float(np.max(w, initial=0.0)), 1e-300)
    undetermined = np.sum(V[:, null] ** 2, axis=1) > 1e-6
    inv = np.where(null, 0.0, 1.0 / np.where(null, 1.0, w))
    cov = (V * inv) @ V.T
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    se = np.where(undetermined, np.inf, se)
    return Covariance(cov, undetermined, se, V[:, null])
