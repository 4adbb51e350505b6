"""One compile per answer (design.md §6, issue 27): a fit whose study leaves the resolution
open compiles its Jacobian once, at the coarsest level, and reaches the finer level's answer
by defect correction (forward runs there only).

The levels are made small here (32 x 36 and 64 x 72; the defaults are 90 x 72 and up) and
the noise low (0.1 µm on whole scans) so that the check fails at the coarse level (by a few
standard errors) and the correction has work to do. The data come from
`jaxwear.synthesize` at finer numerics than either level (truth at 128 x 128, M = 5); the
study keeps M = 100 (eq 23's fixed steps: the finer level's rows are then a smooth function
of the parameters, so that the reference below can difference them).

The reference: the finer level's own least-squares answer, found independently of the
correction by Gauss-Newton with a central finite-difference Jacobian of the finer level's
forward runs (the same rows, prior rows and noise weighting as the fit).

What defect correction reaches is where the coarse Jacobian sees no step with the finer
rows (J_coarseᵀ r_fine = 0), not exactly the finer fit's J_fineᵀ r_fine = 0: the two
differ by about the Jacobian's relative discretisation error, in standard errors (measured
with the adaptive integrator: 0.11 SE between 32 x 36 and 64 x 72, against 2.5 SE
uncorrected). The bound is the 0.1 SE promise, the fit's own stop and that term (0.05).
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from jaxwear._analyses.synth import synthesize
from jaxwear._inference.calibrate import build_problem, fit_study, study_fit_keys
from jaxwear._inference.evaluation import forward_run
from jaxwear._inference.residual import traces, traces_since
from jaxwear._study import resolution as _resolution
from jaxwear._study.study import load_study

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
    # leave the resolution open, keep M = 100 (eq 23)
    text = re.sub(r"\[numerics\][^\[]*", "[numerics]\nrevolutions_per_update = 100\n",
                  syn.study.path.read_text())
    syn.study.path.write_text(text)
    st = load_study(syn.study.path)
    assert st.auto_resolution and st.integrator == "paper"
    return st


@pytest.fixture(scope="module")
def auto(study):
    """The fit at open resolution with the small levels, and its compilations."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_resolution, "LEVELS", LEVELS)
        before = traces()
        result = fit_study(study, study_fit_keys(study))
        return result, traces_since(before)


def fine_answer(study, auto, steps: int = 6, h: float = 1e-4):
    """The finer level's least-squares answer by Gauss-Newton with central differences of
    its forward runs: data rows weighted by the fit's noise level, prior rows in SD units."""
    fine = build_problem(_resolution.at_level(study, LEVELS[1]), study_fit_keys(study),
                         dict(zip(auto.names, np.asarray(auto.problem.start))))
    meas, sigma = fine.measured, auto.noise_um

    def system(u):
        r = (forward_run(fine, u).rows - meas) / sigma
        rp, _ = fine.prior_rows(u)
        return np.concatenate([r, rp])

    u = np.array(auto.u)
    for _ in range(steps):
        r0 = system(u)
        J = np.stack([(system(u + h * e) - system(u - h * e)) / (2 * h)
                      for e in np.eye(len(u))], axis=1)
        step = np.linalg.lstsq(J, -r0, rcond=None)[0]
        u = u + step
        if np.max(np.abs(step)) < 1e-8:
            break
    return fine.packing.values_np(u), fine


def test_one_jacobian_compile_and_the_answer_at_the_finer_level(study, auto):
    auto, compiles = auto
    res = auto.resolution
    # the coarse answer failed its check: corrected to the finer level, whose rows it reports
    assert res["jacobian"] == {"nodes": 32, "steps_per_rev": 36}, res
    assert res["corrected_to"] == {"nodes": 64, "steps_per_rev": 72}, res
    assert (res["nodes"], res["steps_per_rev"]) == LEVELS[1]
    assert res["defect_corrections"] >= 1
    assert res["correction_step_standard_errors"] <= _resolution.FIT_SE_TOL
    # one line says the answer needed the finest level, how far the coarser one was (its
    # first check, before the corrections: over the tolerance) and what the level cost
    (flag,) = [f for f in auto.flags if f.startswith("resolution: the fit needed the finest")]
    assert "64 x 72" in flag and "at 32 x 36 the answer was" in flag, flag
    away = float(flag.split("the answer was ")[1].split(" standard errors")[0])
    assert away > _resolution.FIT_SE_TOL, flag
    runs = int(flag.split("; ")[1].split(" forward run")[0])
    assert 1 <= runs <= auto.forward_runs, flag
    assert compiles["jacobian"] == 1, compiles  # one Jacobian, the coarse level's
    assert auto.compiles == compiles
    assert auto.forward_runs >= 2 and auto.to_json()["compiles"] == sum(compiles.values())
    assert auto.converged, auto.message
    # the finer level's own answer, without its Jacobian: within the promise
    values, fine = fine_answer(study, auto)
    z = np.abs(auto.values - values) / auto.stderr
    assert np.all(z <= _resolution.FIT_SE_TOL + 0.05), z
    # what is reported is the finer level's: a forward run there at the answer (the
    # correction recomputed at the answer), its rows and its snapshots
    f = forward_run(fine, auto.u)
    np.testing.assert_allclose(auto.predicted_um, f.rows, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(auto.snapshots_um, f.snaps, rtol=1e-9, atol=1e-9)
