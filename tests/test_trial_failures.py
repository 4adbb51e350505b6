"""A failed trial is a value, never a crash (issue 41, item 1).

Every kind of failure a model evaluation can have at a trial point (rows or Jacobian NaN
or inf, the caller's `usable` False with its cause, `TrialFailed` raised: a solve or an
integration that did not converge, a work estimate beyond the budget) is driven through
the one least-squares core with a cheap model whose answer is known independently (the
same fit without failures): the fit goes on, the trust region shrinks, one progress line
names the cause, and the answer is the failure-free one. Only the start ends a fit, with
`FitError` naming the values and the cause. Last, the real residual model at a trial whose
parameters make its work estimate NaN (the crash of issue 41: `attempts_needed` ->
`adaptive_attempts` -> `int(math.ceil(nan))`), on data from the independent NumPy
generator (`benchmarks/hidden_physics.py`) at 3x the fit's nodes and steps.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxwear._inference import lsq as lsq
from jaxwear._inference.lsq import FitError, TrialFailed

T = np.linspace(0.0, 5.0, 200)
SIGMA = 0.05


def data(seed=0):
    rng = np.random.default_rng(seed)
    return 3.0 * np.exp(-0.7 * T) + SIGMA * rng.standard_normal(T.size)


def exp_model(y):
    """u = (ln a, k) ↦ Point of a·exp(-k t) − y, exact Jacobian."""

    def evaluate(u):
        a, k = math.exp(u[0]), u[1]
        m = a * np.exp(-k * T)
        J = np.stack([m, -T * m], 1)
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=J,
                         r_prior=np.zeros(0), J_prior=np.zeros((0, 2)), usable=True)

    return evaluate


def _raise(pt):
    raise TrialFailed("the contact solve did not converge (relative force residual 3e-02)")


FAILURES = {  # kind: (what the evaluation returns at a failing trial, cause in the log)
    "nan_rows": (lambda pt: dataclasses.replace(pt, r=np.full_like(pt.r, np.nan)),
                 "200 of 200 data rows not finite"),
    "inf_rows": (lambda pt: dataclasses.replace(pt, r=np.where(T > 2, np.inf, pt.r)),
                 "data rows not finite"),
    "nan_jacobian": (lambda pt: dataclasses.replace(pt, J=np.full_like(pt.J, np.nan)),
                     "400 of 400 Jacobian not finite"),
    "unusable": (lambda pt: dataclasses.replace(pt, usable=False,
                                                why="the layer wore through at cycle 7"),
                 "the layer wore through at cycle 7"),
    "raises": (_raise, "the contact solve did not converge"),
}


def failing(evaluate, kind, fail_at=(1, 2)):
    """`evaluate` whose calls number `fail_at` (0: the start) fail as `kind`; the calls'
    u are recorded."""
    calls = []

    def ev(u):
        calls.append(np.array(u, float))
        pt = evaluate(u)
        return FAILURES[kind][0](pt) if len(calls) - 1 in fail_at else pt

    return ev, calls


U0 = np.array([0.0, 0.3])  # a = 1, k = 0.3; the answer is near (ln 3, 0.7)


@pytest.fixture(scope="module")
def clean():
    return lsq.solve(exp_model(data()), U0, noise_um=SIGMA, max_evaluations=40)


@pytest.mark.parametrize("kind", sorted(FAILURES))
def test_failed_trials_are_rejected_steps_and_the_fit_converges_to_the_same_answer(clean,
                                                                                   kind):
    assert clean.converged, clean.message
    ev, calls = failing(exp_model(data()), kind)
    lines = []
    out = lsq.solve(ev, U0, noise_um=SIGMA, max_evaluations=40, log=lines.append,
                    describe=lambda u: f"a = {math.exp(u[0]):.4g}, k = {u[1]:.4g}")
    assert out.converged, out.message
    # the failure-free answer, to a small fraction of its standard error
    assert np.all(np.abs(out.u - clean.u) < 0.05 * clean.cov.se), (out.u, clean.u)
    # both failed trials were steps from the start (nothing accepted in between), and the
    # trust region shrank: the second is shorter than the first
    first, second = (np.linalg.norm(calls[i] - calls[0]) for i in (1, 2))
    assert 0 < second < first, (first, second)
    failed = [ln for ln in lines if "rejected, the trial failed" in ln]
    assert len(failed) == 2, lines
    cause = FAILURES[kind][1]
    assert all(cause in ln and "a = " in ln and "k = " in ln for ln in failed), failed
    # the failed trials count as evaluations (the start's included)
    assert out.evaluations == len(calls)


def test_a_run_of_failed_trials_is_a_stall_not_a_crash():
    ev, _ = failing(exp_model(data()), "raises", fail_at=range(1, 100))
    out = lsq.solve(ev, U0, noise_um=SIGMA, max_evaluations=40, max_rejections=4)
    assert out.status == "stalled" and not out.converged, out.message
    np.testing.assert_array_equal(out.u, U0)  # nothing to move to: the start stands


def test_a_start_that_raises_ends_the_fit_naming_the_values_and_the_cause():
    ev, _ = failing(exp_model(data()), "raises", fail_at=(0,))
    with pytest.raises(FitError) as err:
        lsq.solve(ev, U0, noise_um=SIGMA, label="base",
                  describe=lambda u: f"K_d_per_Pa = {1e-13 * math.exp(u[0]):.3g}")
    msg = str(err.value)
    assert "base: cannot start the fit at K_d_per_Pa = 1e-13" in msg, msg
    assert "the contact solve did not converge" in msg, msg


def test_an_unusable_start_is_reported_with_the_values_and_the_cause():
    ev, _ = failing(exp_model(data()), "unusable", fail_at=(0,))
    out = lsq.solve(ev, U0, noise_um=SIGMA)
    assert out.status == "unusable" and not out.converged
    assert "at the start, u = [0. , 0.3]" in out.message, out.message
    assert "the layer wore through at cycle 7" in out.message, out.message


def test_only_trial_failures_are_caught():
    """A bug in the model (any other exception) is not a rejected step."""
    calls = []
    inner = exp_model(data())

    def ev(u):
        calls.append(u)
        if len(calls) == 2:
            raise ZeroDivisionError("a bug")
        return inner(u)

    with pytest.raises(ZeroDivisionError):
        lsq.solve(ev, U0, noise_um=SIGMA)


def test_robust_start_lowers_the_scale_past_a_start_that_raises():
    """ln a plays ln K_d: a start that raises (a = 300, over the model's limit 100) is
    lowered tenfold and then rescaled to the data (a = 3)."""
    inner = exp_model(3.0 * np.exp(-0.7 * T))

    def ev(u):
        if u[0] > math.log(100.0):
            raise TrialFailed("the work estimate is not finite")
        return inner(u)

    lines = []
    u, pt, evals, why = lsq.robust_start(ev, np.array([math.log(300.0), 0.7]), 0,
                                         measured=3.0 * np.exp(-0.7 * T), log=lines.append)
    assert why is None and pt.usable
    assert math.exp(u[0]) == pytest.approx(3.0, rel=1e-9)
    assert any("work estimate is not finite" in ln for ln in lines), lines
    # a start that always raises: the cause is returned, no point
    u, pt, evals, why = lsq.robust_start(_always_raises, np.zeros(2), 0, measured=T,
                                         max_reductions=2)
    assert pt is None and "reduced 1e+02-fold" in why and "no model" in why, why


def _always_raises(u):
    raise TrialFailed("no model here")


# ------------------------------------------------- the real residual model (the crash)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.fixture(scope="module")
def small_study(tmp_path_factory):
    """Two rig experiments of 3000 rev, whole-bore scans with 0.3 µm noise, made by the
    independent NumPy generator at 96 x 96 (M = 10); the study fits at 32 x 36, with the
    pressure exponent switched on (fitted from 0; the data have none)."""
    import hidden_physics as hp

    conds = (hp.Condition("a276", 276.0, 3000.0, 0.05, interruptions=(3000.0,)),
             hp.Condition("b148", 148.0, 3000.0, 0.05, interruptions=(3000.0,)))
    gen = hp.generate(hp.Law("null"), conds, seed=3, noise_um=0.3, K_d=1.3e-13,
                      num=hp.Numerics(nodes=96, steps=96, M=10.0))
    path = hp.write(tmp_path_factory.mktemp("trial"), gen, conds, study_numerics=(32, 36))
    path.write_text(path.read_text().replace(
        'preset = "rig"', 'preset = "rig"\neffects = ["pressure_exponent"]'))
    return path


@pytest.fixture(scope="module")
def problem(small_study):
    import jaxwear as jw
    from jaxwear._inference import calibrate as cal

    study = jw.load_study(small_study)
    prob = cal.build_problem(study, cal.study_fit_keys(study))
    assert prob.names == ("K_d_per_Pa", "clearance_mm/a276", "clearance_mm/b148",
                          "pressure_exponent")
    return prob


def test_a_model_not_finite_at_a_trial_is_unusable_at_once(problem):
    """A parameter that makes the model NaN (not its work estimate): every integration
    step is rejected, and more attempts cannot help, so none are added (three doublings to
    8x the attempts took 3.4 s where a run takes 0.03 s)."""
    from jaxwear._inference.evaluation import evaluate

    u = np.zeros(problem.packing.size)
    assert evaluate(problem, u)[0].usable
    u[3] = np.nan
    ev, used = evaluate(problem, u)
    assert not ev.usable and "no wear step could be taken" in ev.why, ev.why
    assert used.schedule.attempts == problem.schedule.attempts


def test_a_trial_whose_work_estimate_is_nan_is_rejected_in_the_real_model(problem):
    from jaxwear._inference.attempts import attempts_needed, needs_more_attempts
    from jaxwear._inference.evaluation import evaluate, forward_run

    prob = problem
    bad = np.zeros(prob.packing.size)
    bad[1] = 10.0  # ln(c / 0.05 mm): c = 1101 mm, beyond the 7.5 mm bore: rate bound NaN
    # the crash was here: int(math.ceil(nan)) in `adaptive_attempts`
    assert attempts_needed(prob, bad) == math.inf and needs_more_attempts(prob, bad)
    ev, _ = evaluate(prob, bad)
    assert not ev.usable and "work estimate is not finite" in ev.why and "a276" in ev.why
    assert ev.snaps.shape == evaluate(prob, np.zeros(prob.packing.size))[0].snaps.shape
    assert not forward_run(prob, bad).usable

    def point(v):
        return evaluate(prob, v)[0].point()

    clean = lsq.solve(point, np.zeros(prob.packing.size), noise_um=0.3)
    calls = []

    def with_bad_trial(v):  # the first trial lands where the work estimate is NaN
        calls.append(v)
        return point(bad if len(calls) == 2 else v)

    lines = []
    out = lsq.solve(with_bad_trial, np.zeros(prob.packing.size), noise_um=0.3,
                    log=lines.append)
    assert clean.converged and out.converged, (clean.message, out.message)
    # the same answer to the stop's resolution (a step within the integrator's error
    # floor counts as converged up to 0.1 standard error, `lsq.solve`)
    assert np.all(np.abs(out.u - clean.u) < 0.2 * clean.cov.se), (out.u, clean.u)
    assert sum("rejected, the trial failed" in ln and "work estimate is not finite" in ln
               for ln in lines) == 1, lines
    # the misfit is the generator's noise (0.3 µm on every point): nothing left to fit
    assert out.point.rms_um < 1.1 * 0.3, out.point.rms_um


def test_the_samplers_density_at_a_failing_point_is_minus_infinity(problem):
    """NUTS and importance sampling share one density (`_predict_nuts.log_density`): at a
    position whose model is not finite it is -inf (the draw is rejected), not a crash."""
    import jax
    import jax.numpy as jnp

    from jaxwear._analyses.predict.nuts import log_density

    prob = problem
    logp = jax.jit(log_density(prob, noise_um=0.3))
    good = np.zeros(prob.packing.size)
    bad = good.copy()
    bad[1] = 10.0  # the clearance at which the work estimate is NaN (test above)
    assert math.isfinite(float(logp({"u": jnp.asarray(good)})))
    assert float(logp({"u": jnp.asarray(bad)})) == -math.inf


def _counted_runs(E, monkeypatch) -> dict:
    """{"jacobian": n, "forward": n}: the Jacobian and forward programs' runs from here on,
    with the attempt estimate's raise switched off (the model's own count is used)."""
    calls = {"jacobian": 0, "forward": 0}
    jac, fwd = E._evaluate_jit, E._forward_jit

    def count(name, f):
        def run(*a, **k):
            calls[name] += 1
            return f(*a, **k)
        return run

    monkeypatch.setattr(E, "_evaluate_jit", count("jacobian", jac))
    monkeypatch.setattr(E, "_forward_jit", count("forward", fwd))
    monkeypatch.setattr(E, "enough_attempts", lambda model, u, **k: model)
    return calls


def test_an_unfinished_run_finds_its_attempt_count_by_forward_runs(problem, monkeypatch):
    """Where the attempt estimate is far too short (one doubling does not reach the end),
    the count that reaches it is found by forward runs and the Jacobian run once more, at
    it (a Jacobian run that does not reach the end uses every attempt, at 1 + P tangents:
    on the fatigue study's shape refit three doubled Jacobian runs were ~60 s of CPU); the
    evaluation is the one at an ample count (the same history, to rounding)."""
    from jaxwear._inference import evaluation as E

    u = np.zeros(problem.packing.size)
    full, _ = E.evaluate(problem, u)
    assert full.usable and full.steps >= 6
    short = problem.with_schedule(dataclasses.replace(problem.schedule, attempts=1))
    calls = _counted_runs(E, monkeypatch)
    ev, used = E.evaluate(short, u, doublings=5)
    assert ev.usable and np.isfinite(ev.error_um)
    assert used.schedule.attempts >= 4  # 1 -> 2 cannot take the history's 6+ steps
    # the short Jacobian run (its bound `HEADROOM` x the count: its doublings counted as
    # taken), then one at the count the forward runs reached (before: one Jacobian run per
    # doubling, 4 or more)
    assert calls["jacobian"] == 2 and calls["forward"] >= 1, calls
    np.testing.assert_allclose(ev.pred, full.pred, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ev.J, full.J, rtol=1e-7, atol=1e-9 * np.abs(full.J).max())


def test_a_count_short_by_up_to_the_headroom_ends_in_one_jacobian_run(problem,
                                                                         monkeypatch):
    """A Jacobian run's loop bound is `HEADROOM` times the model's attempt count (traced:
    the same program), so a run whose estimate was short by up to that factor ends in one
    go, where it was repeated whole at twice the count: the same history to the bit, no
    forward run, and the model's count raised to what the repeats would have left (the
    smallest count x 2^k that holds the attempts it used)."""
    import jax.numpy as jnp

    from jaxwear._inference import evaluation as E

    u = np.zeros(problem.packing.size)
    uj = jnp.asarray(u)
    full, _ = E.evaluate(problem, u)
    used_attempts = int(E._evaluate_jit(E._dynamic(problem), uj)[2][7])
    assert full.usable and used_attempts >= full.steps >= 6
    short_count = -(-used_attempts // 3)  # used in (count, 4 count]: short, in the headroom
    assert short_count < used_attempts <= E.HEADROOM * short_count
    short = problem.with_schedule(dataclasses.replace(problem.schedule,
                                                      attempts=short_count))
    calls = _counted_runs(E, monkeypatch)
    ev, used = E.evaluate(short, u)
    assert calls == {"jacobian": 1, "forward": 0}
    assert np.array_equal(ev.pred, full.pred) and np.array_equal(ev.J, full.J)
    assert ev.steps == full.steps and ev.error_um == full.error_um
    raised = short_count
    while raised < used_attempts:
        raised *= 2
    assert used.schedule.attempts == raised
    # never more room than the caller's doublings allow: a fit's trial (one doubling)
    # gets twice the count, and this run, short by more, stays unusable as before
    calls.update(jacobian=0, forward=0)
    assert 2 * short_count < used_attempts
    trial, _ = E.evaluate(short, u, doublings=1)
    assert not trial.usable and calls == {"jacobian": 1, "forward": 0}
    # a count that holds the run is left as it is
    same, kept = E.evaluate(problem.with_schedule(dataclasses.replace(
        problem.schedule, attempts=used_attempts)), u)
    assert kept.schedule.attempts == used_attempts and np.array_equal(same.pred, full.pred)


def test_columns_of_distinct_experiments_share_a_tangent_and_give_the_dense_jacobian(
        small_study):
    """`evaluation.seeds` (Curtis-Powell-Reid): per-experiment columns (each experiment's
    clearance and registration offset) of distinct experiments share one forward-mode
    tangent, read back from their own experiment's rows. Against the dense Jacobian (one
    unit tangent per column, through the same program): the same J and snapshot Jacobian
    to round-off, a per-experiment column exactly 0 on the other experiment's rows, and
    fewer tangents (K_d, the pressure exponent, one for both clearances, one for both
    offsets: 4 for 6 columns); a subset's width is its padded length less what sharing
    saves, the same for every subset of one length."""
    import jax.numpy as jnp

    import jaxwear as jw
    from jaxwear._inference import calibrate as cal
    from jaxwear._inference import evaluation as E
    from jaxwear._inference.attempts import _dynamic, attempts_needed, enough_attempts

    study = dataclasses.replace(jw.load_study(small_study), angle_tolerance_deg=5.0)
    prob = cal.build_problem(study, cal.study_fit_keys(study))
    cols = prob.packing.columns
    exps = [c.experiment for c in cols]
    assert sorted(e for e in exps if e is not None) == [0, 0, 1, 1], prob.names
    S, color, owner = E.seeds(cols)
    assert S.shape == (len(cols), 4)
    assert sorted(S.sum(axis=0)) == [1.0, 1.0, 2.0, 2.0]
    u = np.zeros(len(cols))
    u[0], u[3] = 0.1, 0.02
    model = _dynamic(enough_attempts(prob, u, need=attempts_needed(prob, u)))
    uj = jnp.asarray(u)
    J, J_snaps, _ = E._evaluate_jit(model, uj)
    P = len(cols)
    Jd, Jd_snaps, _ = E._seeded(model, uj, jnp.eye(P), jnp.arange(P, dtype=jnp.int32),
                                jnp.full(P, E.ALL, jnp.int32))
    J, J_snaps, Jd, Jd_snaps = (np.asarray(a) for a in (J, J_snaps, Jd, Jd_snaps))
    np.testing.assert_allclose(J, Jd, rtol=1e-9, atol=1e-12 * np.abs(Jd).max())
    np.testing.assert_allclose(J_snaps, Jd_snaps, rtol=1e-9,
                               atol=1e-12 * np.abs(Jd_snaps).max())
    row_exp = np.asarray(prob.data.exp)
    for j, e in enumerate(exps):
        if e is not None:
            assert np.all(Jd[row_exp != e, j] == 0.0) and np.any(J[row_exp == e, j] != 0)
            assert np.all(J[row_exp != e, j] == 0.0)
    # a subset padded by repeats (the law search's): its width does not depend on which
    wanted = [0, 1, 2, 0, 0]
    width = E.width_of(cols, wanted)
    assert width == 4 and E.seeds(cols, wanted, width)[0].shape == (P, 4)
    assert E.width_of(cols, [0, 1, 2, 3, 0]) == 4


def test_the_jacobian_of_some_columns_is_those_of_the_full_jacobian(problem):
    """`evaluate(..., columns=)` (the law search's fits hold most of its model's columns):
    the rows as without, the Jacobian's named columns those of the full Jacobian, the
    others 0; a column repeated to pad changes nothing."""
    from jaxwear._inference.evaluation import evaluate

    u = np.zeros(problem.packing.size)
    u[0] = 0.1
    full, _ = evaluate(problem, u)
    some, _ = evaluate(problem, u, columns=[0, 2, 2])
    assert some.usable
    np.testing.assert_allclose(some.pred, full.pred, rtol=1e-12, atol=1e-12)
    scale = np.abs(full.J).max()
    np.testing.assert_allclose(some.J[:, [0, 2]], full.J[:, [0, 2]], rtol=1e-9,
                               atol=1e-12 * scale)
    assert np.all(some.J[:, [1, 3]] == 0.0) and np.any(full.J[:, [1, 3]] != 0.0)
    np.testing.assert_allclose(some.J_snaps[..., 2], full.J_snaps[..., 2], rtol=1e-9,
                               atol=1e-12 * np.abs(full.J_snaps).max())
