"""The diagnose package's contracts that need no model evaluation: immutable results and
model, and the calibration interface it is built from (no compilation: fast)."""

import dataclasses
import math
from dataclasses import replace

import numpy as np
import pytest

import jaxwear as jw
from jaxwear._calibrate import build_problem, parse_fit
from jaxwear._study import Profile
from jaxwear._synth import paper_conditions
from jaxwear.diagnose import Candidate, Diagnosis, Eval, Fit, Model, Screen, _stats


def _study():
    st = paper_conditions(dict(nodes=48, steps_per_rev=48, revolutions_per_update=500))
    ang = np.radians(np.arange(0.0, 360.0, 10.0))
    exps = []
    for i, e in enumerate(st.experiments):
        depth = (1.0 + i) * 1e-6 * np.exp(-0.5 * ((np.degrees(ang) - 180) / 30) ** 2)
        exps.append(replace(e, profile=Profile(ang, depth, np.full(len(ang), e.revolutions),
                                               "")))
    return replace(st, experiments=tuple(exps))


def test_result_types_are_frozen():
    for cls in (Fit, _stats.Tests, Screen, Candidate, Diagnosis, Eval):
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen, cls
    t = _stats.Tests(rmse_um=0.3, noise_um=0.3, ratio=1.0, p_chi2=0.5, rho=0.0, z_autocorr=0.0,
              p_autocorr=0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        t.p_score = 0.0


def test_model_is_immutable_and_variants_are_new_models():
    st = _study()
    m = Model(st)
    with pytest.raises(AttributeError):
        m.noise_weight = 2.0
    assert "__dict__" not in type(m).with_contact.__code__.co_names
    w = m.with_noise_weight(0.25)
    assert w is not m and w.noise_weight == 0.25 and m.noise_weight == 1.0
    assert w.columns == m.columns and w.ext.cfg == m.ext.cfg  # same compiled function
    s = m.with_contact("symmetric")
    assert s.ext.cfg.contact == "symmetric" and m.ext.cfg.contact == "unsymmetric"
    assert s.noise_weight == m.noise_weight


def test_model_rows_come_from_the_calibration_problem():
    st = _study()
    prob = build_problem(st, parse_fit(st, "K_d,clearance"))
    m = Model(st, prob)
    rows = prob.measured_rows()
    np.testing.assert_array_equal(m.measured, rows["depth_um"])
    assert m.n == prob.n_data == 5 * 36
    # the row order is each experiment's profile in file order, depths in µm
    e0 = st.experiments[0].profile
    np.testing.assert_allclose(m.measured[:36], e0.depth * 1e6)
    np.testing.assert_allclose(m.row_x[:36], np.degrees(e0.angle))
    assert m.exp_names == [e.name for e in st.experiments]
    np.testing.assert_allclose(prob.nominal_clearances_mm(), [0.05, 0.05, 0.05, 0.10, 0.15])
    fitted = prob.fitted()
    assert [f.name for f, _ in fitted] == m.names[:len(fitted)]
    assert math.isclose(fitted[0][1], 1e-13)  # K_d starts at the study's value
    # prior rows: (c - c_nom)/τ · weight, zero at the nominal clearances
    r_prior, _ = m.with_noise_weight(0.3)._prior_rows(np.zeros(len(m.names)))
    np.testing.assert_allclose(r_prior, 0.0, atol=1e-12)
    assert jw.diagnose.__module__ == "jaxwear.diagnose._verdict"
