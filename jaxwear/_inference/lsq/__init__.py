"""The one least-squares core: every fit in jaxwear (calibrate, each diagnose refit, the
shape of the missing wear, the forecast's Laplace fit and the NUTS start) runs through
`solve`.

A caller supplies `evaluate(u) -> Point` (data residuals, their Jacobian, prior rows in
units of their standard deviation, whether the model was usable and its numerical error);
the core owns what every fit needs: the robust start, optimistix's Levenberg-Marquardt
pieces (`DampedNewtonDescent` proposes, `ClassicalTrustRegion` accepts and sets the
damping), bounds, masks of held parameters, the noise level re-estimated inside the loop,
the statistical stop, the budget and progress, and the covariance (one SVD of the scaled,
whitened Jacobian for the step, the stop and the errors) with undetermined directions
flagged, and the noise rule of the errors the data support (`error_scale`).
"""

from jaxwear._core.errors import FitError, TrialFailed
from jaxwear._inference.lsq._covariance import Covariance, covariance, gauss_newton
from jaxwear._inference.lsq._point import Point
from jaxwear._inference.lsq._solve import (
    SE_TOL,
    NoiseUndetermined,
    Outcome,
    defect_step,
    error_scale,
    failure,
    lower_core,
    solve,
    step_in_standard_errors,
    step_ratio,
    whitened,
)
from jaxwear._inference.lsq._start import robust_start
from jaxwear._inference.lsq._status import Status

__all__ = [
    "FitError",
    "TrialFailed",
    "failure",
    "Covariance",
    "NoiseUndetermined",
    "Outcome",
    "Point",
    "SE_TOL",
    "defect_step",
    "step_ratio",
    "Status",
    "covariance",
    "error_scale",
    "gauss_newton",
    "robust_start",
    "solve",
    "step_in_standard_errors",
    "lower_core",
    "whitened",
]
