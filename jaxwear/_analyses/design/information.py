"""Fisher information of the study plus a candidate, the goals' values, and the greedy choice of
a set."""

from __future__ import annotations

import math

import numpy as np

from jaxwear._analyses.design.plan import MAX_SCANS, Plan
from jaxwear._analyses.design.runs import Runs
from jaxwear._inference.result import FitResult
from jaxwear._study.study import Study


def _marginal(Iq: np.ndarray, P: int, clear_prec: float | None) -> np.ndarray:
    """Information (..., q, q) over [θ (P), δ] → over θ: the candidate's own clearance δ a
    nuisance with prior precision `clear_prec` (None: held at nominal)."""
    A = Iq[..., :P, :P]
    if clear_prec is None:
        return A
    b = Iq[..., :P, P]
    d = Iq[..., P, P] + clear_prec
    return A - b[..., :, None] * b[..., None, :] / d[..., None, None]


def _clear_prec(study: Study) -> float | None:
    tol = float(study.clearance_tolerance_um)
    if tol == 0:
        return None  # clearances held at nominal
    return 0.0 if math.isinf(tol) else 1.0 / (tol * 1e-3) ** 2


def _logdet(M) -> np.ndarray:
    sign, ld = np.linalg.slogdet(M)
    return np.where(sign > 0, ld, -np.inf)


def _full_information(result: FitResult) -> tuple[np.ndarray, float]:
    """The study's information over every fitted u (data rows at the fit's error scale,
    prior rows) and that scale [µm]."""
    ev = result.evaluation
    s = float(result.error_scale_um) if math.isfinite(result.error_scale_um) else float(
        result.noise_um)
    return ev.J.T @ ev.J / s ** 2 + ev.J_prior.T @ ev.J_prior, s


def _embed(result: FitResult, runs: Runs, plan: Plan, A: np.ndarray, sigma: float,
           clear_prec) -> np.ndarray:
    """(C, P_full, P_full): each candidate's information in the study's full u. A new
    specimen's own clearance is marginalised (prior precision `clear_prec`); the next
    measurement of an existing experiment (timed) shares that experiment's fitted
    clearance column."""
    names = list(result.names)
    P_full = len(names)
    P = len(runs.names)
    idx = [names.index(n) for n in runs.names]
    G = result.problem.packing.value_jacobian(result.u)
    out = np.zeros((plan.size, P_full, P_full))
    col = None
    if plan.continuation is not None:
        col = names.index(f"clearance_mm/{plan.continuation}") if (
            f"clearance_mm/{plan.continuation}" in names) else None
    for i in range(plan.size):
        Iq = A[plan.run[i], plan.snaps[i]].sum(axis=0)[:P + 1, :P + 1] / sigma ** 2
        if plan.continuation is None:
            out[i][np.ix_(idx, idx)] = _marginal(Iq, P, clear_prec)
        elif col is None:
            out[i][np.ix_(idx, idx)] = Iq[:P, :P]
        else:
            g = G[col, col]  # d clearance [mm] / d u of its column
            T = np.zeros((P + 1, P_full))
            T[np.arange(P), idx] = 1.0
            T[P, col] = g
            out[i] = T.T @ Iq @ T
    return out


def _forecast_gradient(result: FitResult, runs: Runs, target, plan: Plan,
                       study: Study) -> np.ndarray:
    """d (forecast maximum depth) / d u (P_full,) [µm]: the shared parameters, and the
    target experiment's own fitted clearance."""
    names = list(result.names)
    r, s = target
    k = int(np.argmax(runs.snaps[r, s]))
    g = np.zeros(len(names))
    g[[names.index(n) for n in runs.names]] = runs.J[r, s, k]
    exp = plan.continuation or study.experiments[0].name
    col = f"clearance_mm/{exp}"
    if col in names:
        i = names.index(col)
        g[i] = runs.J_clear[r, s, k] * result.problem.packing.value_jacobian(result.u)[i, i]
    return g


def _goal_value(goal, info, shared_idx, for_idx, G, values, g, z):
    """The goal's value of information matrices I (..., P_full, P_full) (module
    docstring); and per-parameter standard errors (..., len(shared)) in value units."""
    cov = np.linalg.inv(info)
    Gs = G[np.ix_(shared_idx, shared_idx)]
    cs = cov[..., shared_idx, :][..., :, shared_idx]
    cov_v = Gs @ cs @ Gs.T
    se = np.sqrt(np.clip(np.diagonal(cov_v, axis1=-2, axis2=-1), 0, None))
    if goal == "forecast":
        return z * np.sqrt(np.clip(np.einsum("p,...pq,q->...", g, cov, g), 0, None)), se
    if for_idx:
        rel = se[..., for_idx] / np.abs(values[for_idx])
        return 100.0 * np.sqrt(np.mean(rel ** 2, axis=-1)), se
    return -_logdet(cs), se


def _greedy(value_of, I0, Ic, better, budget):
    """Greedy best set: each pick's information added before the next; returns the picks
    and the value after each."""
    picks, vals, cur = [], [], I0.copy()
    for _ in range(budget):
        v = value_of(cur[None] + Ic)
        if picks:
            v = np.asarray(v, float).copy()
            v[picks] = -np.inf if better == "higher" else np.inf
        best = int(_rank(v, better)[0])
        picks.append(best)
        vals.append(float(v[best]))
        cur = cur + Ic[best]
    return picks, vals


def _chi2(dd, b, UtU, a):
    """d^T (a I + U U^T)^-1 d by Woodbury, from d·d, U^T d, U^T U (batched)."""
    q = UtU.shape[-1]
    x = np.linalg.solve(a[..., None, None] * np.eye(q) + UtU, b[..., None])[..., 0]
    return (dd - np.einsum("...q,...q->...", b, x)) / a


def _scans_needed(parts, sigma) -> list:
    """Per candidate, the fewest repeated scan sets n (noise σ²/n, the parameters'
    uncertainty unchanged) whose expected chi-square reaches `SEPARATE_CHI2`; None where
    even `MAX_SCANS` do not (the models' parameter uncertainty covers the difference)."""
    dd, b, UtU = parts
    out = [None] * len(dd)
    need = np.full(len(dd), -1)
    for n in range(1, MAX_SCANS + 1):
        c = _chi2(dd, b, UtU, np.full(len(dd), sigma ** 2 / n))
        hit = (need < 0) & (c >= SEPARATE_CHI2)
        need[hit] = n
        if (need > 0).all():
            break
    for i, n in enumerate(need):
        out[i] = int(n) if n > 0 else None
    return out


SEPARATE_CHI2 = 2.0 * math.log(20.0)  # a likelihood ratio of 20 between the two models


def _rank(values: np.ndarray, better: str) -> np.ndarray:
    v = np.where(np.isfinite(values), values, -np.inf if better == "higher" else np.inf)
    return np.argsort(-v if better == "higher" else v, kind="stable")
