"""One compile per answer (DESIGN §6, issue 27): a fit whose study leaves the resolution
open compiles its Jacobian once, at the coarsest level, and reaches the finer level's answer
by defect correction (forward runs there only).

The levels are made small here (32 x 36 and 64 x 72; the defaults are 90 x 72 and up) and
the noise low (0.1 µm on whole scans) so that the check fails at the coarse level (by ~2.5
standard errors) and the correction has work to do. The data come from
`jaxwear.synthesize` at finer numerics than either level (truth at 128 x 128, M = 5): the
reference is a full fit at the finer level (its own Jacobian).

What defect correction reaches is where the coarse Jacobian sees no step with the finer
rows (J_coarseᵀ r_fine = 0), not exactly the finer fit's J_fineᵀ r_fine = 0: the two
differ by about the Jacobian's relative discretisation error, in standard errors (measured
here: 0.11 SE between 32 x 36 and 64 x 72, against 2.5 SE uncorrected). The bound below is
the 0.1 SE promise, the fits' own stops and that term (0.05).
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

LEVELS = ((32, 36), (64, 72))


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("defect")
    cond = root / "conditions.toml"
    cond.write_text('[model]\npreset = "rig"\n[model.parameters]\nK_d_per_Pa = 1.0e-13\n'
                    'spring_N_per_m = 1009.4\n[fit]\nclearance_tolerance_um = 5\n'
                    '[[experiment]]\nname = "a276"\nspeed_rpm = 276\nclearance_mm = 0.05\n'
                    'revolutions = 3000\n')
    syn = synthesize([], str(cond), noise_um=0.1, seed=4, out=root / "s",
                     numerics={"nodes": 64, "steps_per_rev": 64,
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
    assert res["jacobian"] == {"nodes": 32, "steps_per_rev": 36}, res
    assert res["corrected_to"] == {"nodes": 64, "steps_per_rev": 72}, res
    assert (res["nodes"], res["steps_per_rev"]) == LEVELS[1]
    assert res["defect_corrections"] >= 1
    assert res["correction_step_standard_errors"] <= _resolution.FIT_SE_TOL
    assert compiles["jacobian"] == 1, compiles  # one Jacobian, the coarse level's
    assert auto.compiles == compiles
    assert auto.forward_runs >= 2 and auto.to_json()["compiles"] == sum(compiles.values())
    # the finer level's own answer: a full fit there (its own Jacobian)
    fine_study = dataclasses.replace(study.with_config(nodes=64, steps_per_rev=72),
                                     auto_resolution=False)
    fine = fit_study(fine_study, keys)
    assert fine.converged and auto.converged, (fine.message, auto.message)
    z = np.abs(auto.values - fine.values) / fine.stderr
    assert np.all(z <= _resolution.FIT_SE_TOL + 0.05), z
    # what is reported is the finer level's: its rows and its snapshots
    assert auto.snapshots_um.shape[-1] == 64
    np.testing.assert_allclose(auto.predicted_um, fine.predicted_um,
                               atol=0.2 * auto.noise_um)
    assert auto.rmse_um == pytest.approx(fine.rmse_um, rel=0.01)
