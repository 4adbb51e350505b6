"""Shared set-up of the physics tests.

`jaxwear` is the first JAX-related import, so float64 (`jax_enable_x64`) is on before any
array is made; every tolerance in these tests assumes 64-bit floats.
"""

import importlib
import os
import sys
from pathlib import Path

import pytest

import jaxwear

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


@pytest.fixture(scope="session")
def rig():
    """Rig preset: Tables 1 and 3, 276 r/min, k = 1009.4 N/m, x0 = L2 - L1 (DESIGN §8)."""
    return jaxwear.preset("rig")


@pytest.fixture
def engines_stubbed(monkeypatch):
    import jaxwear._predict as pre
    import jaxwear.cli.calibrate as cal
    dia = importlib.import_module("jaxwear.diagnose")  # the package, not the function
    import jaxwear._sensitivity as sen
    import jaxwear._simulate_study as sim
    import jaxwear._sweep as swe

    def loaded(*a, **k):
        raise Loaded

    for mod, name in ((sim, "simulate_study"), (cal, "build_problem"), (dia, "diagnose"),
                      (dia, "Model"), (swe, "sweep"), (sen, "study_sensitivities"),
                      (pre, "predict")):
        monkeypatch.setattr(mod, name, loaded)
