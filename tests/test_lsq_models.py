"""The least-squares core inside calibrate, diagnose and predict: one meaning of
`converged`, the same flags for a fit that ran out of budget or a parameter the data do
not determine, refusals before any model evaluation, and the resolution chosen by the
error (design.md §6) checked against a finer fit.

Data come from `jaxwear.synthesize` (truth at twice the fit's nodes and steps and a tenth
of its M, whole-bore noise, negative depths kept), never from the fit's own model and grid.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.diagnose import Model, fit_masked
from jaxwear._analyses.synth import synthesize
from jaxwear._core.errors import InputError
from jaxwear._inference import calibrate as cal
from jaxwear._study.study import load_study

NOISE_UM = 0.3


def conditions(root, *, numerics=True, fit_params=None, tolerance="5", extra_exp=""):
    """A two-experiment rig study without data (the synth conditions)."""
    root.mkdir(parents=True, exist_ok=True)
    lines = ['[model]', 'preset = "rig"', '[model.parameters]', 'K_d_per_Pa = 1.0e-13',
             'spring_N_per_m = 1009.4']
    if numerics:
        lines += ['[numerics]', 'nodes = 32', 'steps_per_rev = 36',
                  'revolutions_per_update = 100']
    lines += ['[fit]', f'clearance_tolerance_um = {tolerance}']
    if fit_params:
        lines.append(f'parameters = {fit_params!r}'.replace("'", '"'))
    for name, n, c in (("a276", 276, 0.05), ("b148", 148, 0.05)):
        lines += ['[[experiment]]', f'name = "{name}"', f'speed_rpm = {n}',
                  f'clearance_mm = {c}', 'revolutions = 3000']
    path = root / "conditions.toml"
    path.write_text("\n".join(lines) + "\n" + extra_exp)
    return path


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A synthesized study at 32 nodes x 36 steps (truth at 64 x 72, M = 10)."""
    root = tmp_path_factory.mktemp("small")
    out = synthesize([], str(conditions(root / "c")), noise_um=NOISE_UM, seed=3,
                     out=root / "s", kd_sd=0.3)
    return out.study.path


def test_budget_is_flagged_alike_in_calibrate_and_diagnose(small):
    """A fit stopped by its budget is not converged, in calibrate and diagnose alike (the
    old diagnose loop called a fit that ran out of damping 'converged')."""
    study = load_study(small)
    res = jw.calibrate(study, max_evaluations=1)
    assert res.status == "budget" and not res.converged
    assert any("did not converge (budget)" in f for f in res.flags), res.flags
    doc = res.to_json()
    assert doc["converged"] is False and doc["status"] == "budget"
    model = Model(study)
    u0 = np.zeros(len(model.names))
    fit = fit_masked(model, model.base_mask, u0, noise_um=NOISE_UM, max_evaluations=1)
    assert fit.status == "budget" and not fit.converged
    assert any("did not converge (budget)" in f for f in fit.flags), fit.flags
    # with its budget the same fits converge, to the same answer
    full = jw.calibrate(study)
    assert full.converged and full.status == "converged", full.message
    assert full.iterations <= 8, full.iterations


def test_undetermined_parameter_is_flagged_alike_in_calibrate_and_diagnose(tmp_path, small):
    """The pin is rigid in the model (design.md §3): its modulus cannot move any depth. Fitted
    anyway, it has no standard error and a flag, in calibrate and in diagnose."""
    study = load_study(small)
    res = jw.calibrate(study, "K_d,clearance,pin_E_GPa")
    i = res.names.index("pin_E_GPa")
    assert not np.isfinite(res.stderr[i])
    assert res.to_json()["parameters"]["pin_E_GPa"]["stderr"] is None
    assert any("do not determine pin_E_GPa" in f for f in res.flags), res.flags
    k = res.names.index("K_d_per_Pa")
    assert np.isfinite(res.stderr[k])  # the determined ones keep theirs
    text = small.read_text().replace("[fit]", '[fit]\nparameters = ["K_d", "clearance", '
                                              '"pin_E_GPa"]')
    alt = small.parent / "with_pin.toml"
    alt.write_text(text)
    model = Model(load_study(alt))
    assert "pin_E_GPa" in model.names  # diagnose honours [fit] parameters
    fit = fit_masked(model, model.base_mask, np.zeros(len(model.names)), noise_um=NOISE_UM)
    assert "pin_E_GPa" in fit.undetermined
    assert any("do not determine pin_E_GPa" in f for f in fit.flags), fit.flags
    assert np.isinf(fit.stderr[model.index["pin_E_GPa"]])


def _no_evaluation(monkeypatch):
    def fail(*a, **k):
        raise AssertionError("a model evaluation ran before the refusal")

    from jaxwear._inference import evaluation as _evaluation

    monkeypatch.setattr(cal, "evaluate", fail)
    monkeypatch.setattr(_evaluation, "_evaluate_jit", fail)
    monkeypatch.setattr(_evaluation, "_forward_jit", fail)


def test_noise_refusal_before_any_evaluation_in_predict(monkeypatch, tmp_path):
    """Three boom rows with K_d and running-in (3 parameters): σ̂ has no degree of freedom.
    Refused with the way out (--noise-um) before any evaluation (it took 11 minutes of
    fitting before)."""
    root = tmp_path / "boom"
    root.mkdir()
    src = load_study("calibration/boom/study.toml").path
    text = src.read_text().replace("[model]\n", '[model]\neffects = ["running_in"]\n')
    (root / "study.toml").write_text(text)
    (root / "boom.csv").write_text((src.parent / "boom.csv").read_text())
    study = load_study(root / "study.toml")
    _no_evaluation(monkeypatch)
    # (jw.predict names its argument noise_um; the command line says --noise-um)
    with pytest.raises(InputError, match=r"do not determine the noise level.*noise_um"):
        jw.predict(study, [20.0, 25.0], train_until=15.0)


