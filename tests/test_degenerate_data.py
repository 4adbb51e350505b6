"""Data that give a fit nothing to work with, and data too large for a dense matrix
(issue 41): each is refused before any work (exit 2, one line naming the study and its
files) or fitted with memory linear in the rows."""

import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from test_bad_inputs import _main, _refused

from jaxwear._inference.lsq._covariance import covariance, gauss_newton

STUDY = """\
[model]
preset = "rig"
[model.parameters]
K_d_per_Pa = 1.0e-13
[numerics]
nodes = 48
steps_per_rev = 48
[[experiment]]
name = "a"
speed_rpm = 276
revolutions = 2000
clearance_mm = 0.05
profile = "a.csv"
"""


def _study(folder: Path, depths) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    angles = np.arange(len(depths)) * (360.0 / len(depths))
    (folder / "a.csv").write_text("angle_deg,depth_um\n" + "".join(
        f"{a!r},{d!r}\n" for a, d in zip(angles.tolist(), list(depths))))
    (folder / "study.toml").write_text(STUDY)
    return folder / "study.toml"


@pytest.mark.parametrize("verb", [["calibrate"], ["diagnose"], ["diagnose", "--shape"],
                                  ["predict", "--at", "3000"]], ids=" ".join)
def test_all_depths_zero_is_no_wear_measured(tmp_path, engines_stubbed, verb):
    """All depths 0: calibrate ran its budget to "not converged" (exit 0), predict died of
    OverflowError, diagnose of LinAlgError (and SIGABRT in LAPACK with --shape)."""
    study = _study(tmp_path, [0.0] * 90)
    _refused([verb[0], study, *verb[1:], "--out", tmp_path / "o"], "study.toml", "a.csv",
             "every measured depth", "is 0", "no wear measured")
    assert not (tmp_path / "o").exists()


def test_equal_depths_give_no_noise_level_for_diagnose(tmp_path, engines_stubbed):
    """Equal non-zero depths: the data's noise estimate is 0, the misfit's weight 1/0."""
    study = _study(tmp_path, [1.5] * 90)
    _refused(["diagnose", study, "--out", tmp_path / "o"], "a.csv", "noise level of 0",
             "[fit] noise_um")
    rc, err = _main(["calibrate", study, "--out", tmp_path / "o"])  # σ from its residuals
    assert rc == "loaded", err
    (tmp_path / "study.toml").write_text(STUDY.replace("[numerics]", "[fit]\nnoise_um = 0.3\n"
                                                                     "[numerics]"))
    rc, err = _main(["diagnose", study, "--out", tmp_path / "o"])  # the noise stated
    assert rc == "loaded", err


def test_covariance_is_linear_in_the_rows():
    """A 300 000-row scan: the SVD kept U as (rows, rows), 671 GiB for one fit. Now the
    step and covariance of a (300 000, 3) Jacobian take memory linear in the rows, and
    agree with the normal equations (an independent formula, well conditioned here)."""
    rng = np.random.default_rng(0)
    J = rng.normal(size=(300_000, 3)) * np.array([1.0, 1e-6, 1e3])
    r = rng.normal(size=300_000)
    tracemalloc.start()
    step, cov = gauss_newton(r, J)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 20 * J.nbytes, peak  # a few copies of J; (rows, rows) would be 720 GB
    JtJ = J.T @ J
    np.testing.assert_allclose(cov.cov, np.linalg.inv(JtJ), rtol=1e-8)
    np.testing.assert_allclose(step, -np.linalg.solve(JtJ, J.T @ r), rtol=1e-8)
    # fewer rows than columns: the null space still spans what the rows leave free
    c2 = covariance(rng.normal(size=(2, 4)))
    assert c2.null_directions.shape == (4, 2) and c2.undetermined.all()


def test_rows_read_their_nodes_without_a_rows_by_nodes_copy(tmp_path):
    """The model's value at each row came from a (rows, nodes) gather of every row's whole
    profile: under the shape analysis's ~150 forward-mode tangents 58 KB a row at 48 nodes,
    17 GB for a 300 000-row scan. No intermediate of the row read-out is larger than a few
    values per row now (the traced program of `predict_from`, no model run)."""
    import jax
    import jax.numpy as jnp

    from jaxwear import load_study
    from jaxwear._inference.packing import parse_fit
    from jaxwear._inference.residual import build_model

    rows = 3000
    study = load_study(_study(tmp_path, np.linspace(-0.3, 2.0, rows).tolist()))
    model = build_model(study, parse_fit(study, "K_d,clearance"))
    jaxpr = jax.make_jaxpr(model.predict_from)(jnp.zeros((1, 1, 48)))
    biggest = max(v.aval.size for eqn in jaxpr.eqns for v in eqn.outvars)
    assert biggest <= 4 * rows, biggest  # was rows x 48 = 144 000
