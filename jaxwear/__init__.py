"""jaxwear: a differentiable wear model for revolute clearance joints.

This module is a façade: it re-exports the public API from the layer packages
(`_physics` → `_study` → `_inference` → `_analyses` → `_report`; docs/architecture.md).

Importing jaxwear switches JAX to float64 (`jax_enable_x64`). This is deliberate and the
only global JAX setting the package touches: wear depths are micrometres on 50 µm clearances
accumulated over 10⁴-10⁵ revolutions, which float32 cannot resolve. XLA's own settings are
left alone: jaxwear's own compiled programs ask XLA:CPU for its legacy emitters per program
(`_core.jit`: faster to compile and to run), and `configure_xla()` opts the whole process in
(the command line does so itself).
"""

from jaxwear._core import interrupt as _interrupt

_interrupt.guard_import()  # only in the command line's process: Ctrl-C while JAX imports

from typing import TYPE_CHECKING

import jax

jax.config.update("jax_enable_x64", True)

from jaxwear import effects  # the public effect interface (a façade module)
from jaxwear._core.errors import InputError, WornThroughError
from jaxwear._core.parallel import points_mesh, sharded_fn, sharded_vmap
from jaxwear._core.xla_flags import apply as configure_xla
from jaxwear._physics.config import DutyBlock, ModelConfig
from jaxwear._physics.contact import ContactSolution, solve_contact, stiffness_per_area
from jaxwear._physics.effects import Effect, EffectParameter, register_effect, unregister_effect
from jaxwear._physics.load import LoadHistory, load_history
from jaxwear._physics.load_cycle import LoadCycle
from jaxwear._physics.mechanism import crank_slider_forces
from jaxwear._physics.params import Params, preset
from jaxwear._physics.schedule import Schedule, make_schedule
from jaxwear._physics.wear import WearResult, build_schedule, simulate, wear_loop
from jaxwear._study.budget import WorkEstimate, check_work, estimate_work
from jaxwear._study.load_file import make_cycle, read_load_file
from jaxwear._study.outputs import input_files, open_outputs
from jaxwear._study.study import Experiment, Study, load_study

__version__ = "0.1.0"

if TYPE_CHECKING:  # for type checkers and the API docs (griffe); at run time: `_LAZY`
    from jaxwear._analyses.diagnose import Candidate, Diagnosis, ShapeResult, VariableShape
    from jaxwear._analyses.diagnose import diagnose as diagnose
    from jaxwear._analyses.predict.forecast import PredictResult, predict
    from jaxwear._analyses.sensitivity import Sensitivities, sensitivities, study_sensitivities
    from jaxwear._analyses.sweep import SweepResult, sweep
    from jaxwear._analyses.synth import SynthResult, synthesize
    from jaxwear._inference.calibrate import FitError, FitResult, calibrate
    from jaxwear._report.diagnosis import write_outputs as write_diagnosis

# Imported on first use (PEP 562): the diagnose package (and scipy.stats with it) is ~0.7 s
# of `import jaxwear`, which every verb and library user would otherwise pay; the fits and
# the analyses on them (optimistix, lineax and the least-squares core with them) another
# 0.3-0.6 s (measured 2026-11-29 on a 2-core AMD EPYC where `import jax` alone takes
# 0.7-0.8 s: `import jaxwear` 1.5-1.8 s with them, 0.9-1.2 s without), which a user who
# only simulates does not need.
_LAZY = {"PredictResult": ("jaxwear._analyses.predict.forecast", "PredictResult"),
         "predict": ("jaxwear._analyses.predict.forecast", "predict"),
         "Sensitivities": ("jaxwear._analyses.sensitivity", "Sensitivities"),
         "sensitivities": ("jaxwear._analyses.sensitivity", "sensitivities"),
         "study_sensitivities": ("jaxwear._analyses.sensitivity", "study_sensitivities"),
         "SweepResult": ("jaxwear._analyses.sweep", "SweepResult"),
         "sweep": ("jaxwear._analyses.sweep", "sweep"),
         "SynthResult": ("jaxwear._analyses.synth", "SynthResult"),
         "synthesize": ("jaxwear._analyses.synth", "synthesize"),
         "FitError": ("jaxwear._inference.calibrate", "FitError"),
         "FitResult": ("jaxwear._inference.calibrate", "FitResult"),
         "calibrate": ("jaxwear._inference.calibrate", "calibrate"),
         "Candidate": ("jaxwear._analyses.diagnose", "Candidate"),
         "Diagnosis": ("jaxwear._analyses.diagnose", "Diagnosis"),
         "ShapeResult": ("jaxwear._analyses.diagnose", "ShapeResult"),
         "VariableShape": ("jaxwear._analyses.diagnose", "VariableShape"),
         "diagnose": ("jaxwear._analyses.diagnose", "diagnose"),
         "write_diagnosis": ("jaxwear._report.diagnosis", "write_outputs")}


def __getattr__(name):
    if name not in _LAZY:
        raise AttributeError(f"module 'jaxwear' has no attribute {name!r}")
    import importlib

    module, attr = _LAZY[name]
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


# The public API: what the README, docs/ and calibration/examples use. Everything else is
# private (underscore packages) and may change without notice.
__all__ = [
    "Candidate", "ContactSolution", "Diagnosis", "DutyBlock", "Effect", "EffectParameter",
    "Experiment", "FitError", "FitResult", "InputError", "LoadCycle", "LoadHistory",
    "ModelConfig", "Params", "PredictResult", "Schedule", "Sensitivities", "ShapeResult",
    "Study", "SweepResult", "SynthResult", "VariableShape", "WearResult", "WorkEstimate",
    "WornThroughError", "build_schedule", "calibrate", "check_work", "configure_xla",
    "crank_slider_forces", "diagnose", "effects", "estimate_work", "input_files",
    "load_history", "load_study", "make_cycle", "make_schedule", "open_outputs",
    "points_mesh", "predict", "preset", "read_load_file", "register_effect",
    "sensitivities", "sharded_fn", "sharded_vmap", "simulate", "solve_contact",
    "stiffness_per_area", "study_sensitivities", "sweep", "synthesize", "unregister_effect",
    "wear_loop", "write_diagnosis",
]
