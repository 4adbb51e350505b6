"""Frozen result types of a diagnosis and the design.md §7 JSON document."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from jaxwear._analyses.diagnose._evidence import derived, rmse_per_experiment, where_it_fails
from jaxwear._analyses.diagnose._fit import Fit
from jaxwear._analyses.diagnose._model import Model
from jaxwear._analyses.diagnose._screen import Screen
from jaxwear._analyses.diagnose._stats import ALPHA, Tests
from jaxwear._study.outside import parameter_flags
from jaxwear._study.study import Study


@dataclass(frozen=True)
class Candidate:
    """One candidate effect of a diagnosis, best first in `Diagnosis.candidates`.

    - `effect`: its name (a registered effect, a structural choice, or a pair `a + b`).
    - `screen`: its score test at the base fit; `fit`: its refit (None: screened only).
    - `evidence`: log Bayes factor against the base model (Laplace; > 0 favours it).
    - `rmse_um`: RMSE of the study with it refitted [µm]; `tests`: its misfit tests.
    """

    effect: str
    screen: Screen | None
    fit: Fit | None
    evidence: float
    rmse_um: float
    tests: Tests | None = None

    @property
    def refit(self) -> bool:
        return self.fit is not None


@dataclass(frozen=True)
class Diagnosis:
    """Everything `diagnose` found; `to_json()` is the design.md §7 document."""

    study: Study
    model: Model
    noise_um: float
    noise_dof: float
    base: Fit
    base_tests: Tests
    screens: list
    candidates: list  # Candidate, best first
    status: str
    effects: list  # names explaining the misfit (effect_found), else []
    partial: list  # names that explain part of it (partly_explained)
    alternatives: list  # candidates the data cannot tell apart from the winner
    final: Fit  # the model after (the winner, or the base)
    final_tests: Tests
    loo_before: dict
    loo_after: dict
    summary: str = ""  # at most five short sentences (`_headline.summary`)
    wall_s: float = 0.0
    log: list = field(default_factory=list)
    compare_fits: dict = field(default_factory=dict)
    resolution: dict | None = None  # the spatial resolution used and its check (design.md §6)
    shape: object = None  # _shape.ShapeResult on top of the base fit (--shape, unexplained)
    shape_after_effect: object = None  # the same on top of the effect found
    # what the answer cost: model evaluations (calibrate's path, then diagnose's own) and
    # compilations by kind (`_residual.traces_since`)
    cost: dict = field(default_factory=dict)
    # candidates whose refit was not usable (`Fit.usable`: unstable derivatives, a model
    # that did not run): they could not be compared
    failed: list = field(default_factory=list)
    # the screen found candidates promising and none was refitted to an answer (`settle`)
    unresolved: bool = False
    # the library's answer weighed against the grammar's best law (`_verdict.contested`,
    # `law_against_library`), or None where it was not contested
    law_contest: dict | None = None
    # what the verdict rests on that a reader must know (the numerics it changed)
    flags: list = field(default_factory=list)
    headline: str = ""  # the answer in one line (`_headline.headline`)
    details: str = ""  # the long text: the verdict's paragraph, the shape's, the law's

    @property
    def confident(self) -> bool:
        """False where the verdict names an effect the data cannot tell from another,
        where a candidate's refit failed (it could not be compared: the verdict might have
        been another with it), or where the screen's promise was not resolved."""
        return (not self.failed and not self.unresolved
                and (self.status != "effect_found" or not self.alternatives))

    @property
    def missing_effect(self):
        return self.effects[0] if self.effects else None

    def parameters_json(self, fit: Fit) -> dict:
        out = {}
        for i in np.flatnonzero(fit.mask):
            se = fit.stderr[i] if fit.stderr is not None else math.nan
            out[self.model.names[i]] = {"value": float(fit.values[i]),
                                        "stderr": float(se) if math.isfinite(se) else None}
        out.update({k: {"value": v, "stderr": se if math.isfinite(se) else None, "derived": True}
                    for k, (v, se) in derived(self.model, fit).items()})
        return out

    def outside_model(self, *parameter_sets) -> list[str]:
        """`_outside.parameter_flags` of the fitted (not derived) values of the base model
        and of the model after, once each."""
        flags = []
        for params in parameter_sets:
            fitted = {k: v["value"] for k, v in params.items() if not v.get("derived")}
            flags += parameter_flags(list(fitted), list(fitted.values()), self.study.preset)
        return list(dict.fromkeys(flags))

    def to_json(self) -> dict:
        m = self.model
        cands = []
        for c in self.candidates:
            d = {"effect": c.effect, "rmse_um": c.rmse_um, "evidence": c.evidence,
                 "refit": c.refit}
            if c.fit is not None:
                d["parameters"] = self.parameters_json(c.fit)
                d["converged"] = c.fit.converged
                d["fit_status"] = c.fit.status
                d["model_evaluations"] = c.fit.evaluations
                d["flags"] = c.fit.flags
            else:
                d["parameters"] = {k: {"value": v, "stderr": None}
                                   for k, v in (c.screen.start if c.screen else {}).items()}
            if c.screen is not None:
                d.update(score=c.screen.score, p_score=c.screen.p,
                         explained_fraction=c.screen.explained)
            if c.tests is not None:
                d["at_noise_level"] = not c.tests.systematic
                d["tests"] = c.tests.to_json()
            cands.append(d)
        base = {"rmse_um": self.base.rmse, "noise_um": self.noise_um,
                "parameters": self.parameters_json(self.base),
                "noise_dof": self.noise_dof, "rmse_per_experiment_um":
                    rmse_per_experiment(m, self.base.ev.r),
                "loo_rmse_per_experiment_um": self.loo_before,
                "loo_rmse_um": _mean_sq(self.loo_before), "tests": self.base_tests.to_json(),
                "converged": self.base.converged, "fit_status": self.base.status,
                "model_evaluations": self.base.evaluations, "flags": self.base.flags,
                "n_data": m.n, "resolution": self.resolution,
                "where_it_fails": where_it_fails(m, self.base.ev.r),
                "integration": m.integration(self.base.ev)}
        after = {"model": self.final.label, "effects": list(self.final.groups),
                 "rmse_um": self.final.rmse,
                 "rmse_per_experiment_um": rmse_per_experiment(m, self.final.ev.r),
                 "loo_rmse_per_experiment_um": self.loo_after,
                 "loo_rmse_um": _mean_sq(self.loo_after),
                 "parameters": self.parameters_json(self.final),
                 "tests": self.final_tests.to_json(),
                "integration": m.integration(self.final.ev)}
        return {
            "baseline": base,
            "candidates": cands,
            "verdict": {"status": self.status, "missing_effect": self.missing_effect,
                        "headline": self.headline, "summary": self.summary,
                        "details": self.details, "effects": list(self.effects),
                        "partial": list(self.partial), "alternatives": list(self.alternatives),
                        "confident": self.confident, "refits_failed": list(self.failed),
                        "flags": list(self.flags),
                        **({"law_against_library": {k: v for k, v in self.law_contest.items()
                                                    if k != "sentence"}}
                           if self.law_contest else {})},
            "after": after,
            "outside_model": self.outside_model(base["parameters"], after["parameters"]),
            **({"shape": self.shape.to_json()} if self.shape is not None else {}),
            **({"shape_after_effect": self.shape_after_effect.to_json()}
               if self.shape_after_effect is not None else {}),
            "study": str(self.study.path),
            "wall_time_s": self.wall_s,
            "model_evaluations": self.cost.get("model_evaluations"),
            "compiles": (None if "compiles" not in self.cost
                         else int(sum(self.cost["compiles"].values()))),
            "cost": self.cost,
            "method": METHOD_NOTE,
        }


METHOD_NOTE = (
    "noise: rms of each residual minus the line through its two neighbours (angle order), "
    "normalised; misfit is systematic when a Bonferroni combination of a chi-square test "
    "(RSS/(n-k) against the noise level), a lag-1 autocorrelation test of angle-ordered "
    f"residuals and the candidates' score tests rejects at alpha = {ALPHA:g}; evidence = "
    "ln Bayes factor against the base model, BIC approximation with the noise level "
    "unknown; an effect is named when its evidence is very strong (> ln 150) and its "
    "residuals pass the same tests; leave-one-experiment-out errors are one Gauss-Newton "
    "step from the full fit.")


def _mean_sq(d: dict) -> float | None:
    return float(np.sqrt(np.mean(np.square(list(d.values()))))) if d else None
