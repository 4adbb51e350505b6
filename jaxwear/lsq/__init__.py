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

from .._errors import FitError as FitError
from .._errors import TrialFailed as TrialFailed
from ._covariance import Covariance as Covariance
from ._covariance import covariance as covariance
from ._covariance import gauss_newton as gauss_newton
from ._point import Point as Point
from ._solve import SE_TOL as SE_TOL
from ._solve import NoiseUndetermined as NoiseUndetermined
from ._solve import Outcome as Outcome
from ._solve import error_scale as error_scale
from ._solve import failure as failure
from ._solve import solve as solve
from ._solve import step_in_standard_errors as step_in_standard_errors
from ._solve import whitened as whitened
from ._start import robust_start as robust_start
