"""What `predict` returns: forecasts with their bands, lives, and the design.md §7 JSON."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from jaxwear._core.jsonfmt import json_float as _jf


@dataclass(frozen=True)
class Prediction:
    """Maximum depth forecast at one point. `at` in `unit` (revolutions or hours); depths µm.
    `lower_um/upper_um`: prediction band (a new measurement); `conf_*`: the model's depth."""

    experiment: str
    at: float
    unit: str
    depth_um: float
    lower_um: float
    upper_um: float
    measured_um: float | None
    conf_lower_um: float
    conf_upper_um: float
    sd_model_um: float
    sd_prediction_um: float

    def to_json(self) -> dict:
        return {k: _jf(v) if isinstance(v, float) else v for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class Life:
    """When the maximum depth reaches `limit_um`: `at` (central forecast), `lower`/`upper`
    (prediction band's crossings), in `unit`; None where not reached, with `reason`."""

    experiment: str
    limit_um: float
    at: float | None
    lower: float | None
    upper: float | None
    unit: str
    reason: str | None = None
    # the found crossings (at, lower, upper) are each within this of the model's own, in
    # `unit`: the widest grid bracket holding one (maximum depth never decreases)
    numerical_error_bound: float | None = None
    # ((t_before, t_after, crossing), ...) of the found crossings: where refining helps
    brackets: tuple = field(default=(), repr=False)

    def to_json(self) -> dict:
        d = {k: _jf(v) if isinstance(v, float) else v for k, v in self.__dict__.items()
             if k != "brackets"}
        if d["reason"] is None:
            d.pop("reason")
        return d


@dataclass(frozen=True)
class Curve:
    """Forecast vs count for one experiment (fan chart): arrays (points,)."""

    at: np.ndarray
    depth_um: np.ndarray
    lower_um: np.ndarray
    upper_um: np.ndarray
    conf_lower_um: np.ndarray
    conf_upper_um: np.ndarray
    valid: np.ndarray  # False once the layer is worn through (or not finite)


@dataclass(frozen=True)
class PredictResult:
    """Outcome of `predict`. `to_json()` gives the design.md §7 document plus diagnostics."""

    level: float
    method: str
    unit: str
    train_until: float | None
    trained_on: list
    predictions: list[Prediction]
    life: list[Life]
    parameters: dict  # name -> {value, stderr, lower, upper, unit}
    noise_um: float
    noise_given: bool
    dof: float  # degrees of freedom of the band's noise scale (inf: σ given, not widened)
    quantile: float
    fit_converged: bool
    fit_message: str
    flags: list
    curves: dict = field(repr=False)  # experiment -> Curve
    profiles: dict = field(repr=False)  # experiment -> dict of arrays (last --at point)
    measured: dict = field(repr=False)  # experiment -> (points, max depth µm, trained?)
    extra: dict = field(default_factory=dict)
    fit_resolution: dict | None = None  # the fit's spatial resolution and its check
    fit_evaluations: int | None = None  # model evaluations of the fit, checks included
    noise_source: str = ""  # how the noise level was obtained (`_noise.Noise.describe`)
    outside: list = field(default_factory=list)  # answers outside the model (`_outside`)

    def to_json(self) -> dict:
        doc = {
            "level": self.level,
            "method": self.method,
            "trained_on": self.trained_on,
            "predictions": [p.to_json() for p in self.predictions],
            "life": [x.to_json() for x in self.life],
            "unit": self.unit,
            "train_until": self.train_until,
            "bands": {"lower_um/upper_um": "prediction band: where a new measurement of the "
                                            "maximum depth falls (model and noise)",
                      "conf_lower_um/conf_upper_um": "confidence band: the model's depth "
                                                     "(parameter uncertainty only)"},
            "parameters": self.parameters,
            "noise_um": _jf(self.noise_um),
            "noise": self.noise_source or ("given" if self.noise_given
                                           else "estimated from the training residuals"),
            "dof": _jf(self.dof),
            "quantile": _jf(self.quantile),
            "fit": {"converged": self.fit_converged, "message": self.fit_message,
                    "resolution": self.fit_resolution,
                    "model_evaluations": self.fit_evaluations},
            "flags": list(self.flags),
            "outside_model": list(self.outside),
        }
        doc.update(self.extra)
        return doc


