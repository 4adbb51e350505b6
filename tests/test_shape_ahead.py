"""What diagnose makes ready for the shape analysis before it asks (`shape.design`): the
numerical-error run beside the design (`NumericalAhead`): it must give the analysis what it
would have computed itself, and nothing for another fit."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.diagnose import Model
from jaxwear._analyses.diagnose.shape.design import (
    NumericalAhead,
    numerical_error_rows,
)

# a grid no other test uses, so that its programs are compiled here first
ODD = dict(nodes=44, steps_per_rev=66, revolutions_per_update=500)


@pytest.fixture(scope="module")
def model_and_answer():
    """Two experiments of the paper's rig at `ODD`, and a stand-in for a fit at u = 0 (its
    evaluation, no candidate groups)."""
    res = jw.synthesize([], "paper", noise_um=0.3, seed=4, numerics=ODD)
    study = res.study.with_experiments(res.study.experiments[:2])
    model = Model(study, candidates=[])
    ev = model.evaluate(np.zeros(len(model.names)))
    return model, SimpleNamespace(ev=ev, groups=(), label="base")


def test_the_numerical_error_made_ahead_is_the_analysis_own_run(model_and_answer):
    """The rows' error a `NumericalAhead` made is the same forward run's as
    `numerical_error_rows` (bit for bit: one program, one input), at the finer level it
    names; asked for another fit or other candidate groups it gives nothing (the analysis
    then runs its own)."""
    model, fit = model_and_answer
    ahead = NumericalAhead(model, fit, [])
    (rows, level), evals = ahead.take(model, fit, [])
    assert level == f"{2 * ODD['nodes']} x {2 * ODD['steps_per_rev']}" and evals == 1
    own = numerical_error_rows(model, fit, candidates=[])
    assert rows is not None and np.array_equal(rows, own)
    other = SimpleNamespace(ev=fit.ev, groups=(), label="other")
    assert ahead.take(model, other, []) is None
    assert ahead.take(model, fit, ["speed_dependence"]) is None
