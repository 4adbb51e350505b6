"""jaxwear: a differentiable wear model for revolute clearance joints.

Importing jaxwear switches JAX to float64 (`jax_enable_x64`). This is deliberate and the
only global JAX setting the package touches: wear depths are micrometres on 50 µm clearances
accumulated over 10⁴-10⁵ revolutions, which float32 cannot resolve. (In the command line's
own process, `jaxwear ...` or `python -m jaxwear`, it also makes Ctrl-C one line:
`_interrupt`.) Before JAX's CPU backend starts, it asks XLA:CPU for its faster-compiling
legacy emitters (`_xla_flags`: same run time, ~1.7x faster compilation), unless `XLA_FLAGS`
or `JAXWEAR_XLA_DEFAULTS=0` say otherwise.
"""

from . import _interrupt

_interrupt.guard_import()  # the command line: Ctrl-C while JAX imports is one line

from . import _xla_flags  # noqa: E402

_xla_flags.apply()  # XLA:CPU's faster-compiling emitters, before its backend starts

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from ._budget import WorkEstimate as WorkEstimate  # noqa: E402
from ._budget import check_work as check_work  # noqa: E402
from ._budget import estimate_work as estimate_work  # noqa: E402
from ._calibrate import FitError as FitError  # noqa: E402
from ._calibrate import FitResult as FitResult  # noqa: E402
from ._calibrate import calibrate as calibrate  # noqa: E402
from ._config import DutyBlock as DutyBlock  # noqa: E402
from ._config import ModelConfig as ModelConfig  # noqa: E402
from ._contact import ContactSolution as ContactSolution  # noqa: E402
from ._contact import solve_contact as solve_contact  # noqa: E402
from ._contact import stiffness_per_area as stiffness_per_area  # noqa: E402
from ._errors import InputError as InputError  # noqa: E402
from ._errors import WornThroughError as WornThroughError  # noqa: E402
from ._io import input_files as input_files  # noqa: E402
from ._io import open_outputs as open_outputs  # noqa: E402
from ._load import LoadHistory as LoadHistory  # noqa: E402
from ._load import load_history as load_history  # noqa: E402
from ._load_file import LoadCycle as LoadCycle  # noqa: E402
from ._load_file import make_cycle as make_cycle  # noqa: E402
from ._load_file import read_load_file as read_load_file  # noqa: E402
from ._mechanism import crank_slider_forces as crank_slider_forces  # noqa: E402
from ._parallel import points_mesh as points_mesh  # noqa: E402
from ._parallel import sharded_fn as sharded_fn  # noqa: E402
from ._parallel import sharded_vmap as sharded_vmap  # noqa: E402
from ._params import Params as Params  # noqa: E402
from ._params import preset as preset  # noqa: E402
from ._predict import PredictResult as PredictResult  # noqa: E402
from ._predict import predict as predict  # noqa: E402
from ._schedule import Schedule as Schedule  # noqa: E402
from ._schedule import make_schedule as make_schedule  # noqa: E402
from ._sensitivity import Sensitivities as Sensitivities  # noqa: E402
from ._sensitivity import sensitivities as sensitivities  # noqa: E402
from ._sensitivity import study_sensitivities as study_sensitivities  # noqa: E402
from ._study import Experiment as Experiment  # noqa: E402
from ._study import Study as Study  # noqa: E402
from ._study import load_study as load_study  # noqa: E402
from ._sweep import SweepResult as SweepResult  # noqa: E402
from ._sweep import sweep as sweep  # noqa: E402
from ._synth import SynthResult as SynthResult  # noqa: E402
from ._synth import synthesize as synthesize  # noqa: E402
from ._wear import WearResult as WearResult  # noqa: E402
from ._wear import build_schedule as build_schedule  # noqa: E402
from ._wear import simulate as simulate  # noqa: E402
from ._wear import wear_loop as wear_loop  # noqa: E402
from .cli.diagnose import write_outputs as write_diagnosis  # noqa: E402

# Binds `jaxwear.diagnose` to the function (the package stays importable by name,
# `from jaxwear.diagnose import Model`).
from .diagnose import diagnose as diagnose  # noqa: E402
from .effects import Effect as Effect  # noqa: E402
from .effects import EffectParameter as EffectParameter  # noqa: E402
from .effects import register_effect as register_effect  # noqa: E402
from .effects import unregister_effect as unregister_effect  # noqa: E402

__version__ = "0.1.0"

# The public API: what the README, docs/ and calibration/examples use. Everything else is
# private (underscore modules) and may change without notice.
__all__ = [
    "ContactSolution", "DutyBlock", "Effect", "EffectParameter", "Experiment", "FitError",
    "FitResult", "InputError", "LoadCycle", "LoadHistory", "ModelConfig", "Params", "PredictResult",
    "Schedule",
    "Sensitivities", "Study", "SweepResult", "SynthResult", "WearResult", "WorkEstimate",
    "WornThroughError", "build_schedule", "calibrate", "check_work", "crank_slider_forces",
    "diagnose", "estimate_work", "input_files", "load_history", "load_study", "make_cycle",
    "make_schedule", "read_load_file",
    "open_outputs", "points_mesh", "predict", "preset", "register_effect", "sensitivities",
    "sharded_fn", "sharded_vmap", "simulate", "solve_contact", "stiffness_per_area",
    "study_sensitivities", "sweep", "synthesize", "unregister_effect", "wear_loop",
    "write_diagnosis",
]
