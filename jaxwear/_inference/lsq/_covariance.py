"""The Gauss-Newton linear algebra of the core: one SVD of the whitened, column-scaled
Jacobian gives the step, the stop's test and the covariance, with the directions the data
leave undetermined flagged.

Why scaled: u mixes log-multipliers, linear strengths in their units and registration
offsets in degrees; a column in small units (×1e-6) has a tiny norm without being any
less determined. Every column of Jw is divided by its norm D first (Marquardt's scaling,
the one the LM step uses), so "undetermined" means a direction the data cannot tell apart,
not a unit. Why SVD of the Jacobian and not an inverse of JᵀJ: the normal equations square
the condition number.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A singular value of the scaled, whitened Jacobian below this fraction of the largest is a
# null direction: a parameter with a component along it has no standard error (a pseudo-
# inverse alone would give it a zero variance, i.e. claim it is known exactly). In scaled
# coordinates a singular value of 1e-6 means two columns with correlation 1 − 5e-13.
NULL_RTOL = 1e-6


@dataclass(frozen=True)
class Covariance:
    """`cov` (k, k): covariance of the free u (inverse of the whitened JᵀJ on its range);
    `undetermined` (k,): u along a null direction; `se` (k,): standard errors of u (inf
    where undetermined); `null_directions` (k, d): an orthonormal basis of the null space
    in u; `k_eff`: the effective number of parameters the *data* rows determine (trace of
    their hat matrix: a parameter fixed by its prior counts ~0, one fixed by the data 1)."""

    cov: np.ndarray
    undetermined: np.ndarray
    se: np.ndarray
    null_directions: np.ndarray
    k_eff: float = 0.0

    @property
    def any_determined(self) -> bool:
        return bool(np.any(~self.undetermined))


@dataclass(frozen=True)
class Factor:
    """SVD of the scaled whitened Jacobian Jw/D = U S Vᵀ (range only) and the scale D."""

    U: np.ndarray  # (rows, r)
    s: np.ndarray  # (r,)
    V: np.ndarray  # (k, r)
    V_null: np.ndarray  # (k, k − r)
    D: np.ndarray  # (k,)
    zero: np.ndarray  # (k,) columns with no information at all


def column_scale(Jw: np.ndarray) -> np.ndarray:
    """Column norms of Jw; 1 for a zero column (it stays zero, flagged undetermined)."""
    D = np.sqrt(np.sum(np.asarray(Jw) ** 2, axis=0))
    return np.where(D > 0, D, 1.0)


def factor(Jw: np.ndarray, D: np.ndarray | None = None) -> Factor:
    """The SVD of Jw/D (D: `column_scale(Jw)` unless given)."""
    Jw = np.asarray(Jw, np.float64)
    k = Jw.shape[1]
    norms = np.sqrt(np.sum(Jw ** 2, axis=0))
    D = column_scale(Jw) if D is None else np.asarray(D, np.float64)
    zero = ~(norms > 1e-300)
    if k == 0 or Jw.shape[0] == 0:
        return Factor(np.zeros((Jw.shape[0], 0)), np.zeros(0), np.zeros((k, 0)), np.eye(k), D,
                      np.ones(k, bool))
    # The thin SVD: U (rows, k), linear in the rows. full_matrices=True made U (rows, rows):
    # 671 GiB for a 300 000-row scan (issue 41). Vt is (k, k) whenever rows >= k; with fewer
    # rows than columns the full Vt is needed for the null space, and U is small then.
    U, s, Vt = np.linalg.svd(Jw / D, full_matrices=Jw.shape[0] < k)
    U = U[:, :len(s)]
    top = float(s[0]) if len(s) else 0.0
    rank = int(np.sum(s > NULL_RTOL * top)) if top > 0 else 0
    V = Vt.T
    return Factor(U[:, :rank], s[:rank], V[:, :rank], V[:, rank:], D, zero)


def covariance(Jw: np.ndarray, n_data: int | None = None, D: np.ndarray | None = None
               ) -> Covariance:
    """Covariance of u from the whitened Jacobian `Jw` (rows, k): data rows divided by the
    noise level, prior rows in units of their standard deviation. `n_data`: how many of the
    leading rows are data rows (for `k_eff`; default all)."""
    Jw = np.asarray(Jw, np.float64)
    k = Jw.shape[1]
    if not np.all(np.isfinite(Jw)):
        return Covariance(np.full((k, k), np.nan), np.ones(k, bool), np.full(k, np.inf),
                          np.eye(k), float(k))
    f = factor(Jw, D)
    return _covariance_of(f, Jw.shape[0] if n_data is None else n_data)


def _covariance_of(f: Factor, n_data: int) -> Covariance:
    k = len(f.D)
    Vs = f.V / f.s if len(f.s) else f.V
    cov_y = Vs @ Vs.T
    cov = cov_y / np.outer(f.D, f.D)
    undetermined = (np.sum(f.V_null ** 2, axis=1) > 1e-6) | f.zero
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    se = np.where(undetermined, np.inf, se)
    # the null space in u (columns orthonormalised: u = y / D)
    N = f.V_null / f.D[:, None] if f.V_null.size else np.zeros((k, 0))
    if N.shape[1]:
        N = np.linalg.qr(N)[0]
    k_eff = float(np.sum(f.U[:n_data] ** 2)) if f.U.size else 0.0
    return Covariance(cov, undetermined, se, N, k_eff)


def gauss_newton(rw: np.ndarray, Jw: np.ndarray, n_data: int | None = None,
                 D: np.ndarray | None = None) -> tuple[np.ndarray, Covariance]:
    """The full Gauss-Newton step of u (k,) minimising ½|rw + Jw δ|² on the determined
    directions (minimum norm in the scaled coordinates along the others), and the
    covariance, from one SVD."""
    Jw = np.asarray(Jw, np.float64)
    f = factor(Jw, D)
    step_y = -(f.V @ ((f.U.T @ rw) / f.s)) if len(f.s) else np.zeros(Jw.shape[1])
    return step_y / f.D, _covariance_of(f, Jw.shape[0] if n_data is None else n_data)
