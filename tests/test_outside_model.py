"""Answers outside the model, said loudly (issue 41): a fitted value outside the range its
key is held to as an input, or a forecast below depths already measured, is a flag that
comes first (the JSON's `outside_model`, the first lines of the output), not only "not
identifiable"."""

import json
from pathlib import Path

import numpy as np

from jaxwear._analyses.predict.result import Prediction
from jaxwear._study.outside import OUTSIDE, forecast_flags, loud_lines, parameter_flags
from jaxwear.cli import main


def test_fitted_values_outside_their_input_ranges_are_flagged():
    """The clearance of issue 41 (6.2e-12 mm) and a K_d below the table's 1e-20 1/Pa, by the
    table's own bounds (docs/plausibility.md: clearance [1e-4, 100] mm); values inside and
    names without a range pass."""
    flags = parameter_flags(["clearance_mm/n276", "K_d_per_Pa", "angle_offset_deg/a",
                             "K_d_per_Pa", "no_such_key"],
                            [6.2e-12, 1e-21, 3.0, 1.4e-13, 1e99], "rig")
    assert len(flags) == 2 and all(f.startswith(OUTSIDE) for f in flags), flags
    assert "clearance_mm/n276 = 6.2e-12" in flags[0] and "[0.0001, 100]" in flags[0]
    assert "K_d_per_Pa = 1e-21" in flags[1]
    assert parameter_flags(["K_d_per_Pa"], [float("nan")], "rig")  # not finite: outside


def test_a_clearance_held_at_the_end_of_its_range_by_the_fits_bound_is_flagged():
    """A fitted clearance is bounded by the range it is held to as an input (0.1 µm to
    100 mm, docs/plausibility.md): at an end (to 1e-6) the bound, not the data, set it, and
    the flag says so. Just inside, a K_d at its table's end (not a bound of the fit: K_d is
    fitted on (0, inf)) and an effect strength at its `off` bound (the nested model without
    the effect) pass."""
    flags = parameter_flags(["clearance_mm/a", "clearance_mm/b", "clearance_mm/c",
                             "K_d_per_Pa", "backing_compliance_um_per_MPa"],
                            [1e-4 * (1 + 1e-12), 1.001e-4, 100.0, 1e-20, 0.0], "rig")
    assert len(flags) == 2 and all(f.startswith(OUTSIDE) for f in flags), flags
    assert "clearance_mm/a = 0.0001 is held at the lower end" in flags[0], flags[0]
    assert "clearance_mm/c = 100 is held at the upper end" in flags[1], flags[1]
    assert "by the fit's bound" in flags[0]


def test_a_fitted_clearance_is_bounded_by_its_plausible_range():
    """The fit's box on each clearance is the plausible range (0.1 µm to 100 mm), in the
    log coordinate u = ln(c / c_nominal): the tolerance prior alone tends to a constant as
    c -> 0 and stops nothing (a held-out study's fit walked to 1.3e-8 mm). The prior is
    truncated to the same range for the posterior."""
    import math

    from jaxwear._inference.packing import packing_of, study_columns
    from jaxwear._study.study import load_study

    study = load_study(Path(__file__).parent / "data" / "heldout41" / "unsymmetric"
                       / "study.toml")
    cols = study_columns(study, ["K_d_per_Pa", "clearance_mm"],
                         [study.params(e) for e in study.experiments])
    pk = packing_of(cols)
    lo, hi = pk.bounds_u()
    i = pk.index("clearance_mm/n276-r15000")
    assert math.isclose(lo[i], math.log(1e-4 / 0.05)) and math.isclose(hi[i],
                                                                        math.log(100 / 0.05))
    k = pk.index("K_d_per_Pa")
    assert lo[k] == -np.inf and hi[k] == np.inf
    at_lo = np.zeros(pk.size)
    at_lo[i] = lo[i]
    assert np.isfinite(float(pk.log_prior(at_lo)))  # a fit held at the bound is inside
    at_lo[i] = lo[i] - 1e-3
    assert float(pk.log_prior(at_lo)) == -np.inf


def _pred(at, depth, upper):
    return Prediction("a", at, "revolutions", depth, depth - 1.0, upper, None, depth - 0.5,
                      depth + 0.5, 0.5, 0.6)


def test_a_forecast_below_a_measured_depth_is_flagged():
    """Issue 41: 0.027 µm [-1.03, 1.08] at 3000 rev where 3.3 µm was measured at 2000 rev.
    Bands that reach the measured depth, within 3 noise levels, or points before the first
    measurement pass."""
    measured = {"a": (np.array([1000.0, 2000.0]), np.array([1.2, 3.3]), np.ones(2, bool))}
    flags = forecast_flags([_pred(3000.0, 0.027, 1.08), _pred(3000.0, 3.0, 3.4),
                            _pred(2000.0, 2.0, 2.5), _pred(500.0, 0.0, 0.2)],
                           measured, 0.3, "revolutions")
    assert len(flags) == 1 and flags[0].startswith(OUTSIDE), flags
    assert "0.027 µm" in flags[0] and "3.3 µm already measured at 2000" in flags[0]
    assert loud_lines(flags + ["a quieter flag"]) == [f"WARNING: {flags[0]}"]


def test_calibrate_says_it_first_and_in_the_json(tmp_path):
    """A scan of material added (a scar of -3 µm: the data ask for K_d < 0) fitted
    K_d = 1.2e-21 1/Pa, flagged only "not identifiable"/"not converged" before: now the
    first line of the output and `outside_model` in calibration.json."""
    angles = np.arange(0.0, 360.0, 6.0)
    rng = np.random.default_rng(3)
    d = -3.0 * np.exp(-0.5 * (((angles - 178.0 + 180) % 360 - 180) / 25.0) ** 2)
    d = d + 0.3 * rng.normal(size=len(angles))
    (tmp_path / "a.csv").write_text("angle_deg,depth_um\n" + "".join(
        f"{a},{x}\n" for a, x in zip(angles, d)))
    (tmp_path / "study.toml").write_text(
        '[model]\npreset = "rig"\n[model.parameters]\nK_d_per_Pa = 1.0e-13\n'
        '[numerics]\nnodes = 32\nsteps_per_rev = 36\n[[experiment]]\nname = "a"\n'
        'speed_rpm = 276\nrevolutions = 2000\nclearance_mm = 0.05\nprofile = "a.csv"\n')
    out = tmp_path / "o"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        rc = main(["calibrate", str(tmp_path / "study.toml"), "--fit", "K_d", "--out",
                   str(out)])
    assert rc == 0
    first = buf.getvalue().splitlines()[0]
    assert first.startswith(f"WARNING: {OUTSIDE}: K_d_per_Pa = "), first
    doc = json.loads(Path(out / "calibration.json").read_text())
    assert doc["parameters"]["K_d_per_Pa"]["value"] < 1e-20
    assert doc["outside_model"] and doc["outside_model"][0] == doc["flags"][0]
