"""The effect interface, public: what an effect file imports (docs/effects.md).

An effect is a candidate piece of physics the base model may be missing (docs/design.md §5):
a small `Effect` subclass with named strength parameters (`EffectParameter`) whose hooks
change the local wear rate, the contact or add wear not tied to sliding. This module only
re-exports; the implementations live in `jaxwear._physics.effects`.
"""

from jaxwear._physics.effects import (
    STRUCTURAL_CANDIDATES,
    Creep,
    Effect,
    EffectParameter,
    Friction,
    PressureExponent,
    RateContext,
    RunningIn,
    SpeedDependence,
    effect_parameter_specs,
    get_effect,
    register_effect,
    registered_effects,
    safe_power,
    unregister_effect,
)
from jaxwear._physics.effects.shape import state_variables, swept_kernel
from jaxwear._study.effect_files import load_effect_file, load_effect_files

__all__ = [
    "STRUCTURAL_CANDIDATES", "Creep", "Effect", "EffectParameter", "Friction",
    "PressureExponent", "RateContext", "RunningIn", "SpeedDependence", "effect_parameter_specs",
    "get_effect", "load_effect_file", "load_effect_files", "register_effect",
    "registered_effects", "safe_power", "state_variables", "swept_kernel", "unregister_effect",
]
