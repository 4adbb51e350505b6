"""What a fit returns: the values with the standard errors the data support, correlations,
flags (undetermined directions, shared products, the noise), and the JSON document."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from jaxwear._core.jsonfmt import json_float as _jf
from jaxwear._core.noise import Noise
from jaxwear._inference import lsq
from jaxwear._inference.evaluation import Evaluation, integration_report
from jaxwear._inference.packing import unit_of
from jaxwear._inference.residual import ResidualModel


@dataclass
class FitResult:
    """Outcome of a calibration. Values and standard errors in the names' units.

    `noise` is the noise level of the rule (`_noise`): `noise_um` its value (given, or the
    data's own estimate, or σ̂ of the residuals); `error_scale_um` what the standard
    errors were computed with (the noise, or the misfit where that is larger).
    `evaluation` is the model at the answer; `covariance` the core's at the error scale
    (free u)."""

    names: list[str]
    values: np.ndarray
    stderr: np.ndarray
    correlation: np.ndarray
    u: np.ndarray
    rmse_um: float
    rmse_per_experiment: dict
    noise_um: float
    residuals_um: np.ndarray  # data rows
    predicted_um: np.ndarray
    measured_um: np.ndarray
    row_experiment: np.ndarray
    iterations: int
    message: str
    flags: list[str]
    problem: ResidualModel
    evaluation: Evaluation
    covariance: lsq.Covariance
    snapshots_um: np.ndarray  # (experiments, snapshots, nodes)
    max_contact_residual: float
    integration: dict | None = None  # error estimate at the fitted values (see `calibrate`)
    status: str = "converged"
    noise: Noise | None = None
    error_scale_um: float = math.nan
    error_dof: float = math.inf
    step_se: float = 0.0  # the next Gauss-Newton step at the answer, in standard errors
    resolution: dict | None = None  # the spatial resolution and its check (`calibrate`)
    clearance_tolerance_um: float = 5.0
    forward_runs: int = 0  # of `iterations`, those without a Jacobian (finer levels)
    compiles: dict | None = None  # compilations for this answer by kind (`fit_study`)
    # rows of the level the answer was checked against minus the answer's rows (rows,)
    # [µm], at `u`: its numerical error, from the check's own forward run (`correct_to_finer`;
    # None where no finer level was run)
    finer_minus_rows_um: np.ndarray | None = None
    finer_level: tuple | None = None
    # fitted values outside the ranges the inputs are held to (`_outside.parameter_flags`)
    outside: list = dataclasses.field(default_factory=list)

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    @property
    def jacobian(self) -> np.ndarray:
        """d rows / d u (data rows [µm], then prior rows [SD])."""
        return np.vstack([self.evaluation.J, self.evaluation.J_prior])

    @property
    def noise_given(self) -> bool:
        return self.noise is not None and self.noise.source == "given"

    def parameters_json(self) -> dict:
        return {n: {"value": float(v), "stderr": (float(s) if np.isfinite(s) else None)}
                for n, v, s in zip(self.names, self.values, self.stderr)}

    def to_json(self) -> dict:
        """The design.md §7 document: `parameters` and `rmse_um`, then diagnostics."""
        tol = float(self.clearance_tolerance_um)
        noise = self.noise
        return {
            "parameters": self.parameters_json(),
            "rmse_um": float(self.rmse_um),
            "rmse_per_experiment_um": {k: float(v) for k, v in self.rmse_per_experiment.items()},
            "noise_um": float(self.noise_um),
            "noise": noise.describe() if noise else "estimated from the residuals",
            "error_scale_um": _jf(self.error_scale_um),
            "units": {n: unit_of(n) for n in self.names},
            "correlation": {"names": list(self.names),
                            "matrix": [[float(x) if np.isfinite(x) else None for x in row]
                                       for row in np.asarray(self.correlation)]},
            "converged": bool(self.converged),
            "status": self.status,
            "iterations": int(self.iterations),
            "model_evaluations": int(self.iterations),
            "evaluations": {"jacobian": int(self.iterations - self.forward_runs),
                            "forward": int(self.forward_runs)},
            "compiles": (None if self.compiles is None
                         else int(sum(self.compiles.values()))),
            "compiles_by_kind": self.compiles,
            "next_step_standard_errors": _jf(self.step_se),
            "message": self.message,
            "flags": list(self.flags),
            "outside_model": list(self.outside),
            "n_data": int(self.n_data),
            "clearance_tolerance_um": tol if math.isfinite(tol) else "inf",
            "max_contact_residual": float(self.max_contact_residual),
            "integration": self.integration,
            "resolution": self.resolution,
        }

    @property
    def n_data(self) -> int:
        return len(self.residuals_um)

    @property
    def rss(self) -> float:
        return float(np.sum(self.residuals_um ** 2))


def value_errors(packing, u, cov: lsq.Covariance, free=None):
    """(se (P,), correlation (P, P), undetermined (P,) bool) of the values from the core's
    covariance of the free u (delta method through the packing: exact for its diagonal
    part); a value that depends on an undetermined u is undetermined."""
    P = packing.size
    free = np.ones(P, bool) if free is None else np.asarray(free, bool)
    idx = np.flatnonzero(free)
    G = packing.value_jacobian(u)[np.ix_(idx, idx)]
    cov_v = G @ cov.cov @ G.T
    bad = np.any((np.abs(G) > 0) & cov.undetermined[None, :], axis=1)
    se = np.full(P, np.nan)
    se[idx] = np.where(bad, np.inf, np.sqrt(np.clip(np.diag(cov_v), 0, None)))
    d = np.sqrt(np.clip(np.diag(cov_v), 1e-300, None))
    corr_f = cov_v / np.outer(d, d)
    corr_f[bad, :] = np.nan
    corr_f[:, bad] = np.nan
    corr = np.full((P, P), np.nan)
    corr[np.ix_(idx, idx)] = corr_f
    und = np.zeros(P, bool)
    und[idx] = bad
    return se, corr, und


def _design_hint(a: str, b: str) -> str:
    """Where two shared parameters are tied: the command that names the experiment that
    pins them down (issue 44); none for an experiment's own clearance or registration."""
    if "/" in a or "/" in b:
        return ""
    return (f"; `jaxwear design STUDY --for {a},{b}` names the next experiment that pins "
            f"them down")


def _product_flag(names, vals, se, corr, und) -> list[str]:
    """With K_d and load_scale both fitted: only their product is identifiable from depths
    (the wear rate is K_d p dS and the pressure scales with the load; the load's size moves
    the contact arc only a little), so say so, with the product and its standard error."""
    if not ("K_d_per_Pa" in names and "load_scale" in names):
        return []
    i, j = names.index("K_d_per_Pa"), names.index("load_scale")
    prod = vals[i] * vals[j]
    r = corr[i, j]
    rel2 = ((se[i] / vals[i]) ** 2 + (se[j] / vals[j]) ** 2
            + 2 * r * se[i] * se[j] / (vals[i] * vals[j]))
    se_p = "undetermined" if und[i] or und[j] or not rel2 >= 0 else \
        f"{abs(prod) * np.sqrt(rel2):.3g}"
    return [f"K_d_per_Pa and load_scale: only their product K_d x load_scale = {prod:.4g} "
            f"(standard error {se_p}) 1/Pa is identifiable from depth data (wear is K_d p dS and "
            f"p scales with the load); each alone (correlation {r:+.3f}) rests on how the "
            f"load's size shapes the contact arc: fix one of them (the load from the "
            f"multibody model, or K_d from a wear test)"]


def summarize(problem: ResidualModel, out: lsq.Outcome, evaluations: int,
              noise: Noise | None = None) -> FitResult:
    """FitResult at the core's answer: values, standard errors (the core's covariance at
    the error scale the data support), correlations, RMSE, flags and the status."""
    u, ev = out.u, out.point.extra
    names = list(problem.names)
    P = len(names)
    pred, meas = ev.pred, problem.measured
    r = pred - meas
    flags = []
    status, msg = out.status, out.message
    if P:
        vals = problem.packing.values_np(u)
        se, corr, und = value_errors(problem.packing, u, out.errors)
        if np.any(und):
            flags.append(f"the data do not determine {', '.join(np.array(names)[und])} "
                         f"(Jacobian rank deficient: no standard error)")
        for i, c in enumerate(problem.columns):
            if c.log:
                rel = se[i] / max(abs(vals[i]), 1e-300)
                if rel > 1.0:
                    flags.append(f"{names[i]}: standard error {rel:.0%} of the value "
                                 f"(not identifiable from these data)")
            elif se[i] > 10 * c.scale:
                flags.append(f"{names[i]}: standard error {se[i]:.3g} is > 10x its typical "
                             f"size {c.scale:g} (not identifiable from these data)")
            for j in range(i + 1, P):
                if abs(corr[i, j]) > 0.99:
                    flags.append(f"{names[i]} and {names[j]}: correlation "
                                 f"{corr[i, j]:+.3f} (|r| > 0.99, not separately identifiable)"
                                 + _design_hint(names[i], names[j]))
        flags += _product_flag(names, vals, se, corr, und)
    else:
        vals, se, corr = np.zeros(0), np.zeros(0), np.zeros((0, 0))
    if out.error_scale_um > out.noise_um * (1 + 1e-9) and noise is not None \
            and noise.source != "residuals":
        flags.append(f"the misfit ({out.error_scale_um:.3g} µm per degree of freedom) exceeds "
                     f"the noise ({out.noise_um:.3g} µm, {noise.describe()}): standard "
                     f"errors are widened by the misfit; `jaxwear diagnose` looks for the "
                     f"physics the model lacks")
    if status == "converged" and float(ev.worn) >= 0:
        status = "worn_through"
        msg += "; but the layer wears through at the fitted values"
    if status == "converged" and not float(ev.max_residual) < 1e-9:
        status = "contact_unresolved"
        msg += (f"; but the contact residual {float(ev.max_residual):.1e} ≥ 1e-9 at the "
                f"fitted values (try more nodes)")
    if status != "converged":
        flags.append(f"the fit did not converge ({status}): {msg}")
    exp_idx = np.asarray(problem.data.exp)
    per = {name: float(np.sqrt(np.mean(r[exp_idx == i] ** 2)))
           for i, name in enumerate(problem.exp_names) if np.any(exp_idx == i)}
    tol = next((c.prior_sd * 1e3 for c in problem.columns if c.key == "clearance_mm"),
               math.inf)
    return FitResult(names=names, values=np.asarray(vals), stderr=np.asarray(se),
                     correlation=np.asarray(corr), u=np.asarray(u),
                     rmse_um=float(np.sqrt(np.mean(r ** 2))), rmse_per_experiment=per,
                     noise_um=float(out.noise_um), residuals_um=r, predicted_um=pred,
                     measured_um=meas, row_experiment=exp_idx, iterations=int(evaluations),
                     message=msg, flags=flags, problem=problem, evaluation=ev,
                     covariance=out.errors, snapshots_um=ev.snaps,
                     max_contact_residual=float(ev.max_residual),
                     integration=integration_report(problem, ev), status=status,
                     noise=noise, error_scale_um=float(out.error_scale_um),
                     error_dof=float(out.error_dof), step_se=float(out.step_se),
                     clearance_tolerance_um=tol)
