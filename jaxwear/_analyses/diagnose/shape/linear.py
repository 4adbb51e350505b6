"""The linear algebra of the shape analysis (`shape.analysis`): penalised fits of the correction's
coefficients to the misfit, alone and jointly, their GCV penalty, and their null
distributions by simulation. Pure numpy on the whitened, projected system: rows are data
rows divided by σ (prewhitened along each scan where the noise is correlated) and prior
rows in SD units, with every nuisance column (the fit's own parameters, the model's
numerical error) projected off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

LAMBDAS = np.logspace(-4, 6, 41)  # penalty grid, relative to tr(A'A)/tr(S)


def sum_zero(n: int) -> np.ndarray:
    """Orthonormal basis Z (n, n−1) of the coefficients that sum to zero."""
    q, _ = np.linalg.qr(np.eye(n) - 1.0 / n)
    return q[:, :n - 1]


# ---------------------------------------------------------------- correlated noise


def _second_difference_lag1(phi: float) -> float:
    """Lag-1 autocorrelation of the second differences x_{i-1} − 2x_i + x_{i+1} of AR(1)
    noise with coefficient φ (−2/3 for white noise)."""
    var = 6.0 - 8.0 * phi + 2.0 * phi ** 2
    cov = -4.0 + 7.0 * phi - 4.0 * phi ** 2 + phi ** 3
    return cov / var


def ar1_coefficient(e: np.ndarray, mids: np.ndarray) -> tuple[float, float]:
    """AR(1) coefficient φ of the measurement noise along the scans, from the lag-1
    autocorrelation of its normalised second differences `e` (at rows `mids`, consecutive
    within a series where the rows are): smooth misfit cancels in second differences, so
    this reads the noise, not the physics. Returns (φ, z): z is the deviation from white
    noise's −2/3 in standard errors; φ = 0 unless z > 3."""
    if len(e) < 8:
        return 0.0, 0.0
    adjacent = np.flatnonzero(np.diff(mids) == 1)
    if len(adjacent) < 8:
        return 0.0, 0.0
    a, b = e[adjacent], e[adjacent + 1]
    r = float(a @ b) / max(float(np.sqrt((a @ a) * (b @ b))), 1e-300)
    # for white noise the lag-1 products of second differences have a variance of about
    # (1 + 2·(4/9 + 1/36))/n around −2/3 (their lag-2 correlation 1/6 inflates it)
    se = math.sqrt(1.944 / len(adjacent))
    z = (r + 2.0 / 3.0) / se
    if z <= 3.0:
        return 0.0, z
    grid = np.linspace(0.0, 0.95, 191)
    vals = np.array([_second_difference_lag1(p) for p in grid])
    return float(np.interp(r, vals, grid)), z


def prewhiten(X: np.ndarray, series: list, phi: float, n_data: int) -> np.ndarray:
    """X (rows, k) with its data rows transformed along each series so that AR(1) noise
    of coefficient φ becomes white: x_t − φ x_{t−1} scaled by 1/√(1 − φ²), the first row of
    a series kept (Prais-Winsten); prior rows unchanged."""
    if phi == 0.0:
        return X
    out = np.array(X, np.float64, copy=True)
    c = 1.0 / math.sqrt(1.0 - phi * phi)
    for rows, _, _ in series:
        rows = np.asarray(rows)
        rows = rows[rows < n_data]
        if len(rows) < 2:
            continue
        out[rows[1:]] = c * (X[rows[1:]] - phi * X[rows[:-1]])
    return out


# ---------------------------------------------------------------- penalised fits


