"""The diagnose package's contracts that need no model evaluation: immutable results and
model, and the calibration interface it is built from (no compilation: fast)."""

import dataclasses
import math
from dataclasses import replace

import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.diagnose import Candidate, Diagnosis, Fit, Model, Screen, _stats
from jaxwear._analyses.synth import paper_conditions
from jaxwear._inference.calibrate import build_problem, parse_fit
from jaxwear._inference.evaluation import Evaluation
from jaxwear._study.study import Profile


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
    for cls in (Fit, _stats.Tests, Screen, Candidate, Diagnosis, Evaluation):
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen, cls
    t = _stats.Tests(rmse_um=0.3, noise_um=0.3, ratio=1.0, p_chi2=0.5, rho=0.0, z_autocorr=0.0,
              p_autocorr=0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        t.p_score = 0.0


def test_model_is_immutable_and_variants_are_new_models():
    st = _study()
    m = Model(st)
    with pytest.raises(AttributeError):
        m.keys = ["K_d_per_Pa"]
    ext, columns = m.ext, m.columns
    s = m.with_contact("symmetric")
    assert m.ext is ext and m.columns == columns  # the original model is untouched
    assert s is not m and s.columns == m.columns
    assert s.ext.cfg.contact == "symmetric" and m.ext.cfg.contact == "unsymmetric"


def test_model_is_the_calibration_problem_with_candidate_columns():
    """Diagnose's model is calibrate's residual model (one packing) with the candidates'
    columns appended: the same rows, the same base columns, starts and prior rows."""
    st = _study()
    prob = build_problem(st, parse_fit(st, "K_d,clearance"))
    m = Model(st)
    np.testing.assert_array_equal(m.measured, prob.measured)
    assert m.n == prob.n_data == 5 * 36
    # the row order is each experiment's profile in file order, depths in µm
    e0 = st.experiments[0].profile
    np.testing.assert_allclose(m.measured[:36], e0.depth * 1e6)
    np.testing.assert_allclose(m.row_x[:36], np.degrees(e0.angle))
    assert m.exp_names == [e.name for e in st.experiments]
    k = prob.packing.size
    assert m.packing.columns[:k] == prob.packing.columns
    np.testing.assert_allclose(np.asarray(m.packing.start)[:k], np.asarray(prob.packing.start))
    assert math.isclose(float(prob.packing.start[0]), 1e-13)  # K_d starts at the study's
    centres = [c.prior_centre for c in prob.columns if c.has_prior]
    np.testing.assert_allclose(centres, [0.05, 0.05, 0.05, 0.10, 0.15])
    assert all(c.group for c in m.packing.columns[k:])  # candidates only after the base
    # prior rows (c - c_nom)/τ in SD units: zero at the nominal clearances, 1 at +τ
    u = np.zeros(m.packing.size)
    np.testing.assert_allclose(m.packing.prior_rows(u)[0], 0.0, atol=1e-12)
    i = m.index["clearance_mm/" + st.experiments[0].name]
    u[i] = math.log((0.05 + st.clearance_tolerance_um * 1e-3) / 0.05)
    assert m.packing.prior_rows(u)[0][0] == pytest.approx(1.0, rel=1e-12)
    assert jw.diagnose.__module__ == "jaxwear._analyses.diagnose._verdict"


def test_the_shapes_design_is_started_ahead_only_where_the_verdict_will_likely_run_it(
        monkeypatch):
    # `_verdict._design_ahead`: a misfit well above the noise that no candidate's score
    # explains half of (the generator's fatigue and thermal studies: 38 % and 41 %)
    from types import SimpleNamespace

    from jaxwear._analyses.diagnose import _verdict

    started = []
    monkeypatch.setattr(_verdict, "Background", lambda fn, *a, **k: started.append(fn) or fn)
    model = SimpleNamespace(n=1000)
    noise = 0.3
    expected = (1000 - 6) * noise ** 2

    def ahead(rss, explained, allowed=True, scores=True):
        started.clear()
        base = SimpleNamespace(k=6, rss=rss)
        sc = [SimpleNamespace(explained=explained)] if scores else []
        out = _verdict._design_ahead(model, base, noise, sc, allowed)
        return out is not None and started == [_verdict.prepare_design]

    assert ahead(3 * expected, 0.38)
    assert not ahead(3 * expected, 0.6)  # a candidate that explains most of it
    assert not ahead(1.2 * expected, 0.1)  # near the noise: likely adequate or found
    assert not ahead(3 * expected, 0.38, allowed=False)  # `--shape` or no shape
    assert not ahead(3 * expected, 0.38, scores=False)  # no candidates
