"""Fitting a subset of the extended parameters (host-side Levenberg-Marquardt) and the
standard errors at a fit."""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, replace

import numpy as np

from ._extended import Eval
from ._model import Model


@dataclass(frozen=True)
class Fit:
    """A fit of the extended model with the columns in `mask` free (the rest fixed)."""

    label: str  # "base", a candidate name, or "a+b"
    groups: tuple  # candidates switched on
    mask: np.ndarray
    ev: Eval
    converged: bool
    evaluations: int
    message: str
    cov_u: np.ndarray | None = None  # (free, free), noise-scaled
    values: np.ndarray | None = None
    stderr: np.ndarray | None = None
    contact: str | None = None
    unstable: bool = False  # the wear loop's derivatives were unstable at the fit

    @property
    def rss(self) -> float:
        return float(self.ev.r @ self.ev.r)

    @property
    def k(self) -> int:
        return int(self.mask.sum())

    @property
    def rmse(self) -> float:
        return float(np.sqrt(np.mean(self.ev.r ** 2)))


def _objective(ev: Eval) -> float:
    return float(ev.r @ ev.r + ev.r_prior @ ev.r_prior)


def _system(ev: Eval, mask):
    J = np.vstack([ev.J[:, mask], ev.J_prior[:, mask]])
    r = np.concatenate([ev.r, ev.r_prior])
    return J, r


def _log(verbose, msg):
    if verbose:
        print(msg, file=sys.stderr, flush=True)


def fit_masked(model: Model, mask, u0, *, label="base", groups=(), ev0: Eval | None = None,
               max_evaluations: int = 40, f_tol: float = 0.0, verbose=False) -> Fit:
    """Levenberg-Marquardt (Marquardt scaling, Nielsen damping) over the free columns,
    with bounds enforced by projection. Every trial is one evaluation of the compiled
    extended model. Stops when an accepted step changes the objective by < 1e-6 relative
    or by < `f_tol` [µm², the objective's unit], or when the Gauss-Newton step would lower
    it by < `f_tol` (checked before evaluating it), or u by < 1e-8, or when no step reduces
    it, or after `max_evaluations`."""
    mask = np.asarray(mask, bool)
    lo, hi = model.bounds_u()
    u = np.clip(np.array(u0, np.float64), lo, hi)
    ev = model.evaluate(u) if ev0 is None else ev0
    evals = 1 if ev0 is None else 0
    if not ev.usable:
        # worn through at the start: K_d down until the model is usable
        kd = model.index.get("K_d_per_Pa")
        for _ in range(8):
            if kd is None or ev.usable:
                break
            u[kd] -= math.log(10.0)
            ev, evals = model.evaluate(u), evals + 1
        if not ev.usable:
            return Fit(label, tuple(groups), mask, ev, False, evals,
                       "the model is not usable at the start (worn through or not finite)")
    F = _objective(ev)
    lam, nu = 1e-3, 2.0
    t0 = time.perf_counter()
    message, converged = f"did not converge within {max_evaluations} evaluations", False
    while evals < max_evaluations:
        J, r = _system(ev, mask)
        A, g = J.T @ J, J.T @ r
        col = np.sqrt(np.maximum(np.diag(A), 1e-300))
        free_u = u[mask]
        # gradient test on the components not pinned at a bound by the gradient's sign
        at_lo = (free_u <= lo[mask] + 1e-12) & (g > 0)
        at_hi = (free_u >= hi[mask] - 1e-12) & (g < 0)
        gt = np.where(at_lo | at_hi, 0.0, g)
        if np.max(np.abs(gt) / col, initial=0.0) <= 1e-9 * math.sqrt(F + 1e-300):
            message, converged = "converged (gradient)", True
            break
        if lam > 1e16:
            message, converged = "converged (no step reduces the misfit)", True
            break
        if f_tol > 0:
            # Gauss-Newton decrement g'A⁻¹g over the components free to move: what a full
            # step could still remove. Below the tolerance the trial is not worth its
            # evaluation (near the minimum the linearisation is accurate).
            k = ~(at_lo | at_hi)
            s_gn = np.linalg.lstsq(A[np.ix_(k, k)], -g[k], rcond=None)[0]
            if -float(g[k] @ s_gn) < f_tol:
                message, converged = "converged (predicted decrease below tolerance)", True
                break
        D = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
        step = np.linalg.lstsq(A + lam * np.diag(D), -g, rcond=None)[0]
        trial = u.copy()
        trial[mask] = np.clip(u[mask] + step, lo[mask], hi[mask])
        step = trial[mask] - u[mask]
        ev_t = model.evaluate(trial)
        evals += 1
        F_t = _objective(ev_t) if ev_t.usable else math.inf
        pred = -(2 * float(step @ g) + float(step @ A @ step))
        rho = (F - F_t) / pred if pred > 0 else -1.0
        if F_t < F and rho > 0:
            rel = (F - F_t) / max(F, 1e-300)
            F_old = F
            u, ev, F = trial, ev_t, F_t
            lam *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
            nu = 2.0
            _log(verbose, f"    {label}: rms {math.sqrt(np.mean(ev.r ** 2)):.4f} µm "
                          f"({evals} evaluations, {time.perf_counter() - t0:.1f} s)")
            # 1e-6 of the objective is ~1e-3 of one noise variance here: far below what
            # the evidence or the standard errors resolve
            if (rel <= 1e-6 or F_old - F <= f_tol
                    or np.max(np.abs(step)) <= 1e-8 * (1 + np.max(np.abs(u)))):
                message, converged = "converged", True
                break
        else:
            lam *= nu
            nu *= 2.0
    return Fit(label, tuple(groups), mask, ev, converged, evals, message)


def finish(model: Model, fit: Fit, noise_um: float) -> Fit:
    """Standard errors of the free parameters (Gauss-Newton, residuals in units of
    max(noise, rms misfit), so an inadequate model does not get falsely small errors)."""
    J, r = _system(fit.ev, fit.mask)
    n, k = model.n, fit.k
    s2 = max(noise_um ** 2, float(fit.ev.r @ fit.ev.r) / max(n - k, 1))
    Jn = J.copy()
    Jn[:n] /= math.sqrt(s2)
    Jn[n:] /= max(model.noise_weight, 1e-12)  # prior rows are (c - c_nom)/τ · weight
    cov = np.linalg.pinv(Jn.T @ Jn, rcond=1e-13, hermitian=True)
    vals = model.values(fit.ev.u)
    idx = np.flatnonzero(fit.mask)
    deriv = np.array([vals[i] if model.columns[i].log else model.columns[i].scale
                      for i in idx])
    se = np.full(len(vals), np.nan)
    se[idx] = np.sqrt(np.clip(np.diag(cov), 0, None)) * np.abs(deriv)
    return replace(fit, cov_u=cov, values=vals, stderr=se)
