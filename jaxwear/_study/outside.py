"""Answers outside the model, said loudly (issue 41).

A study stated symmetric with strongly unsymmetric data fitted K_d = 4.2e-16 (truth
1.4e-13) and forecast 0.027 µm [-1.03, 1.08] at 3000 revolutions where 3.3 µm had already
been measured at 2000; a fitted clearance of 6.2e-12 mm was flagged "not identifiable".
Both are answers the model gives outside what it describes, and they come first:

- `parameter_flags`: a fitted value outside the plausible range its key is held to as an
  input (`_plausible.key_range`: the table of docs/plausibility.md, an effect strength's
  own bounds), or held at an end of it by the fit's bound (a clearance: the fit is bounded
  by that range, `_packing.clearance_bounds_mm`);
- `forecast_flags`: a forecast whose prediction band lies wholly below a depth already
  measured at or before its count (maximum depth never decreases), by more than three
  noise levels (a scan's maximum is the largest of many noisy points).

Each flag starts with `OUTSIDE`: calibrate, predict and diagnose put them first among their
flags and in their JSON under `outside_model`, and print them in their first lines.
"""

from __future__ import annotations

import math

import numpy as np

from jaxwear._study.plausible import key_range

OUTSIDE = "OUTSIDE THE MODEL"
NOISE_LEVELS = 3.0  # a forecast band this many noise levels below a measured depth


def parameter_flags(names, values, preset: str | None) -> list[str]:
    """One flag per fitted value (`names` as output: "clearance_mm/EXP" is checked against
    "clearance_mm") outside its key's plausible range, or not finite."""
    out = []
    for name, v in zip(names, values):
        r = key_range(str(name).split("/")[0], preset)
        if r is None:
            continue
        v = float(v)
        if not math.isfinite(v) or v not in r:
            out.append(f"{OUTSIDE}: {name} = {v:.4g} was fitted outside the plausible range "
                       f"{r} that the inputs are held to ({r.reason}): the fit left the "
                       f"model's range instead of measuring within it; its other answers "
                       f"are not to be trusted (`jaxwear diagnose` looks for the physics "
                       f"the model lacks)")
        elif _held_at_edge(str(name).split("/")[0], v, r):
            edge = "lower" if abs(v - r.lo) <= abs(v - r.hi) else "upper"
            out.append(f"{OUTSIDE}: {name} = {v:.4g} is held at the {edge} end of the "
                       f"plausible range {r} ({r.reason}) by the fit's bound: the data pull "
                       f"it further, out of the model's range; its other answers are not to "
                       f"be trusted (`jaxwear diagnose` looks for the physics the model "
                       f"lacks)")
    return out


# fitted study keys whose plausible range is also the fit's bound (`_packing.study_columns`)
BOUNDED_BY_RANGE = ("clearance_mm",)


def _held_at_edge(key: str, v: float, r) -> bool:
    """A fitted value at (to 1e-6 relative) an end of its plausible range where the fit
    holds that key to the range: the bound, not the data, set it."""
    if key not in BOUNDED_BY_RANGE:
        return False
    return any(math.isfinite(e) and abs(v - e) <= 1e-6 * max(abs(e), 1e-300)
               for e in (r.lo, r.hi))


def forecast_flags(predictions, measured: dict, noise_um: float, unit: str) -> list[str]:
    """One flag per forecast (`Prediction`) whose band's upper end is below the largest
    depth measured at or before its count by more than `NOISE_LEVELS` noise levels.
    `measured`: experiment -> (counts, maximum depth µm at each, ...) (`PredictResult`)."""
    out = []
    sigma = float(noise_um) if math.isfinite(float(noise_um)) else 0.0
    for p in predictions:
        if p.experiment not in measured:
            continue
        pts, depth = (np.asarray(a, float) for a in measured[p.experiment][:2])
        before = pts <= p.at * (1 + 1e-12)
        if not np.any(before):
            continue
        k = int(np.flatnonzero(before)[np.argmax(depth[before])])
        top = float(depth[k])
        upper = float(p.upper_um) if p.upper_um is not None else float(p.depth_um)
        if upper < top - NOISE_LEVELS * sigma:
            out.append(f"{OUTSIDE}: {p.experiment} forecast {p.depth_um:.4g} µm [band up to "
                       f"{upper:.4g}] at {p.at:g} {unit}, below the {top:.4g} µm already "
                       f"measured at {pts[k]:g} {unit} (wear never shrinks): the fitted model "
                       f"does not describe these data (`jaxwear diagnose`)")
    return out


def loud_lines(flags) -> list[str]:
    """The `OUTSIDE` flags as the first lines of a verb's output."""
    return [f"WARNING: {f}" for f in flags if str(f).startswith(OUTSIDE)]