class Smoother:
    """min_a ||y − A a||² + λ a'Sa for the (whitened, projected) columns A, in the
    coordinates of A's left singular vectors: everything data-dependent is y = U'ρ (m,)
    and ||ρ||²."""

    def __init__(self, A: np.ndarray, S: np.ndarray, lambdas: np.ndarray = LAMBDAS):
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        keep = s > 1e-10 * max(s[0] if len(s) else 0.0, 1e-300)
        self.U, self.s, self.Vt = U[:, keep], s[keep], Vt[keep]
        AtA = (self.Vt.T * self.s ** 2) @ self.Vt
        scale = np.trace(AtA) / max(np.trace(S), 1e-300)
        self.lambdas = lambdas * scale
        ridge = 1e-12 * max(np.trace(AtA), 1e-300) * np.eye(len(S))
        # pinv: a variable whose columns the base fit's projection left (numerically) null
        # makes AtA + λS singular to working precision, whatever the ridge (a 3-experiment
        # study with its registration held made np.linalg.inv raise)
        self.inv = [np.linalg.pinv(AtA + lam * S + ridge, hermitian=True)
                    for lam in self.lambdas]
        B = self.Vt.T * self.s  # A'U = V Σ
        self.M = np.stack([B.T @ inv @ B for inv in self.inv])  # (L, m, m)
        self.trace = np.einsum("lii->l", self.M)
        # 2 y·My − ||My||² = y'(M + M' − M'M)y: one quadratic form per λ (the null's
        # 20000 draws x 41 penalties: 2.5x faster than the two contractions)
        Mt = self.M.transpose(0, 2, 1)
        self.Q = self.M + Mt - np.matmul(Mt, self.M)
        self.AtU = B

    @property
    def m(self) -> int:
        return self.U.shape[1]

    def rss_drop(self, Y):
        """RSS_0 − RSS_λ (..., L) for y's (..., m): 2 y·ŷ − ||ŷ||²."""
        Y = np.asarray(Y, np.float64)
        flat = Y.reshape(-1, Y.shape[-1])
        d = np.einsum("ldi,di->dl", np.matmul(flat[None], self.Q), flat, optimize=True)
        return d.reshape(*Y.shape[:-1], self.Q.shape[0])

    def choose(self, drop, rss0, n_res):
        """GCV: argmin over λ of RSS_λ / (n − tr)² (rss0, n_res: the base fit's)."""
        rss = rss0[..., None] - drop
        gcv = rss / np.maximum(n_res - self.trace, 1e-9) ** 2
        return np.argmin(gcv, axis=-1)

    def coefficients(self, i: int, y: np.ndarray) -> np.ndarray:
        return self.inv[i] @ (self.AtU @ y)


@dataclass(frozen=True)
class PenalisedFit:
    """A penalised fit of coefficients `a` (in the columns' own coordinates) to the misfit:
    `drop` ΔRSS (σ² units), `dof` effective parameters, `p` its simulated p-value, `lam`
    the penalty, `cov` the Bayesian (Wahba) covariance of `a`."""

    a: np.ndarray
    drop: float
    dof: float
    p: float
    lam: float
    cov: np.ndarray
    index: int


def penalised_fit(A, S, rho, n_res, nu, rng, draws) -> PenalisedFit:
    """The GCV-penalised fit of A's columns to ρ, with the null distribution of its ΔRSS
    simulated with the penalty re-chosen in every draw (so the choice is paid for): y* ~
    N(0, I), the rest of the base residual χ²_{n_res − m}, σ̂²/σ² ~ χ²_ν/ν;
    p = (1 + #{T* ≥ T}) / (1 + n), n ≤ draws (`null_p_value`)."""
    sm = Smoother(A, S)
    y = sm.U.T @ rho
    rss0 = float(rho @ rho)
    drop = sm.rss_drop(y)
    i = int(sm.choose(drop, np.asarray(rss0), n_res))
    T = float(drop[i])
    p = null_p_value(sm, T, n_res, nu, rng, draws)
    return PenalisedFit(sm.coefficients(i, y), T, float(sm.trace[i]), p, float(sm.lambdas[i]),
                        sm.inv[i], i)


FIRST_DRAWS = 2000  # the null's first batch; more only where the statistic is rare
STOP_AT = 20  # exceedances that end the simulation (Besag & Clifford's sequential p)


def null_p_value(sm: Smoother, T: float, n_res, nu, rng, draws) -> float:
    """p = (1 + #{T* ≥ T}) / (1 + n) over n simulated nulls: `FIRST_DRAWS` first, the
    rest of `draws` only where fewer than `STOP_AT` exceeded T (Besag & Clifford 1991:
    a p-value that is already ≥ ~0.01 needs no resolution near the Bonferroni level;
    the variables of a null study cost a tenth)."""
    if draws <= 0 or sm.m == 0:
        return math.nan
    done, hits = 0, 0
    for n in (min(draws, FIRST_DRAWS), draws - min(draws, FIRST_DRAWS)):
        if n <= 0 or (done and hits >= STOP_AT):
            break
        hits += int(np.sum(_null_statistics(sm, n_res, nu, rng, n) >= T))
        done += n
    return (1.0 + hits) / (1.0 + done)


def _null_statistics(sm: Smoother, n_res, nu, rng, draws) -> np.ndarray:
    """T* of `draws` simulated nulls (the penalty re-chosen in each)."""
    m = sm.m
    Y = rng.standard_normal((draws, m))
    rest = rng.chisquare(max(n_res - m, 1), draws)
    s2 = rng.chisquare(nu, draws) / nu if math.isfinite(nu) and nu > 0 else np.ones(draws)
    Y = Y / np.sqrt(s2)[:, None]
    rss0_star = np.einsum("ij,ij->i", Y, Y) + rest / s2
    d_star = sm.rss_drop(Y)
    j = sm.choose(d_star, rss0_star, n_res)
    return d_star[np.arange(draws), j]


