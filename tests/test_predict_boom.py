"""Forecasts on the stiff bimetal boom joint under the default adaptive integrator, and the
early stop that makes its posterior forecasts affordable.

The boom is the case where an integrator that keeps going past the copper layer into the
steel substrate takes over 30 000 stability-limited steps per forecast: the forecast (and
each NUTS draw's forecast) stops once worn through, and the life must still be found. The
data are the paper's Table 5 (`calibration/boom/`); the CLI runs in subprocesses, so its
large compiled programs stay out of the test process.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np


def _adaptive_boom(tmp_path):
    """The boom study under the default adaptive integrator at 48 x 36 (in `tmp_path`)."""
    src = Path(__file__).resolve().parents[1] / "calibration" / "boom"
    text = (src / "study.toml").read_text()
    text = "\n".join(ln for ln in text.splitlines()
                     if not ln.startswith(("revolutions_per_update", "nodes", "steps_per_rev")))
    (tmp_path / "study.toml").write_text(text.replace("[numerics]",
                                                      "[numerics]\nnodes = 48\nsteps_per_rev = 36"))
    (tmp_path / "boom.csv").write_text((src / "boom.csv").read_text())
    return tmp_path / "study.toml"


def test_laplace_life_on_an_adaptive_stiff_joint_reaches_its_end(tmp_path):
    """The boom under the adaptive integrator, life searched to 10x the last measurement
    (250 h). Integrating on through the substrate ran out of attempts (error inf, later
    points left at zero: measured 7428 steps, then truncated); the forecast now stops past
    2x the layer and must end with its error within the tolerance, a life with both bounds,
    and the depth at the `--at` point unchanged by the stop (it lies before it)."""
    study = _adaptive_boom(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-m", "jaxwear", "predict", str(study), "--at", "20",
         "--train-until", "15", "--fit", "K_d", "--out", str(tmp_path / "o"),
         "--json", str(tmp_path / "p.json")], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    doc = json.loads((tmp_path / "p.json").read_text())
    integ = doc["integration"]
    assert 0 < integ["error_estimate_um"] <= integ["tolerance_um"], integ
    assert not any("integration" in f for f in doc["flags"]), doc["flags"]
    life = doc["life"][0]
    assert life["lower"] < life["at"] < life["upper"] < 250.0
    # the central life is where the central forecast crosses 500 µm: beyond 20 h, where it
    # is shallower
    pred = doc["predictions"][0]
    assert pred["depth_um"] < 500.0 and life["at"] > 20.0


def test_nuts_on_an_adaptive_stiff_joint_starts_where_the_fit_ended(tmp_path):
    """The boom (bimetal layer) under the default adaptive integrator, K_d started 20x below
    its fitted value: the schedule's attempt count estimated at the start is far short at
    the fit. NUTS must still start on a finite density and move (measured before the fix:
    every transition diverged at -inf, all draws equal to the start)."""
    _adaptive_boom(tmp_path)
    # In a subprocess: its large compiled programs (thousands of static attempts) stay out
    # of the test process. Every full-suite run that died inside XLA (three locally, one in
    # CI, all later in test_wear) ran this test in-process with JAX's persistent cache on.
    proc = subprocess.run(
        [sys.executable, "-m", "jaxwear", "predict", str(tmp_path / "study.toml"), "--at", "20",
         "--train-until", "15", "--fit", "K_d", "--method", "nuts", "--draws", "8",
         "--warmup", "8", "--chains", "1", "--predictive-draws", "2", "--noise-um", "5",
         "--out", str(tmp_path / "o"), "--json", str(tmp_path / "p.json")],
        capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    doc = json.loads((tmp_path / "p.json").read_text())
    nuts = doc["nuts"]
    assert nuts["divergences"] < 8
    assert nuts["posterior"]["K_d_per_Pa"]["sd"] > 0
    # the draws' forecasts stop past the layer; the life (~40 h at the fit) must still be
    # found (a stop at a regime change, between snapshots, once left it "not reached")
    life = doc["life"][0]
    assert life["at"] is not None and 20.0 < life["at"] < 150.0, life


def test_draws_past_their_early_stop_hold_a_lower_bound():
    """A posterior draw's forecast stops once its layer is worn through: the points after
    repeat its last computed profile (depth never decreases: a lower bound past the layer),
    per experiment, and a draw that did not stop is untouched."""
    from jaxwear._predict import fill_past_stop

    inf = np.inf
    s = np.array([[[1.0, 2.0], [3.0, 5.0], [inf, inf], [inf, inf]],
                  [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0], [4.0, 4.0]]])
    f, _ = fill_past_stop(s)
    np.testing.assert_array_equal(f[0], [[1, 2], [3, 5], [3, 5], [3, 5]])
    np.testing.assert_array_equal(f[1], s[1])
