"""Fits of a subset of the extended parameters and their standard errors, through the one
least-squares core (`jaxwear.lsq`)."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, replace

import numpy as np

from .. import lsq
from ..effects import project_products
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
    stderr: np.ndarray | None = None  # inf where the data do not determine the parameter
    contact: str | None = None
    unstable: bool = False  # the wear loop's derivatives were unstable at the fit
    status: str = "converged"  # the core's: converged, stalled, budget, unusable
    undetermined: tuple = ()  # names of parameters the data leave undetermined

    @property
    def rss(self) -> float:
        return float(self.ev.r @ self.ev.r)

    @property
    def k(self) -> int:
        return int(self.mask.sum())

    @property
    def rmse(self) -> float:
        return float(np.sqrt(np.mean(self.ev.r ** 2)))

    @property
    def flags(self) -> list[str]:
        """What a reader must know about this fit (as `calibrate`'s flags)."""
        out = []
        if self.status != "converged":
            out.append(f"the fit did not converge ({self.status}): {self.message}")
        if self.undetermined:
            out.append(f"the data do not determine {', '.join(self.undetermined)} (Jacobian "
                       f"rank deficient: no standard error)")
        return out


# A refit is done when the next Gauss-Newton step is under 0.1 standard error: it would change
# χ² by ~0.01, the ln Bayes factor by half that, against the ln 20 that separates candidates.
# (calibrate's 0.01 is for reported values; a misspecified candidate's large residuals make
# Gauss-Newton converge only linearly, measured ~0.75 per step, so 0.01 would cost ~8 more
# evaluations per refit for nothing a verdict can see.)
REFIT_SE_TOL = 0.1


def _objective(ev: Eval) -> float:
    return float(ev.r @ ev.r + ev.r_prior @ ev.r_prior)


def _system(ev: Eval, mask):
    J = np.vstack([ev.J[:, mask], ev.J_prior[:, mask]])
    r = np.concatenate([ev.r, ev.r_prior])
    return J, r


def _log(verbose, msg):
    if verbose:
        print(msg, file=sys.stderr, flush=True)


def _point(ev: Eval, noise_um: float, adaptive: bool) -> lsq.Point:
    """The core's view of an evaluation. The core weights data rows by 1/σ and takes prior
    rows as they are; diagnose's objective is Q = Σr² + Σr_prior² (prior rows in µm), so
    the prior rows are divided by σ too: the core then minimises Q/σ², the same fit. The
    integrator's error sets the core's floor only where its steps adapt (as calibrate's)."""
    return lsq.Point(u=ev.u, r=ev.r, predicted=ev.pred, J=ev.J, r_prior=ev.r_prior / noise_um,
                     J_prior=ev.J_prior / noise_um, usable=ev.usable,
                     error_um=(float(ev.error_um) if adaptive and math.isfinite(ev.error_um)
                               else 0.0),
                     extra=ev)


def fit_masked(model: Model, mask, u0, *, noise_um: float, label="base", groups=(),
               ev0: Eval | None = None, max_evaluations: int = 20, verbose=False) -> Fit:
    """The free columns `mask` fitted by `lsq.solve` (bounds by projection), from u0, with
    the data's noise level `noise_um` [µm] (diagnose's estimate from neighbour differences,
    held fixed: the candidates are compared at one noise level); a start where the model
    wears through first lowers K_d (`lsq.robust_start`, step 1)."""
    mask = np.asarray(mask, bool)
    lo, hi = model.bounds_u()
    u = np.clip(np.array(u0, np.float64), lo, hi)

    sigma = max(float(noise_um), 1e-9)

    def evaluate(v):
        return _point(model.evaluate(v), sigma, model.ext.schedule.adaptive)

    log = (lambda m: _log(True, m)) if verbose else None
    if ev0 is not None and ev0.usable:
        pt0, evals = _point(ev0, sigma, model.ext.schedule.adaptive), 0
    else:
        kd = model.index.get("K_d_per_Pa")
        u, pt0, evals, why = lsq.robust_start(evaluate, u, kd if kd is not None and mask[kd]
                                              else None, measured=model.measured,
                                              log=log, rescales=0)
        if why:
            return Fit(label, tuple(groups), mask, pt0.extra, False, evals, why,
                       status="unusable")
    cols = model.columns
    out = lsq.solve(evaluate, u, point0=pt0, free=mask, lower=lo, upper=hi,
                    noise_um=sigma, max_evaluations=max_evaluations, se_tol=REFIT_SE_TOL,
                    project=lambda v: project_products([c.key for c in cols],
                                                      np.asarray(model.ext.start),
                                                      [c.scale for c in cols], v),
                    label=f"  {label}", log=log)
    names = [model.names[i] for i, bad in zip(np.flatnonzero(mask), out.cov.undetermined)
             if bad]
    return Fit(label, tuple(groups), mask, out.point.extra, out.converged,
               evals + out.evaluations, out.message, status=out.status,
               undetermined=tuple(names))


def finish(model: Model, fit: Fit, noise_um: float) -> Fit:
    """Standard errors of the free parameters: the core's covariance with the residuals in
    units of max(noise, rms misfit), so an inadequate model does not get falsely small
    errors; parameters the data leave undetermined get an infinite standard error."""
    J, _ = _system(fit.ev, fit.mask)
    n, k = model.n, fit.k
    s = math.sqrt(max(noise_um ** 2, float(fit.ev.r @ fit.ev.r) / max(n - k, 1)))
    Jw = J.copy()
    Jw[:n] /= s
    Jw[n:] /= max(model.noise_weight, 1e-12)  # prior rows are (c - c_nom)/τ · weight
    c = lsq.covariance(Jw)
    vals = model.values(fit.ev.u)
    idx = np.flatnonzero(fit.mask)
    # delta method through the parameterisation (diagonal but for product pairs)
    G = model.value_jacobian(fit.ev.u)[np.ix_(idx, idx)]
    bad = np.any((np.abs(G) > 0) & c.undetermined[None, :], axis=1)
    se = np.full(len(vals), np.nan)
    se[idx] = np.where(bad, np.inf, np.sqrt(np.clip(np.diag(G @ c.cov @ G.T), 0, None)))
    names = tuple(model.names[i] for i, b in zip(idx, bad) if b)
    return replace(fit, cov_u=c.cov, values=vals, stderr=se, undetermined=names)