def psolve(H: np.ndarray, b: np.ndarray) -> np.ndarray:
    """H⁺ b for a symmetric positive semi-definite H (k, k): eigenvalues under 1e-12 of the
    largest (or all, where the largest is itself below 1e-290) are dropped. Blocks whose
    columns are exactly zero (a B-spline of a deposit variable that no step reaches) leave
    H singular, or scaled by a subnormal ridge that a flush-to-zero FPU reads as 0: two null
    studies of 124 at auto numerics raised "Singular matrix" in `np.linalg.solve`."""
    w, V = np.linalg.eigh(H)
    top = float(np.max(w)) if len(w) else 0.0
    if not top > 1e-290:
        return np.zeros(H.shape[0])
    keep = w > 1e-12 * top
    return V[:, keep] @ ((V[:, keep].T @ b) / w[keep])


def block_penalty(blocks) -> tuple[np.ndarray, np.ndarray]:
    """The columns of several variables side by side, and their block-diagonal penalty
    with each block scaled by its own tr(A'A)/tr(S), so that one λ penalises every
    variable alike relative to its information."""
    A = np.hstack([a for a, _ in blocks])
    n = A.shape[1]
    S = np.zeros((n, n))
    k = 0
    for a, s in blocks:
        w = np.trace(a.T @ a) / max(np.trace(s), 1e-300)
        S[k:k + a.shape[1], k:k + a.shape[1]] = s * w
        k += a.shape[1]
    return A, S


def joint_fit(blocks, rho, n_res, nu, rng, draws):
    """The joint penalised fit of several variables (additive: the sum of their
    corrections), one GCV penalty; and each block's unique share: the ΔRSS it adds to the
    fit of the others at the same penalty. Returns (PenalisedFit, [unique drop per
    block])."""
    A, S = block_penalty(blocks)
    fit = penalised_fit(A, S, rho, n_res, nu, rng, draws)
    unique = []
    sizes = [a.shape[1] for a, _ in blocks]
    starts = np.cumsum([0] + sizes)
    for b in range(len(blocks)):
        keep = np.ones(A.shape[1], bool)
        keep[starts[b]:starts[b + 1]] = False
        if not keep.any():
            unique.append(fit.drop)
            continue
        Ak, Sk = A[:, keep], S[np.ix_(keep, keep)]
        lam = fit.lam
        # the others alone at the same λ (absolute, not re-scaled)
        H = Ak.T @ Ak + lam * Sk + 1e-12 * max(np.trace(Ak.T @ Ak), 1e-300) * np.eye(
            keep.sum())
        a = psolve(H, Ak.T @ rho)
        fitted = Ak @ a
        drop = float(2 * rho @ fitted - fitted @ fitted)
        unique.append(fit.drop - drop)
    return fit, unique


def nonnegative_fit(A, S, rho, lam) -> np.ndarray:
    """min ||A c − ρ||² + λ c'Sc over c ≥ 0 (a deposit is never negative): NNLS on the
    stacked system [A; √λ L], L'L = S (+ a ridge)."""
    n = A.shape[1]
    L = np.linalg.cholesky(S + 1e-9 * max(np.trace(S) / n, 1e-300) * np.eye(n)).T
    M = np.vstack([A, math.sqrt(max(lam, 0.0)) * L])
    b = np.concatenate([rho, np.zeros(n)])
    return nnls(M, b, maxiter=50 * n)[0]


def explained(drop: float, dof: float, excess: float, rss0: float) -> float:
    """Share of the misfit a correction explains, net of what it would take from noise
    alone (a correction with `dof` effective parameters removes ~dof σ² of pure noise):
    (ΔRSS − dof)⁺ over the misfit beyond the noise level (RSS_base − (n − k), σ² units)
    where there is some, else over the whole residual sum. Not clipped above: a share over
    1 means the correction also takes up noise, which the ranking (by AIC) then pays for."""
    net = max(drop - dof, 0.0)
    return float(net / max(excess if excess > 0.0 else rss0, 1e-300))


DRAWS = 20000  # null simulations per variable (p resolves 5e-5 < ALPHA / 14)


def trend(v) -> float:
    """Slope of the correction against the wear-weighted quantile t ∈ [0, 1] of z (least
    squares over the plotting grid, which is uniform in t): > 0 where the extra wear rises
    with z."""
    t = np.linspace(0.0, 1.0, len(v.g))
    return float(np.polyfit(t, v.g, 1)[0])
