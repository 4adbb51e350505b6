"""Shared set-up of the physics tests.

`jaxwear` is the first JAX-related import, so float64 (`jax_enable_x64`) is on before any
array is made; every tolerance in these tests assumes 64-bit floats.
"""

import importlib
import os
import sys
from pathlib import Path

import pytest

# The tests compile every program at LLVM's O1 (XLA:CPU's default is O2). The product
# compiles jaxwear's own programs at O1 too, per program (`jaxwear._core.jit`; its rate
# programs at O0); this flag also covers the tests' other programs. The suite is bound by
# compilation; O1 compiles ~10-20 % faster (a diagnosis test 52 -> 47 s; the shape's
# 146-column Jacobian 15.4 -> 12.2 s) with the same arithmetic (no fast-math at either level)
# and, measured on the wear loop and a Jacobian, the same run time within a few %
# (docs/performance.md). Subprocesses (the CLI tests) inherit it; a user's own XLA_FLAGS
# setting of it is kept.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_backend_optimization_level=1").strip()

import jaxwear  # noqa: E402

jaxwear.configure_xla()  # the faster-compiling emitters, as the CLI has them

# No persistent compilation cache in the tests. The CLI turns JAX's cache on process-wide
# (~/.cache/jaxwear), and the tests run the CLI in-process, so every later library test read
# and wrote that cache. Four full-suite runs died inside it (segfaults and an abort while
# reading or writing an entry, in test_wear), once in CI. The tests check the model, not
# JAX's cache; JAXWEAR_NO_CACHE=1 keeps the CLI off it, in-process and in subprocesses
# (they inherit it). A fresh cache folder of the suite's own measured no faster (the
# programs are rarely traced twice identically), so none is used.
os.environ["JAXWEAR_NO_CACHE"] = "1"

# tests/ on the path so that `import helpers` works whatever the import mode.
sys.path.insert(0, str(Path(__file__).parent))

from helpers import Loaded  # noqa: E402


def pytest_configure(config):
    import jax

    assert jax.config.jax_enable_x64, "importing jaxwear must switch JAX to float64"


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Free every compiled program after each test module. Each XLA:CPU executable keeps
    ~18 memory mappings (measured: 200 small jits took a process from 424 to 3 993 maps,
    `jax.clear_caches()` back to 514), and a worker that runs half the suite compiles
    thousands: past Linux's vm.max_map_count (65 530) the next compilation segfaults inside
    XLA (twice at the same test of a full run, in `backend_compile_and_load`). A module's
    own fixtures are torn down before this runs, so nothing it still needs is dropped."""
    yield
    import gc

    import jax

    jax.clear_caches()
    gc.collect()


@pytest.fixture(autouse=True)
def _effect_registry_as_found():
    """Each test leaves the effect registry as it found it. An effect a test registers (an
    effect file a study loads, an example's `missing_wear.py`) would otherwise be a
    candidate, computed at zero strength in every stage, of every later diagnosis in the
    same worker: after the shape's worked example the synth tests ran 4-15x slower."""
    from jaxwear._physics.effects import _base

    before = dict(_base._REGISTRY)
    yield
    _base._REGISTRY.clear()
    _base._REGISTRY.update(before)


@pytest.fixture(scope="session")
def rig():
    """Rig preset: Tables 1 and 3, 276 r/min, k = 1009.4 N/m, x0 = L2 - L1 (design.md §8)."""
    return jaxwear.preset("rig")


@pytest.fixture
def engines_stubbed(monkeypatch):
    import jaxwear._analyses.predict.forecast as pre
    import jaxwear.cli.calibrate as cal
    dia = importlib.import_module("jaxwear._analyses.diagnose")
    import jaxwear._analyses.sensitivity as sen
    import jaxwear._analyses.sweep as swe
    import jaxwear.cli.simulate as sim

    def loaded(*a, **k):
        raise Loaded

    for mod, name in ((sim, "simulate_study"), (cal, "build_problem"), (dia, "diagnose"),
                      (dia, "Model"), (swe, "sweep"), (sen, "study_sensitivities"),
                      (pre, "predict")):
        monkeypatch.setattr(mod, name, loaded)
