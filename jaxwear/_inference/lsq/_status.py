"""Why a fit stopped: one enumeration for every fit result (the core's, calibrate's, each
diagnose refit's). A `StrEnum`, so a status is its JSON string and compares equal to it."""

from __future__ import annotations

from enum import StrEnum


class Status(StrEnum):
    """How a least-squares fit ended.

    - `CONVERGED`: the next Gauss-Newton step moves every determined parameter by less than
      the stop's fraction of its standard error (or less than 0.1 standard error within the
      model's numerical error).
    - `STALLED`: trials kept being rejected or gaining nothing; the message says why.
    - `BUDGET`: the evaluation budget was spent first.
    - `UNUSABLE`: the model cannot be evaluated at the start (worn through, not finite).
    - `UNDETERMINED`: the data and priors determine none of the fitted parameters.
    """

    CONVERGED = "converged"
    STALLED = "stalled"
    BUDGET = "budget"
    UNUSABLE = "unusable"
    UNDETERMINED = "undetermined"
