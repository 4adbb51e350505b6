"""A loaded law used beyond the states it was fitted on (issue 48 item 2; docs/design.md §7
`shape.law`): `law.py` carries the range of each of its variables met where it was fitted
(`state_range`: the wear-weighted 0.5-99.5 % quantiles, the steps' for a deposit), and
calibrate and predict flag a study whose states go beyond it, where the answer is the
law's extrapolation and not what the data it was learned from showed.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from jaxwear._physics.effects._base import get_effect, registered_effects
from jaxwear._physics.effects.law import DERIVED, derived_states, variable_unit

# a range met this far (a share of the fitted range's span) beyond the fitted one is flagged:
# the quantiles of a distribution met at other numerics move by a few per cent
SLACK = 0.05


def law_ranges(study) -> dict:
    """{effect name: {variable: (lo, hi)}} of the study's effects that carry the range of
    states they were fitted on (`state_range`, e.g. a `law.py`)."""
    out = {}
    known = registered_effects()
    for name in getattr(study.config, "effects", ()):
        if name not in known:
            continue
        rng = getattr(get_effect(name), "state_range", None)
        if isinstance(rng, dict) and rng:
            out[name] = {k: (float(lo), float(hi)) for k, (lo, hi) in rng.items()}
    return out


def met(problem, evaluation, variables, deposit: bool) -> dict:
    """{variable: (lo, hi)}: the range of each of `variables` met by the model `problem`
    (an extended or residual model: `cfg`, `batched_params`) at `evaluation` (its answer:
    `u`, `snaps`, `sliding_m`), as a law's range was measured (`law.search.states_met`)."""
    # here, not at the top: calibrate and predict import this module, and a plain
    # `import jaxwear` must not import the diagnose package (only a loaded law needs it)
    from jaxwear._analyses.diagnose.law.start import joint_states
    from jaxwear._analyses.diagnose.shape.design import RANGE_QUANTILES, _weighted_quantiles

    names = tuple(dict.fromkeys(v for n in variables
                                for v in (DERIVED[n][1] if n in DERIVED else (n,))))
    Z, w = joint_states(SimpleNamespace(ext=problem), SimpleNamespace(ev=evaluation), names,
                        deposit=deposit)
    if len(w) == 0:
        return {}
    if any(n in DERIVED for n in variables):
        Z = derived_states(Z)
    out = {}
    for n in variables:
        if n in Z:
            q = _weighted_quantiles(np.asarray(Z[n], float), w, np.asarray(RANGE_QUANTILES))
            out[n] = (float(q[0]), float(q[1]))
    return out


def beyond(fitted: dict, seen: dict) -> list[tuple]:
    """(variable, fitted (lo, hi), seen (lo, hi)) where `seen` goes beyond `fitted` by more
    than `SLACK` of its span at either end."""
    out = []
    for k, (lo, hi) in fitted.items():
        if k not in seen:
            continue
        slo, shi = seen[k]
        tol = SLACK * max(hi - lo, abs(hi) * 1e-9, 1e-300)
        if slo < lo - tol or shi > hi + tol:
            out.append((k, (lo, hi), (slo, shi)))
    return out


def range_flags(study, problem, evaluation, extra: dict | None = None) -> list[str]:
    """One flag per loaded law (`law_ranges`) and variable whose states met at the answer
    (`met`), or in `extra` ({variable: (lo, hi)}: what a forecast reaches beyond the
    training data), go beyond the range the law was fitted on. [] where no loaded effect
    carries a range."""
    out = []
    for name, fitted in law_ranges(study).items():
        deposit = bool(getattr(get_effect(name), "uses_swept_kernel", False))
        try:
            seen = met(problem, evaluation, tuple(fitted), deposit)
        except Exception as e:  # noqa: BLE001 (a flag is advice: never the answer's failure)
            out.append(f"law {name}: the states met could not be checked against the range "
                       f"it was fitted on ({type(e).__name__}: {e})")
            continue
        for k, (elo, ehi) in (extra or {}).items():
            if k in seen:
                seen[k] = (min(seen[k][0], elo), max(seen[k][1], ehi))
        for k, (lo, hi), (slo, shi) in beyond(fitted, seen):
            u = variable_unit(k)
            out.append(f"law {name} used beyond the states it was fitted on: {k} "
                       f"{slo:.4g} to {shi:.4g} {u} met here, fitted on {lo:.4g} to "
                       f"{hi:.4g} {u}: there the answer is the law's extrapolation, not "
                       f"what its data showed")
    return out
