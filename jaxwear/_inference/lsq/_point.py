"""What the core needs of one model evaluation."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Point:
    """One evaluation of a least-squares model at u.

    - `u` (P,): the parameters, in the fit's parameterisation.
    - `r` (n,): data residuals, model − measured [µm]; `predicted` (n,) the model [µm].
    - `J` (n, P): d r / d u.
    - `r_prior` (m,), `J_prior` (m, P): prior rows in units of their standard deviation
      (dimensionless, e.g. (c − c_nominal)/τ); the core weights the data rows by the noise
      level instead, so the prior's weight needs no re-evaluation when the noise changes.
    - `usable`: False where the model wore through the layer or is not finite (a trial
      there is rejected; a start there is moved by `robust_start`).
    - `error_um`: the model's own numerical error estimate at u [µm] (the integrator's),
      0 where none is known. It sets the floor below which a decrease of the misfit is
      not evidence of progress.
    - `extra`: the caller's full evaluation (snapshots, contact residual, ...).
    - `why`: where not usable, the cause in words (worn through at cycle ..., work
      estimate not finite, ...): the progress line of a rejected trial and the message of
      a start that fails name it.
    """

    u: np.ndarray
    r: np.ndarray
    predicted: np.ndarray
    J: np.ndarray
    r_prior: np.ndarray
    J_prior: np.ndarray
    usable: bool
    error_um: float = 0.0
    extra: Any = None
    why: str = ""

    @property
    def rms_um(self) -> float:
        return float(np.sqrt(np.mean(self.r ** 2))) if self.r.size else 0.0
