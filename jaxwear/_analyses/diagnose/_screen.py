"""Screening the candidates: score (Lagrange-multiplier) tests at a fit."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from jaxwear._analyses.diagnose._fit import Fit, _log, whitened_system
from jaxwear._analyses.diagnose._model import Model
from jaxwear._analyses.diagnose._stats import f_sf

SHAPE_GRID = (0.1, 0.3, 1.0, 3.0, 10.0)  # multiples of a shape parameter's default tried


def well_above_noise(model, fit, noise_um: float) -> bool:
    """The fit's misfit is over 1.5x what noise alone leaves ((n - k) σ²): a share of it
    that a candidate explains means something (the screen says it; the shape's design is
    started ahead on it, `_verdict._design_ahead`)."""
    return fit.rss > 1.5 * (model.n - fit.k) * noise_um ** 2


@dataclass(frozen=True)
class Screen:
    """Score test of one candidate at a fit (linearised: one Gauss-Newton step).

    `score`: LM statistic r'Z(Z'Z)⁻¹Z'r / σ̂² with Z the candidate's strength column(s)
    projected off the fitted columns (χ²(df) under the model fitted); `delta_rss`: the
    RSS it would remove [µm²]; `explained`: that as a fraction of the systematic misfit
    RSS - (n-k) σ̂²; `start`: the step's strength and the best shape values (key units).
    A step that leaves a strength's bounds is infeasible (score 0).
    """

    effect: str
    score: float
    df: int
    p: float
    delta_rss: float
    explained: float
    start: dict
    feasible: bool


def _project_out(J, Z):
    """Z minus its least-squares projection on the columns of J."""
    if J.shape[1] == 0:
        return Z
    coef = np.linalg.lstsq(J, Z, rcond=None)[0]
    return Z - J @ coef


def screen(model: Model, fit: Fit, noise_um: float, nu: float = math.inf, *,
           verbose=False) -> list[Screen]:
    """Score tests of every parametric candidate not in `fit` (structural `unsymmetric`
    has no strength and is left to a refit).

    An effect with shape parameters (log-fitted, e.g. the running-in distance) is tested
    at each of `SHAPE_GRID` times their value in `fit` (the strength's column depends on
    them; the model does not, at strength off) and keeps the best; its p-value is
    multiplied by the grid size. p-values use F(df, ν): the noise level is estimated with
    ν degrees of freedom.
    """
    groups = [g for g in model.candidates if g not in fit.groups and g != "unsymmetric"]
    # the whitened system (data rows / σ, prior rows in SD units): the score is then the
    # χ² a linearised refit would remove
    r, J = whitened_system(fit.ev, fit.mask, noise_um)
    n_prior = len(fit.ev.r_prior)
    q_sys = max(fit.rss - (model.n - fit.k) * noise_um ** 2, 1e-300)
    lo, hi = model.bounds_u()
    out = []
    for g in groups:
        idx = [i for i, c in enumerate(model.columns) if c.group == g]
        s_idx = [i for i in idx if model.columns[i].strength]
        h_idx = [i for i in idx if not model.columns[i].strength]
        grid = [1.0] if not h_idx else list(SHAPE_GRID)
        best = None
        for mult in grid:
            u = fit.ev.u.copy()
            u[h_idx] += math.log(mult)
            ev = fit.ev if mult == 1.0 else model.evaluate(u)
            Z = np.vstack([ev.J[:, s_idx] / noise_um, np.zeros((n_prior, len(s_idx)))])
            Zp = _project_out(J, Z)
            ZZ = Zp.T @ Zp
            if not np.all(np.isfinite(ZZ)) or np.max(np.abs(ZZ)) < 1e-300:
                continue
            coef = np.linalg.lstsq(ZZ, -(Zp.T @ r), rcond=None)[0]  # GN step in u
            d_chi2 = float(-(Zp.T @ r) @ coef)
            step = u[s_idx] + coef
            # one-sided where the strength sits at a bound (a ≥ 0, μ ≥ 0, C ≥ 0, q ≥ 0):
            # a step out of bounds means the effect cannot explain this misfit
            feasible = bool(np.all(step >= lo[s_idx] - 1e-12)
                            and np.all(step <= hi[s_idx] + 1e-12))
            score = d_chi2 if feasible else 0.0
            d_rss = score * noise_um ** 2
            if best is None or score > best.score:
                # refit start: the step, capped at 3 typical sizes (the linearisation is
                # only a guide far from the base model)
                u_start = u.copy()
                u_start[s_idx] = np.clip(u[s_idx] + np.clip(coef, -3.0, 3.0), lo[s_idx],
                                         hi[s_idx])
                vals = model.values(u_start)
                best = Screen(g, score, len(s_idx), 1.0, d_rss, d_rss / q_sys,
                              {model.names[i]: float(vals[i]) for i in idx}, feasible)
        if best is not None:
            p = f_sf(best.score / best.df, best.df, nu) if best.score > 0 else 1.0
            best = replace(best, p=min(1.0, p * len(grid)))
            out.append(best)
            share = (f", explains {100 * best.explained:.0f}% of the misfit"
                     if well_above_noise(model, fit, noise_um) else "")
            _log(verbose, f"    score {g:18s} {best.score:10.1f} (p {best.p:.1e}{share})")
    out.sort(key=lambda s: -s.score)
    return out
