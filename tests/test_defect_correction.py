"""One compile per answer (DESIGN §6, issue 27): a fit whose study leaves the resolution
open compiles its Jacobian once, at the coarsest level, and reaches the finer level's answer
by defect correction (forward runs there only).

The levels are made small here (16 x 24 and 32 x 36; the defaults are 90 x 72 and up) so
that the check fails at the coarse level and the correction has work to do. The data come
from `jaxwear.synthesize` at finer numerics than either level (truth at 96 x 96, M = 5,
whole-bore noise 0.3 µm): the reference is a full fit at the finer level (its own
Jacobian), which the corrected answer must meet within the 0.1 standard-error promise.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from jaxwear import _resolution
from jaxwear._calibrate import fit_study, study_fit_keys
from jaxwear._residual import traces, traces_since
from jaxwear._study import load_study
from jaxwear._synth import synthesize

LEVELS = ((16, 24), (32, 36))


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("defect")
    cond = root / "conditions.toml"
    cond.write_text('[model]\npreset = "rig"\n[model.parameters]\nK_d_per_Pa = 1.0e-13\n'
                    'spring_N_per_m = 1009.4\n[fit]\nclearance_tolerance_um = 5\n'
                    '[[experiment]]\nname = "a276"\nspeed_rpm = 276\nclearance_mm = 0.05\n'
                    'revolutions = 3000\n')
    syn = synthesize([], str(cond), noise_um=0.3, seed=4, out=root / "s",
                     numerics={"nodes": 48, "steps_per_rev": 48,
                               "revolutions_per_update": 50})
    text = re.sub(r"\[numerics\][^\[]*", "", syn.study.path.read_text())
    syn.study.path.write_text(text)
    st = load_study(syn.study.path)
    assert st.auto_resolution
    return st


def test_defect_correction_meets_the_finer_levels_answer_with_one_jacobian(study,
                                                                           monkeypatch):
    monkeypatch.setattr(_resolution, "LEVELS", LEVELS)
    keys = study_fit_keys(study)
    before = traces()
    auto = fit_study(study, keys)
    compiles = traces_since(before)
    res = auto.resolution
    # the coarse answer failed its check: corrected to the finer level, whose rows it reports
    assert res["jacobian"] == {"nodes": 16, "steps_per_rev": 24}, res
    assert res["corrected_to"] == {"nodes": 32, "steps_per_rev": 36}, res
    assert (res["nodes"], res["steps_per_rev"]) == LEVELS[1]
    assert res["defect_corrections"] >= 1
    assert res["correction_step_standard_errors"] <= _resolution.FIT_SE_TOL
    assert compiles["jacobian"] == 1, compiles  # one Jacobian, the coarse level's
    assert auto.compiles == compiles
    assert auto.forward_runs >= 2 and auto.to_json()["compiles"] == sum(compiles.values())
    # the finer level's own answer: a full fit there (its own Jacobian)
    fine_study = dataclasses.replace(study.with_config(nodes=32, steps_per_rev=36),
                                     auto_resolution=False)
    fine = fit_study(fine_study, keys)
    assert fine.converged and auto.converged, (fine.message, auto.message)
    z = np.abs(auto.values - fine.values) / fine.stderr
    # the promise, 0.1 SE, plus the two fits' own stops (0.01 SE each)
    assert np.all(z <= _resolution.FIT_SE_TOL + 0.02), z
    # what is reported is the finer level's: its rows and its snapshots
    assert auto.snapshots_um.shape[-1] == 32
    np.testing.assert_allclose(auto.predicted_um, fine.predicted_um,
                               atol=0.2 * auto.noise_um)
    assert auto.rmse_um == pytest.approx(fine.rmse_um, rel=0.01)