def test_parameter_no_row_can_see_is_refused_before_any_evaluation(monkeypatch, tmp_path):
    path = conditions(tmp_path, tolerance='"inf"')
    st = synthesize([], str(path), noise_um=NOISE_UM, seed=1, out=tmp_path / "s").study.path
    text = st.read_text() + ('\n[[experiment]]\nname = "unmeasured"\nspeed_rpm = 230\n'
                             'clearance_mm = 0.1\nrevolutions = 3000\n')
    st.write_text(text)
    study = load_study(st)
    _no_evaluation(monkeypatch)
    with pytest.raises(InputError, match="no measured row can see clearance_mm/unmeasured"):
        jw.calibrate(study)


@pytest.mark.slow
def test_auto_resolution_within_a_tenth_of_a_standard_error_of_the_finer_fit(tmp_path):
    """A study without nodes/steps: the fit runs at the coarsest level whose answer a finer
    level moves by < 0.1 SE (checked at the answer). Fitted again, in full, at the next
    finer level, every parameter lies within that check's figure (+ the fits' own stop,
    0.01 SE each) of the auto answer. Data at 1 µm noise from a truth at 240 x 240."""
    path = conditions(tmp_path / "c", numerics=False)
    syn = synthesize([], str(path), noise_um=1.0, seed=4, out=tmp_path / "s",
                     numerics={"nodes": 120, "steps_per_rev": 120,
                               "revolutions_per_update": 50})
    text = re.sub(r"\[numerics\][^\[]*", "", syn.study.path.read_text())
    syn.study.path.write_text(text)
    study = load_study(syn.study.path)
    assert study.auto_resolution
    auto = jw.calibrate(study)
    res = auto.resolution
    assert auto.converged and res["auto"] and res["within_tolerance"], (auto.message, res)
    assert res["refinement_step_standard_errors"] <= 0.1
    assert auto.to_json()["resolution"] == res
    finer = res["checked_against"]
    # a full fit at the finer level, its numerics given (`with_config` alone keeps the
    # study's auto mark, and so fitted the same answer again)
    fine = jw.calibrate(dataclasses.replace(
        study.with_config(nodes=finer["nodes"], steps_per_rev=finer["steps_per_rev"]),
        auto_resolution=False))
    z = np.abs(auto.values - fine.values) / fine.stderr
    assert np.all(z <= res["refinement_step_standard_errors"] + 0.05), z


@pytest.mark.slow
def test_auto_resolution_of_a_forward_run_states_its_error(tmp_path):
    """simulate without nodes/steps: the peak at the chosen level is within 0.1 % of the
    next finer level's, and its stated error bounds the distance to a 360 x 360 run within
    a factor 2 (first-order convergence in the grid: the next-level difference is about
    the error)."""
    from jaxwear._analyses.simulate import run_experiment
    from jaxwear._study.outputs import open_outputs
    from jaxwear.cli.simulate import simulate_study

    path = tmp_path / "s.toml"
    path.write_text('[model]\npreset = "rig"\n[model.parameters]\nK_d_per_Pa = 1.0e-13\n'
                    'spring_N_per_m = 1009.4\n[[experiment]]\nname = "n276"\n'
                    'speed_rpm = 276\nclearance_mm = 0.05\nrevolutions = 3000\n')
    study = load_study(path)
    out = open_outputs(study, tmp_path / "out", planned=["profiles.csv", "summary.json"])
    summary = simulate_study(study, out, plots=False)
    import json

    doc = json.loads((tmp_path / "out" / "summary.json").read_text())
    res = doc["resolution"]
    assert res["auto"] and res["within_tolerance"]
    peak = summary["n276"]["peak_depth_um"]
    assert res["error_estimate_um"] <= 1e-3 * peak
    full = run_experiment(study.with_config(nodes=360, steps_per_rev=360),
                          study.experiments[0])
    ref = float(np.max(np.asarray(full.depth))) * 1e6
    assert abs(peak - ref) <= 2 * res["error_estimate_um"] + 1e-6 * peak, (peak, ref, res)


def test_calibrate_honours_the_study_fit_parameters(monkeypatch, small):
    """`jw.calibrate(study)` fits what the study's `[fit] parameters` name, as the command
    line and `jw.predict` do (it used to fit K_d and the clearances whatever the study
    said); a `fit_spec` given still wins."""
    import jaxwear._inference.calibrate as calmod

    seen = []
    monkeypatch.setattr(calmod, "fit_study", lambda study, keys, **kw: seen.append(keys))
    text = small.read_text().replace("[fit]", '[fit]\nparameters = ["K_d"]')
    alt = small.parent / "k_only.toml"
    alt.write_text(text)
    jw.calibrate(load_study(alt))
    jw.calibrate(load_study(alt), "K_d,clearance")
    jw.calibrate(load_study(small))
    assert seen[0] == ["K_d_per_Pa"]
    assert seen[1] != seen[0] and "K_d_per_Pa" in seen[1] and len(seen[1]) > 1
    assert seen[2] == seen[1]  # no [fit] parameters: K_d and the clearances
