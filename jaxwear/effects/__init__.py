"""Candidate effects (DESIGN §5): one small module each, registered by name."""

from ._base import Effect as Effect
from ._base import EffectParameter as EffectParameter
from ._base import RateContext as RateContext
from ._base import effect_parameter_specs as effect_parameter_specs
from ._base import get_effect as get_effect
from ._base import register_effect as register_effect
from ._base import registered_effects as registered_effects
from .creep import Creep
from .friction import Friction
from .pressure_exponent import PressureExponent
from .running_in import RunningIn
from .speed_dependence import SpeedDependence

for _e in (RunningIn(), SpeedDependence(), PressureExponent(), Friction(), Creep()):
    register_effect(_e)

# Structural candidates change a model choice rather than add a term (see diagnose).
STRUCTURAL = ("unsymmetric", "double_layer")
