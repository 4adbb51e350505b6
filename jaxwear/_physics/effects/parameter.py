"""`EffectParameter`: a named parameter of an effect, in the unit its study key names."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EffectParameter:
    """A parameter of an effect, in the unit its study key names.

    - `to_si`: factor from the key's unit to SI.
    - `default`: value used when the study does not set it (and when fitting starts, for
      shape parameters).
    - `off`: the value at which the effect vanishes (nesting). A *strength* parameter
      (`log=False`) starts every fit at `off`; diagnosis differentiates the model with
      respect to it there.
    - `lower`, `upper`: bounds of a fit (key's unit).
    - `doc`: one line with symbol, meaning and unit.
    - `log`: fitted in log space. Use it for strictly positive *shape* parameters (a
      distance, a time constant) that are not identifiable while the strength is off.
    - `scale`: typical size of a fitted change (key's unit); sets the fit's scaling.
    - `realistic`: strength that `jaxwear synth` hides by default: detectable in the
      paper's rig matrix at 0.3 µm noise, and plausible for the physics (see docs/effects.md).
    - `per`: the key of a `log` parameter of the same effect such that data fix the product
      of the two (running-in: the excess a·S_r, not a and S_r apart). Where both are
      fitted, the fit's coordinate of this one measures value·per/per_start (the product)
      instead of the value: the valley of equal products becomes a coordinate axis, which
      is what lets a quadratic model follow it. Values and outputs are unchanged.
    """

    to_si: float
    default: float
    off: float
    lower: float
    upper: float
    doc: str = ""
    log: bool = False
    scale: float = 1.0
    realistic: float | None = None
    per: str | None = None
