"""Fits of a subset of the extended parameters and their standard errors, through the one
least-squares core (`jaxwear._inference.lsq`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from jaxwear._analyses.diagnose._model import Model
from jaxwear._core.log import log as _log
from jaxwear._inference import lsq
from jaxwear._inference.attempts import attempts_needed, needs_more_attempts, work_failure
from jaxwear._inference.evaluation import Evaluation, unusable_point
from jaxwear._inference.result import value_errors


@dataclass(frozen=True)
class Fit:
    """A fit of the extended model with the columns in `mask` free (the rest fixed).

    `status`: the core's (converged, stalled, budget, unusable, undetermined), or
    "unstable" (the wear loop's derivatives were unstable at the fit); `converged` is
    `status == "converged"`. `cov`: the core's covariance of the free u at the error scale
    the data support; `values`, `stderr`: all columns (stderr inf where the data do not
    determine the parameter, nan for held columns)."""

    label: str  # "base", a candidate name, or "a+b"
    groups: tuple  # candidates switched on
    mask: np.ndarray
    ev: Evaluation
    evaluations: int
    message: str
    cov: lsq.Covariance | None = None
    values: np.ndarray | None = None
    stderr: np.ndarray | None = None
    contact: str | None = None
    status: str = "converged"
    undetermined: tuple = ()  # names of parameters the data leave undetermined

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    @property
    def unstable(self) -> bool:
        return self.status == "unstable"

    @property
    def usable(self) -> bool:
        """False where the fit cannot be compared at all: its derivatives were unstable,
        or the model did not run at its start (a fit out of budget or stalled still is,
        with the misfit it reached)."""
        return self.status not in ("unstable", "unusable")

    @property
    def cov_u(self) -> np.ndarray | None:
        return None if self.cov is None else self.cov.cov

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


def whitened_system(ev: Evaluation, mask, noise_um: float):
    """(rw, Jw) of the free columns: data rows / σ, prior rows in SD units (as the core
    sees them)."""
    return lsq.whitened(ev.point(), noise_um, np.asarray(mask, bool))


def fit_masked(model: Model, mask, u0, *, noise_um: float, noise_dof: float = math.inf,
               label="base", groups=(), ev0: Evaluation | None = None, max_evaluations: int = 20,
               verbose=False, rescales: int = 0, settled: float | None = None) -> Fit:
    """The free columns `mask` fitted by `lsq.solve` (bounds by projection), from u0, with
    the data's noise level `noise_um` [µm] and its degrees of freedom (held fixed: the
    candidates are compared at one noise level); a start where the model wears through
    first lowers K_d (`lsq.robust_start`, step 1); `rescales`: times K_d is first scaled
    to the data by least squares (its step 2: a start whose level is off, e.g. a law that
    adds wear on top of a K_d fitted without it); `settled`: `lsq.solve`'s stop on the
    data's misfit (a candidate ranked by its RMSE)."""
    mask = np.asarray(mask, bool)
    lo, hi = model.bounds_u()
    u = np.clip(np.array(u0, np.float64), lo, hi)
    sigma = max(float(noise_um), 1e-9)

    def evaluate(v):
        return model.evaluate(v).point()

    def trial(v):
        # as calibrate's fits: a trial that needs far more integration steps than the model
        # has run (a stiff corner) is cut off unevaluated, a rejected step: the trust
        # region shrinks towards where the model is affordable; one whose work estimate is
        # not finite cannot run at all
        if not math.isfinite(attempts_needed(model.ext, v)):
            return unusable_point(model.ext, v, work_failure(model.ext, v))
        if needs_more_attempts(model.ext, v):
            return unusable_point(model.ext, v, "cut off unevaluated: it needs over 4x the "
                                  "integration steps of the current point (a stiff corner)")
        return evaluate(v)

    def describe(v):  # the fitted values, for a failed trial's progress line
        return ", ".join(f"{n} = {x:.6g}" for n, x, f in
                         zip(model.names, model.values(v), mask) if f)

    log = (lambda m: _log(True, m)) if verbose else None
    if ev0 is not None and ev0.usable:
        pt0, evals = ev0.point(), 0
    else:
        kd = model.index.get("K_d_per_Pa")
        u, pt0, evals, why = lsq.robust_start(evaluate, u, kd if kd is not None and mask[kd]
                                              else None, measured=model.measured,
                                              log=log, rescales=rescales)
        if why and pt0 is None:  # every start raised: nothing to report a fit at
            raise lsq.FitError(f"{label}: cannot start the fit at {describe(u)}: {why}")
        if why:
            return Fit(label, tuple(groups), mask, pt0.extra, evals, why, status="unusable")
    out = lsq.solve(trial, u, point0=pt0, free=mask, lower=lo, upper=hi,
                    noise_um=sigma, noise_dof=noise_dof, max_evaluations=max_evaluations,
                    se_tol=REFIT_SE_TOL, project=model.packing.project, label=f"  {label}",
                    log=log, describe=describe, settled=settled)
    return fit_of(model, mask, out, label, groups, evals + out.evaluations)


def fit_of(model: Model, mask, out: lsq.Outcome, label, groups, evaluations) -> Fit:
    """A `Fit` from the core's outcome: values and standard errors through the packing
    (`_calibrate.value_errors`, the same delta method as calibrate's)."""
    u = out.u
    se, _, und = value_errors(model.packing, u, out.errors, free=mask)
    names = tuple(n for n, b in zip(model.names, und) if b)
    return Fit(label, tuple(groups), np.asarray(mask, bool), out.point.extra, evaluations,
               out.message, cov=out.errors, values=model.values(u), stderr=se,
               status=out.status, undetermined=names)
