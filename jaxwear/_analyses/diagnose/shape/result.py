"""What the shape analysis returns: the correction along each variable with its band and test,
the form's joint fit, the refitted correction and the law (JSON: design.md §7 `shape`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from jaxwear._analyses.diagnose.shape.linear import trend
from jaxwear._analyses.diagnose.shape.text import threshold
from jaxwear._core.jsonfmt import json_float as _num


@dataclass(frozen=True)
class VariableShape:
    """The correction along one variable in one form (JSON: `to_json`). `z`, `g` (factor:
    ln of the rate factor; deposit: e in nm·rad of depth per step) and the band on a grid
    over the range met in the data."""

    name: str
    unit: str
    form: str
    explained_fraction: float
    unique_fraction: float
    dof: float
    p_value: float
    significant: bool
    peak_at: float
    lower: float
    upper: float
    lam: float
    statistic: float  # T = ΔRSS/σ²
    aic: float
    z: np.ndarray = field(repr=False)
    g: np.ndarray = field(repr=False)
    g_lower: np.ndarray = field(repr=False)
    g_upper: np.ndarray = field(repr=False)
    coef: np.ndarray = field(repr=False)
    extra_wear_um: np.ndarray = field(repr=False)  # linearised Δdepth over the bore (N,)
    range: tuple = (0.0, 0.0)
    carries: bool = False  # its unique share is significant in the form's joint fit
    stand_in_for: str | None = None
    refit_rmse_um: float | None = None
    unique_p_value: float = float("nan")  # of its unique share in the joint fit

    @property
    def label(self) -> str:
        return self.name if self.form == "factor" else f"deposit:{self.name}"

    def threshold(self, rising: bool = True) -> float:
        """Where the correction steps up (`rising`; else down), in the variable's unit: the
        best two-level step fitted to it, weighted by its band (`shape.text.threshold`).
        For a rate that jumps at a threshold, the threshold."""
        return threshold(self, rising)

    def to_json(self) -> dict:
        return {"name": self.name, "unit": self.unit, "form": self.form,
                "explained_fraction": _num(self.explained_fraction),
                "unique_fraction": _num(self.unique_fraction), "dof": _num(self.dof),
                "p_value": _num(self.p_value), "significant": bool(self.significant),
                "peak_at": _num(self.peak_at), "lower": _num(self.lower),
                "upper": _num(self.upper), "range": [_num(self.range[0]), _num(self.range[1])],
                "penalty": _num(self.lam), "statistic": _num(self.statistic),
                "aic": _num(self.aic), "trend": _num(trend(self)),
                "carries_the_misfit": bool(self.carries), "stand_in_for": self.stand_in_for,
                "refit_rmse_um": _num(self.refit_rmse_um)}


@dataclass(frozen=True)
class ShapeResult:
    """The shape analysis on top of one fit (`after`: "base" or the effect's name)."""

    after: str
    best: str | None
    form: str | None
    variables: tuple  # VariableShape of both forms
    alpha: float
    noise_um: float
    rmse_before_um: float
    rmse_after_um: float | None  # with the refitted correction, through the loop
    evaluations: int
    status: str  # the refit's (lsq) status, or "none"
    sentence: str
    phase_load: dict = field(default_factory=dict, repr=False)  # for the phase plot
    bore_deg: np.ndarray = field(default=None, repr=False)
    experiment: str = ""  # whose bore the extra wear is drawn on
    alternatives: tuple = ()  # variable labels the data cannot tell from `best`
    forms: dict = field(default_factory=dict)  # form -> joint fit summary
    carriers: tuple = ()  # the variables of the refitted correction
    correction: dict = field(default_factory=dict, repr=False)  # for the effect file
    when_where: object = None  # shape.map.WhenWhere
    numerical: dict = field(default_factory=dict)
    effect_file: str | None = None
    design: object = field(default=None, repr=False)  # `Design`, for a later analysis
    pending: object = field(default=None, repr=False)  # the refit still to run (`defer`)
    pngs: dict = field(default_factory=dict, repr=False)  # figures drawn beforehand
    # the linearised system the variables were tested on (whitened, nuisance projected
    # off): {"blocks": {label: (A, S, Z, cols, var)}, "rho": misfit}, for the law search's
    # pre-screen (`law.search`)
    linear: dict = field(default_factory=dict, repr=False)
    law: object = None  # `law.search.LawResult`: the law found from the shape, or None
    # the surface over the leading pair (`shape.interaction.Interaction`), or None
    interaction: object = None
    confounded: tuple = ()  # labels the data cannot tell apart (`shape.choice`)
    # the command that tells the best variable from its rival (`shape.text.next_test`;
    # `jaxwear design --between shape:A,shape:B`), or None where none is tied with it
    next_test: str | None = None
    # the rows' residuals (model - measured) [µm] (rows,) with the refitted correction,
    # for the report's error table and profiles (None before the refit)
    residual_um: np.ndarray | None = field(default=None, repr=False, compare=False)
    # how the refit through the loop ended (the least-squares core's message, with the
    # starts that could not be evaluated before it); where `rmse_after_um` is None after a
    # refit, why it has none
    refit_message: str = ""
    # (the refit's model, u at its answer (P,)), for a later refit of the same correction
    # on the same model to start from (`shape.refit._warm_start`); None before the refit
    refit_at: object = field(default=None, repr=False, compare=False)
    # the adaptive wear tolerance the refit integrated at [µm] (`refit.REFIT_TOLERANCE`
    # times the study's), None without a refit or under the paper's integrator
    refit_tolerance_um: float | None = None


    def finished(self, warm: ShapeResult | None = None) -> ShapeResult:
        """This result with its refit run (itself if none is pending); `warm`: an earlier
        analysis whose refit's correction it starts from where it refits the same
        correction on the same model (`refit_at`, `shape.refit._warm_start`)."""
        if self.pending is None:
            return self
        return replace(self.pending(None if warm is None else warm.refit_at),
                       pngs=self.pngs)

    def settled_labels(self) -> tuple:
        """Labels of the variable figures the pending refit will not change (all but its
        carriers')."""
        refitted = {f"deposit:{n}" if self.form == "deposit" else n for n in self.carriers}
        return tuple(v.label for v in self.variables if v.label not in refitted)

    def form_variables(self, form: str | None = None) -> tuple:
        form = form or self.form or "factor"
        return tuple(v for v in self.variables if v.form == form)

    def to_json(self) -> dict:
        return {"after": self.after, "best": self.best, "form": self.form,
                "rmse_after_um": _num(self.rmse_after_um), "effect_file": self.effect_file,
                "variables": [v.to_json() for v in self.form_variables()],
                "other_form": {"form": _other(self.form or "factor"),
                               "variables": [v.to_json() for v in self.form_variables(
                                   _other(self.form or "factor"))]},
                "alternatives": list(self.alternatives),
                "confounded": list(self.confounded),
                "interaction": (None if self.interaction is None
                                else self.interaction.to_json()),
                "carriers": list(self.carriers),
                "forms": self.forms,
                "when_where": None if self.when_where is None else self.when_where.to_json(),
                "alpha": self.alpha, "noise_um": _num(self.noise_um),
                "rmse_before_um": _num(self.rmse_before_um),
                "model_evaluations": self.evaluations, "refit_status": self.status,
                "refit_message": self.refit_message or None,
                "refit_tolerance_um": _num(self.refit_tolerance_um),
                "numerical_error": self.numerical, "summary": self.sentence,
                "next_test": self.next_test,
                **({"law": self.law.to_json()} if self.law is not None else {})}

    def variable(self, name: str, form: str | None = None) -> VariableShape:
        form = form or self.form or "factor"
        return next(v for v in self.variables if v.name == name and v.form == form)


def _other(form: str) -> str:
    return "deposit" if form == "factor" else "factor"
