"""Candidate effects (design.md §5): one small module each, registered by name.

`registered_effects()` are the parametric candidates (hooks into the wear loop);
`STRUCTURAL_CANDIDATES` the model choices `unsymmetric` and `double_layer`. docs/effects.md
explains how to add your own; `load_effect_file` registers those a Python file defines (a
study's `[model] effect_files`).
"""

from jaxwear._physics.effects._base import (
    Effect,
    RateContext,
    effect_parameter_specs,
    get_effect,
    product_pairs,
    project_products,
    register_effect,
    registered_effects,
    safe_power,
    unregister_effect,
)
from jaxwear._physics.effects.creep import Creep
from jaxwear._physics.effects.friction import Friction
from jaxwear._physics.effects.parameter import EffectParameter
from jaxwear._physics.effects.pressure_exponent import PressureExponent
from jaxwear._physics.effects.running_in import RunningIn
from jaxwear._physics.effects.speed_dependence import SpeedDependence
from jaxwear._physics.effects.structural import STRUCTURAL_CANDIDATES, StructuralCandidate

for _e in (RunningIn(), SpeedDependence(), PressureExponent(), Friction(), Creep()):
    register_effect(_e)

# Names a study may list in `effects` that switch a model choice rather than add a term.
STRUCTURAL = tuple(STRUCTURAL_CANDIDATES)

__all__ = [
    "Creep",
    "Effect",
    "EffectParameter",
    "Friction",
    "PressureExponent",
    "RateContext",
    "RunningIn",
    "STRUCTURAL_CANDIDATES",
    "SpeedDependence",
    "StructuralCandidate",
    "effect_parameter_specs",
    "get_effect",
    "product_pairs",
    "project_products",
    "register_effect",
    "registered_effects",
    "safe_power",
    "unregister_effect",
]
