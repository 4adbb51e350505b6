"""Candidate effects (DESIGN §5): one small module each, registered by name.

`registered_effects()` are the parametric candidates (hooks into the wear loop);
`STRUCTURAL_CANDIDATES` the model choices `unsymmetric` and `double_layer`. docs/effects.md
explains how to add your own; `load_effect_file` registers those a Python file defines (a
study's `[model] effect_files`).
"""

from ._base import Effect as Effect
from ._base import EffectParameter as EffectParameter
from ._base import RateContext as RateContext
from ._base import effect_parameter_specs as effect_parameter_specs
from ._base import get_effect as get_effect
from ._base import product_pairs as product_pairs
from ._base import project_products as project_products
from ._base import register_effect as register_effect
from ._base import registered_effects as registered_effects
from ._base import safe_power as safe_power
from ._base import unregister_effect as unregister_effect
from ._files import load_effect_file as load_effect_file
from ._files import load_effect_files as load_effect_files
from .creep import Creep as Creep
from .friction import Friction as Friction
from .pressure_exponent import PressureExponent as PressureExponent
from .running_in import RunningIn as RunningIn
from .speed_dependence import SpeedDependence as SpeedDependence
from .structural import STRUCTURAL_CANDIDATES as STRUCTURAL_CANDIDATES
from .structural import StructuralCandidate as StructuralCandidate

for _e in (RunningIn(), SpeedDependence(), PressureExponent(), Friction(), Creep()):
    register_effect(_e)

# Names a study may list in `effects` that switch a model choice rather than add a term.
STRUCTURAL = tuple(STRUCTURAL_CANDIDATES)
