"""The one least-squares core (`jaxwear._inference.lsq`) on problems whose answers are known
independently: linear and exponential models with closed-form or finite-difference
references, a cost with the jitter of an adaptive integrator, a wrong Jacobian, a null
direction. No wear model here (fast); `test_lsq_models.py` checks the core inside
calibrate, diagnose and predict.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from jaxwear._inference import lsq

T = np.linspace(0.0, 5.0, 200)
TRUE = np.array([math.log(3.0), 0.7])  # u = (ln a, k) of a·exp(-k t)
SIGMA = 0.05


def data(seed=0):
    rng = np.random.default_rng(seed)
    return 3.0 * np.exp(-0.7 * T) + SIGMA * rng.standard_normal(T.size)


def exp_model(y, *, jitter=0.0, jacobian_scale=1.0, calls=None):
    """u ↦ Point of a·exp(-k t) − y. `jitter` [µm]: a piecewise-constant error of that size
    that jumps with u (as an adaptive integrator's error jumps when its step count changes:
    no derivative, a cost that is noisy at that level); `jacobian_scale` corrupts J."""

    def evaluate(u):
        if calls is not None:
            calls.append(np.array(u))
        a, k = math.exp(u[0]), u[1]
        m = a * np.exp(-k * T)
        if jitter:
            phase = np.floor(u * 1e7) @ np.array([0.618, 0.414])
            m = m + jitter * np.sin(phase + 7.3 * T)
        J = np.stack([a * np.exp(-k * T), -T * a * np.exp(-k * T)], 1) * jacobian_scale
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=J,
                         r_prior=np.zeros(0), J_prior=np.zeros((0, 2)), usable=True,
                         error_um=jitter)

    return evaluate


def old_host_lm(evaluate, u0, noise, max_evaluations=60):
    """The Levenberg-Marquardt loop calibrate used before the core (`_calibrate.
    levenberg_marquardt` at commit 8a985ba, bookkeeping trimmed, tests unchanged): Nielsen
    damping, stops on a step < 1e-8, < 1e-3 standard errors, a relative gain < 1e-10 or
    λ > 1e16. Kept here as the reference the new stop is measured against. Returns
    (u, evaluations, rejected evaluations)."""
    u = np.array(u0, float)
    pt = evaluate(u)
    r, J = pt.r, pt.J
    F = 0.5 * float(r @ r)
    A, g = J.T @ J, J.T @ r
    lam, nu, evals, rejected = 1e-3, 2.0, 1, 0
    while evals < max_evaluations and lam <= 1e16:
        D = np.maximum(np.diag(A), 1e-12 * float(np.max(np.diag(A))))
        step = np.linalg.solve(A + lam * np.diag(D), -g)
        pt_t = evaluate(u + step)
        evals += 1
        F_t = 0.5 * float(pt_t.r @ pt_t.r)
        pred = -(float(step @ g) + 0.5 * float(step @ A @ step))
        rho = (F - F_t) / pred if pred > 0 else -1.0
        if F_t < F and rho > 0:
            rel = (F - F_t) / F
            u, F = u + step, F_t
            A, g = pt_t.J.T @ pt_t.J, pt_t.J.T @ pt_t.r
            lam *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
            nu = 2.0
            se = np.sqrt(np.diag(np.linalg.inv(A)) * 2 * F / (len(pt_t.r) - 2))
            if (np.max(np.abs(step)) <= 1e-8 * (1 + np.max(np.abs(u)))
                    or np.all(np.abs(step) <= 1e-3 * se) or rel <= 1e-10):
                break
        else:
            lam *= nu
            nu *= 2.0
            rejected += 1
    return u, evals, rejected


def test_recovers_exponential_within_standard_errors():
    y = data(0)
    out = lsq.solve(exp_model(y), np.array([0.0, 1.0]))
    assert out.converged, out.message
    z = (out.u - TRUE) / out.cov.se
    assert np.all(np.abs(z) < 3.0), z
    # σ re-estimated inside the loop: the residual RMS with n − k degrees of freedom
    assert out.noise_um == pytest.approx(SIGMA, rel=0.15)
    assert out.step_se <= 0.01


def test_new_stop_ends_where_the_old_loop_keeps_rejecting():
    """Near the minimum the jittery cost (an adaptive integrator's error, 1e-3 of the
    noise) makes every gain ratio noise: the old loop rejected trial after trial until its
    λ ran out (here 6 of its 10 evaluations; on the rig, issue 19: 29 evaluations over two
    passes, λ to 1e19). The core stops as soon as the next Gauss-Newton step is far below
    the standard errors, and lands on the same answer."""
    y = data(1)
    model = exp_model(y, jitter=5e-3 * SIGMA)
    ref = lsq.solve(exp_model(y), np.array([0.0, 1.0]))
    u_old, evals_old, rejected_old = old_host_lm(model, ref.u + 0.3 * ref.cov.se, SIGMA)
    calls: list = []
    out = lsq.solve(exp_model(y, jitter=5e-3 * SIGMA, calls=calls), ref.u + 0.3 * ref.cov.se)
    assert out.converged, out.message
    assert evals_old >= 10 and rejected_old >= 6, (evals_old, rejected_old)
    assert len(calls) <= 3 and out.evaluations == len(calls)
    assert np.all(np.abs(out.u - ref.u) < 0.1 * ref.cov.se)
    assert np.all(np.abs(u_old - ref.u) < 0.1 * ref.cov.se)  # the same answer, dearer


def test_covariance_equals_inverse_hessian_of_the_cost_by_finite_differences():
    """At the minimum of a linear model ½χ² is exactly quadratic: the core's covariance of u
    must equal the inverse of its Hessian, computed here by central differences of the
    cost alone (no Jacobian)."""
    rng = np.random.default_rng(3)
    X = np.stack([np.ones_like(T), T, np.sin(T)], 1)
    y = X @ np.array([1.0, -0.3, 0.5]) + SIGMA * rng.standard_normal(T.size)

    def evaluate(u):
        m = X @ u
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=X,
                         r_prior=np.zeros(0), J_prior=np.zeros((0, 3)), usable=True)

    out = lsq.solve(evaluate, np.zeros(3), noise_um=SIGMA)
    assert out.converged, out.message

    def half_chi2(u):
        r = evaluate(u).r / SIGMA
        return 0.5 * float(r @ r)

    h = 1e-3
    H = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            ei, ej = np.eye(3)[i] * h, np.eye(3)[j] * h
            H[i, j] = (half_chi2(out.u + ei + ej) - half_chi2(out.u + ei - ej)
                       - half_chi2(out.u - ei + ej) + half_chi2(out.u - ei - ej)) / (4 * h * h)
    np.testing.assert_allclose(out.cov.cov, np.linalg.inv(H), rtol=1e-6)
    # and the answer is the closed-form least-squares solution
    np.testing.assert_allclose(out.u, np.linalg.lstsq(X, y, rcond=None)[0], atol=1e-3 *
                               float(np.min(out.cov.se)))


def test_covariance_of_a_nonlinear_fit_matches_finite_differences():
    """Exponential model: the Gauss-Newton covariance drops Σ r ∇²r, which is of the size
    of the noise relative to the signal; with σ = 0.05 on a signal of ~1 it agrees with the
    finite-difference Hessian of ½χ² to a few percent."""
    y = data(4)
    model = exp_model(y)
    out = lsq.solve(model, np.array([0.0, 1.0]), noise_um=SIGMA)

    def half_chi2(u):
        r = model(u).r / SIGMA
        return 0.5 * float(r @ r)

    h = 1e-4
    H = np.zeros((2, 2))
    for i in range(2):
        for j in range(2):
            ei, ej = np.eye(2)[i] * h, np.eye(2)[j] * h
            H[i, j] = (half_chi2(out.u + ei + ej) - half_chi2(out.u + ei - ej)
                       - half_chi2(out.u - ei + ej) + half_chi2(out.u - ei - ej)) / (4 * h * h)
    np.testing.assert_allclose(out.cov.cov, np.linalg.inv(H), rtol=0.05)


def test_a_stall_is_reported_as_a_stall():
    """A Jacobian of the wrong sign: no trial lowers the misfit. The old loop's answer to
    that was 'converged (no step reduces the misfit)' (diagnose) after λ ran out; the core
    says stalled, with the numbers, and keeps the best point."""
    y = data(5)
    calls: list = []
    out = lsq.solve(exp_model(y, jacobian_scale=-1.0, calls=calls), np.array([0.5, 1.0]))
    assert out.status == "stalled" and not out.converged
    assert "stalled after 6" in out.message and "standard errors" in out.message
    assert out.evaluations == len(calls) == 7  # the start and six rejected trials
    np.testing.assert_array_equal(out.u, [0.5, 1.0])


def test_budget_is_reported():
    y = data(6)
    out = lsq.solve(exp_model(y), np.array([1.5, 0.1]), max_evaluations=2)
    assert out.status == "budget" and not out.converged
    assert "not converged within 2 model evaluations" in out.message


def test_undetermined_direction_is_flagged_not_given_zero_variance():
    """Two identical columns: their sum is determined, each alone is not. A pseudo-inverse
    would give both a finite (zero-variance) answer; the core flags them with an infinite
    standard error and still converges on the determined direction."""
    rng = np.random.default_rng(7)
    y = 2.0 * T + SIGMA * rng.standard_normal(T.size)
    X = np.stack([T, T, np.ones_like(T)], 1)

    def evaluate(u):
        m = X @ u
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=X,
                         r_prior=np.zeros(0), J_prior=np.zeros((0, 3)), usable=True)

    out = lsq.solve(evaluate, np.zeros(3))
    assert out.converged, out.message
    assert list(out.cov.undetermined) == [True, True, False]
    assert np.all(np.isinf(out.cov.se[:2])) and np.isfinite(out.cov.se[2])
    assert out.u[0] + out.u[1] == pytest.approx(2.0, abs=5 * SIGMA / T.std() / 14)


def test_noise_undetermined_is_refused_before_any_evaluation():
    def evaluate(u):
        raise AssertionError("the model was evaluated")

    few = lsq.Point(u=np.zeros(2), r=np.zeros(2), predicted=np.zeros(2), J=np.eye(2),
                    r_prior=np.zeros(0), J_prior=np.zeros((0, 2)), usable=True)
    with pytest.raises(lsq.NoiseUndetermined, match="do not determine the noise"):
        lsq.solve(evaluate, np.zeros(2), point0=few)
    # with σ given the same rows are a well-posed fit
    out = lsq.solve(lambda u: lsq.Point(u=u, r=u - 1.0, predicted=u, J=np.eye(2),
                                        r_prior=np.zeros(0), J_prior=np.zeros((0, 2)),
                                        usable=True),
                    np.zeros(2), noise_um=0.1)
    assert out.converged and np.allclose(out.u, 1.0)


def test_bounds_hold_a_strength_at_its_off_value():
    """A nested strength bounded below by its off value (0) where the data pull it negative:
    the answer sits on the bound, and the free parameter is the constrained least-squares
    solution (the slope with the offset held at 0)."""
    rng = np.random.default_rng(8)
    y = 1.5 * T - 0.4 + SIGMA * rng.standard_normal(T.size)
    X = np.stack([T, np.ones_like(T)], 1)

    def evaluate(u):
        m = X @ u
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=X,
                         r_prior=np.zeros(0), J_prior=np.zeros((0, 2)), usable=True)

    out = lsq.solve(evaluate, np.array([1.0, 0.0]), lower=np.array([-np.inf, 0.0]))
    assert out.converged, out.message
    assert out.u[1] == 0.0
    # within the core's stop: the next step would move it by < 0.01 standard errors
    assert abs(out.u[0] - float(T @ y) / float(T @ T)) < 0.01 * out.cov.se[0]


def test_prior_rows_weighted_by_the_noise_level():
    """A Gaussian prior on one parameter with known σ: the posterior mean of a linear model
    is the precision-weighted average, in closed form."""
    rng = np.random.default_rng(9)
    y = 0.8 + SIGMA * rng.standard_normal(4)  # four measurements of one value
    tau, mu0 = 0.02, 0.75

    def evaluate(u):
        m = np.full(4, u[0])
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=np.ones((4, 1)),
                         r_prior=np.array([(u[0] - mu0) / tau]),
                         J_prior=np.array([[1 / tau]]), usable=True)

    out = lsq.solve(evaluate, np.zeros(1), noise_um=SIGMA)
    w_data, w_prior = 4 / SIGMA ** 2, 1 / tau ** 2
    expect = (w_data * y.mean() + w_prior * mu0) / (w_data + w_prior)
    assert out.u[0] == pytest.approx(expect, abs=1e-9)
    assert out.cov.se[0] == pytest.approx((w_data + w_prior) ** -0.5, rel=1e-9)


def test_robust_start_backs_off_a_worn_through_start_and_rescales():
    y = data(10)
    base = exp_model(y)

    def evaluate(u):
        pt = base(u)
        if u[0] > 3.0:  # "worn through" above a scale of e³
            return lsq.Point(u=pt.u, r=pt.r, predicted=pt.predicted, J=pt.J,
                             r_prior=pt.r_prior, J_prior=pt.J_prior, usable=False)
        return pt

    u, pt, evals, why = lsq.robust_start(evaluate, np.array([8.0, 0.7]), 0, measured=y)
    assert why is None and pt.usable
    assert u[0] == pytest.approx(TRUE[0], abs=0.05)  # ln 10 steps down, then rescaled
    assert evals >= 4


def _linear(X, y, prior=None):
    """u ↦ Point of X u − y (prior: (rows r0 (m,), J (m, k)) in SD units, linear in u)."""

    def evaluate(u):
        m = X @ u
        rp = np.zeros(0) if prior is None else prior[0] + prior[1] @ u
        Jp = np.zeros((0, X.shape[1])) if prior is None else prior[1]
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=X, r_prior=rp,
                         J_prior=Jp, usable=True)

    return evaluate


def test_a_lost_jacobian_is_a_status_never_converged():
    """An all-zero Jacobian (the model lost its dependence on u: a truncated history, a
    tangent dropped) determines nothing: the core says so at the start, with the misfit
    untouched, instead of "converged" (it did before: every column undetermined, so no
    determined parameter was left to move and the stop held vacuously)."""
    y = np.linspace(1.0, 2.0, 50)
    calls: list = []

    def evaluate(u):
        calls.append(u)
        return lsq.Point(u=np.array(u, float), r=-y, predicted=np.zeros_like(y),
                         J=np.zeros((50, 2)), r_prior=np.zeros(0), J_prior=np.zeros((0, 2)),
                         usable=True)

    out = lsq.solve(evaluate, np.zeros(2), noise_um=0.1)
    assert out.status == "undetermined" and not out.converged, out.message
    assert "determine none" in out.message
    assert out.evaluations == 1 and len(calls) == 1
    assert np.all(out.cov.undetermined) and np.all(np.isinf(out.cov.se))


def test_a_column_in_small_units_is_determined():
    """The same linear model with one column in units a million times smaller (a
    parameter in µm fitted beside one in m): the answer and its standard error are the same
    up to the unit, not 'undetermined'. Judged on the unscaled JᵀJ, the small column's
    eigenvalue (1e-12 of the other's) fell under the null threshold: SE inf, and it left the
    stop."""
    rng = np.random.default_rng(11)
    X = np.stack([np.ones_like(T), T], 1)
    y = X @ np.array([0.5, -0.2]) + SIGMA * rng.standard_normal(T.size)
    ref = lsq.solve(_linear(X, y), np.zeros(2), noise_um=SIGMA)
    Xs = X * np.array([1.0, 1e-6])  # u_1 now in µ-units
    out = lsq.solve(_linear(Xs, y), np.zeros(2), noise_um=SIGMA)
    assert out.converged, out.message
    assert not out.cov.undetermined.any()
    np.testing.assert_allclose(out.u * [1.0, 1e-6], ref.u, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.cov.se * [1.0, 1e-6], ref.cov.se, rtol=1e-6)


def test_a_parameter_its_prior_determines_costs_the_noise_no_dof():
    """Ten rows, two parameters, one of them fixed by a tight prior and not seen by the
    data: σ̂ from the residuals divides by n − k_eff with k_eff = 1 (the data determine one
    parameter), not n − 2; its standard error is the prior's. Independent reference: the
    closed-form σ̂ of the one-parameter fit."""
    rng = np.random.default_rng(12)
    x = np.linspace(0.0, 1.0, 10)
    y = 2.0 * x + SIGMA * rng.standard_normal(10)
    X = np.stack([x, np.zeros(10)], 1)  # the data do not see u_1
    tau = 0.01
    prior = (np.array([0.0]), np.array([[0.0, 1.0 / tau]]))  # u_1 / τ
    out = lsq.solve(_linear(X, y, prior), np.zeros(2))
    assert out.converged, out.message
    b = float(x @ y) / float(x @ x)
    sigma_hat = math.sqrt(float(np.sum((y - b * x) ** 2)) / (10 - 1))
    assert out.cov.k_eff == pytest.approx(1.0, abs=1e-9)
    assert out.noise_um == pytest.approx(sigma_hat, rel=1e-6)
    assert out.cov.se[1] == pytest.approx(tau, rel=1e-9)


def test_status_says_why_the_fit_stopped():
    """Converged means the stop's own criterion holds at the answer; a budget spent before
    it holds is `BUDGET`, and an unknown status is refused."""
    y = data(13)
    out = lsq.solve(exp_model(y), np.array([1.5, 0.1]))
    assert out.status is lsq.Status.CONVERGED and out.converged
    assert out.step_se <= lsq.SE_TOL
    short = lsq.solve(exp_model(y), np.array([1.5, 0.1]), max_evaluations=1)
    assert short.status is lsq.Status.BUDGET and not short.converged
    assert short.step_se > lsq.SE_TOL
    assert short.status == "budget"  # its JSON string
    with pytest.raises(ValueError):
        dataclasses.replace(out, status="done")


def test_errors_widen_where_the_misfit_exceeds_the_noise():
    """σ stated too small (0.1 of the real noise): the fit is weighted with it, but the
    standard errors the core reports (`errors`) are those of the misfit per degree of
    freedom, as the closed-form OLS errors with σ̂ give them."""
    rng = np.random.default_rng(14)
    X = np.stack([np.ones_like(T), T], 1)
    y = X @ np.array([0.5, -0.2]) + SIGMA * rng.standard_normal(T.size)
    out = lsq.solve(_linear(X, y), np.zeros(2), noise_um=0.1 * SIGMA)
    beta = np.linalg.lstsq(X, y, rcond=None)[0]
    s2 = float(np.sum((y - X @ beta) ** 2)) / (T.size - 2)
    se_ols = np.sqrt(np.diag(s2 * np.linalg.inv(X.T @ X)))
    np.testing.assert_allclose(out.errors.se, se_ols, rtol=1e-6)
    assert out.error_scale_um == pytest.approx(math.sqrt(s2), rel=1e-9)
    assert out.error_dof == pytest.approx(T.size - 2, rel=1e-9)
    np.testing.assert_allclose(out.cov.se, se_ols * 0.1 * SIGMA / math.sqrt(s2), rtol=1e-6)


def test_the_resolution_check_measures_what_refining_moves():
    """A linear model y = X u: at a point the fit left short of its minimum (0.3 SE in
    its level), finer rows that differ by δ move the answer by (X'X)⁻¹X'δ, whatever the
    step left: the check against the finer level subtracts the coarse rows' own step
    (without it the leftover step reads as a discretisation error, and a defect
    correction that cannot move re-runs until its count runs out)."""
    rng = np.random.default_rng(0)
    n, sigma = 200, 0.5
    X = np.column_stack([np.ones(n), np.linspace(-1, 1, n)])
    y = X @ np.array([2.0, -1.0]) + sigma * rng.standard_normal(n)
    u_hat = np.linalg.lstsq(X, y, rcond=None)[0]
    se = sigma * np.sqrt(np.diag(np.linalg.inv(X.T @ X)))
    u = u_hat + np.array([0.3, 0.0]) * se  # where the fit's own stop left it

    def pt(shift):
        m = X @ u + shift
        return lsq.Point(u=u.copy(), r=m - y, predicted=m, J=X, r_prior=np.zeros(0),
                         J_prior=np.zeros((0, 2)), usable=True)

    delta = 0.005 * X[:, 1]  # the finer level tilts the rows
    move = np.linalg.solve(X.T @ X, X.T @ delta) / se
    alone = lsq.step_in_standard_errors(pt(delta), sigma)[0]
    refined = lsq.step_in_standard_errors(pt(delta), sigma, relative_to=pt(0.0))[0]
    assert refined == pytest.approx(np.max(np.abs(move)), rel=1e-9)
    assert 0.05 < refined < 0.1 < 0.29 < alone  # alone: the leftover step counted too
    assert lsq.step_in_standard_errors(pt(0.0), sigma, relative_to=pt(0.0))[0] == 0.0


def test_settled_stops_on_the_data_misfit_and_says_so():
    """`settled`: a fit whose answer is its misfit (the shape's refit, a candidate law)
    stops once three evaluations lower the data's ½χ² by less than the threshold. With a
    Jacobian at half its true scale the parameter stop needs 25 evaluations; the misfit
    stop ends sooner, says which stop it was, and its ½χ² is within 1.5 of the true least
    squares minimum (scipy's, with the true Jacobian)."""
    from scipy.optimize import least_squares

    y = data(0)
    plain = lsq.solve(exp_model(y, jacobian_scale=0.5), np.array([0.0, 0.2]),
                      noise_um=SIGMA, max_evaluations=40)
    out = lsq.solve(exp_model(y, jacobian_scale=0.5), np.array([0.0, 0.2]),
                    noise_um=SIGMA, max_evaluations=40, settled=1.0)
    assert out.status == "converged" and "converged in the misfit" in out.message
    assert out.evaluations < plain.evaluations
    best = least_squares(lambda u: (math.exp(u[0]) * np.exp(-u[1] * T) - y) / SIGMA,
                         [0.0, 0.2])
    chi = 0.5 * float(out.point.r @ out.point.r) / SIGMA ** 2
    assert 0.0 <= chi - 0.5 * float(best.fun @ best.fun) < 1.5


def test_settled_rmse_stops_on_the_relative_misfit_and_says_so():
    """`settled_rmse`: the misfit stop relative to the RMSE itself (the shape's refit,
    whose RMSE enters only comparisons with tolerances of 1 % (`LOO_TIE`) and 5 %). With a
    Jacobian at half its true scale the parameter stop needs 25 evaluations, creeping the
    last ~0.4 % of the RMSE over its last 9; stopping once three accepted steps lowered the
    RMSE by less than 0.2 % ends sooner, says which stop it was, and is within half of
    that 1 % of the true least squares minimum (scipy's, with the true Jacobian). A
    threshold of 0 never stops it before the parameter stop."""
    y = data(0)
    plain = lsq.solve(exp_model(y, jacobian_scale=0.5), np.array([0.0, 0.2]),
                      noise_um=SIGMA, max_evaluations=40)
    out = lsq.solve(exp_model(y, jacobian_scale=0.5), np.array([0.0, 0.2]),
                    noise_um=SIGMA, max_evaluations=40, settled_rmse=2e-3)
    assert out.status == "converged" and "lowered the data's RMSE by" in out.message
    assert out.evaluations < plain.evaluations
    assert 0.0 <= out.point.rms_um / least_squares_rmse(y) - 1.0 < 5e-3
    never = lsq.solve(exp_model(y, jacobian_scale=0.5), np.array([0.0, 0.2]),
                      noise_um=SIGMA, max_evaluations=40, settled_rmse=0.0)
    assert never.evaluations == plain.evaluations and "RMSE" not in never.message


def test_settled_rmse_is_not_fooled_by_rejected_trials():
    """Three trials in a row that fail (a trust region too wide for the model) lower the
    misfit by nothing, yet the misfit has not settled: `settled_rmse` counts accepted
    steps only, so the fit goes on to the minimum's neighbourhood (within 0.5 % of scipy's
    RMSE) instead of stopping at its start."""
    from jaxwear._core.errors import TrialFailed

    y = data(1)
    inner = exp_model(y)
    calls = []

    def evaluate(u):
        calls.append(u)
        if 2 <= len(calls) <= 4:  # the three trials after the start
            raise TrialFailed("the adaptive loop ran out of attempts")
        return inner(u)

    out = lsq.solve(evaluate, np.array([0.0, 0.2]), noise_um=SIGMA, max_evaluations=40,
                    settled_rmse=1e-3)
    assert out.evaluations > 4
    start_rmse = inner(np.array([0.0, 0.2])).rms_um
    assert out.point.rms_um < 0.5 * start_rmse
    best = least_squares_rmse(y)
    assert 0.0 <= out.point.rms_um / best - 1.0 < 5e-3


def test_settled_rmse_stops_where_the_quadratic_model_leaves_less_than_it():
    """At a numerical floor (the model's rows jump by 0.005 with u, as an adaptive
    integrator's error does) trials near the minimum are rejected one after another:
    without a misfit stop the fit stalls after 10 evaluations. `settled_rmse` also stops
    where the next Gauss-Newton step predicts the RMSE lower by less than its fraction
    (what the quadratic model says is left), says so, and is then within 0.5 % of the
    true least-squares RMSE (scipy's, without the floor). Why: the fatigue study's shape
    refit, whose last three trials (1.1-1.7 s each) were rejected at the floor with
    0.31 % predicted left."""
    y = data(2)
    plain = lsq.solve(exp_model(y, jitter=0.005), np.array([0.0, 0.2]), noise_um=SIGMA,
                      max_evaluations=40)
    out = lsq.solve(exp_model(y, jitter=0.005), np.array([0.0, 0.2]), noise_um=SIGMA,
                    max_evaluations=40, settled_rmse=4e-3)
    assert plain.status == "stalled"
    assert out.status == "converged" and "step predicts the data's RMSE lower" in out.message
    assert out.evaluations < plain.evaluations
    assert 0.0 <= out.point.rms_um / least_squares_rmse(y) - 1.0 < 5e-3


def test_settled_rmse_stops_where_the_step_promises_less_than_the_numerical_floor():
    """A fit whose answer is its misfit (`settled_rmse`) also stops once the next
    Gauss-Newton step predicts a decrease of ½χ² below the floor the model's numerical
    error can move it by (rows that jump by 0.02 with u, `error_um` 0.02: a floor of
    Σ|r|·0.02/σ²) and a trial from there has failed, and says so, whatever fraction of
    the RMSE it predicts left (here a threshold too small to stop it); without it the fit
    stalls on trials the floor decides. Its RMSE is then within 1 % of the RMSE the fit
    reaches by going on, and within 5 % of the true least-squares RMSE (scipy's, without
    the floor): the jitter
    alone (RMS 0.014 beside σ = 0.05) adds 4 % in quadrature. Why: the fatigue study's
    shape refit, whose last five trials (four rejected, ~1 s each) moved its RMSE within
    0.45 %."""
    y = data(3)
    plain = lsq.solve(exp_model(y, jitter=0.02), np.array([0.0, 0.2]), noise_um=SIGMA,
                      max_evaluations=40)
    out = lsq.solve(exp_model(y, jitter=0.02), np.array([0.0, 0.2]), noise_um=SIGMA,
                    max_evaluations=40, settled_rmse=1e-12)
    assert out.status == "converged" and "numerical error" in out.message, out.message
    assert "the last trial was rejected" in out.message
    assert out.predicted_decrease <= out.floor
    assert out.evaluations < plain.evaluations
    assert out.point.rms_um < 1.01 * plain.point.rms_um
    assert 0.0 <= out.point.rms_um / least_squares_rmse(y) - 1.0 < 5e-2
    # a fit whose answer is its parameters is not stopped by it
    assert plain.status != "converged" or "numerical error" not in plain.message


def least_squares_rmse(y) -> float:
    """The RMSE of the least-squares minimum of a·exp(-k t) against y (scipy's)."""
    from scipy.optimize import least_squares

    best = least_squares(lambda u: (math.exp(u[0]) * np.exp(-u[1] * T) - y), [0.0, 0.2])
    return math.sqrt(float(best.fun @ best.fun) / T.size)


def test_robust_start_rescales_a_power_law_in_one_evaluation():
    """Depth ∝ K^β (β = 0.8: wear widens the contact) from a start 20x low: the factor a of
    the depths, taken to the power 1/β from the Jacobian, lands on K exactly (power-law
    identity), where K·a alone falls short (a = 20^0.8 = 11.0, then 1.6, ...)."""
    beta, k_true = 0.8, 2.5e-13
    shape = 1.0 + 0.3 * T
    y = (k_true / 1e-13) ** beta * shape

    def evaluate(u):
        m = math.exp(beta * u[0]) * shape  # u[0] = ln(K / 1e-13)
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=beta * m[:, None],
                         r_prior=np.zeros(0), J_prior=np.zeros((0, 1)), usable=True)

    u0 = np.array([math.log(k_true / 1e-13 / 20.0)])
    u, pt, evals, why = lsq.robust_start(evaluate, u0, 0, measured=y)
    assert why is None
    assert evals == 2  # the start and one rescale
    assert math.exp(u[0]) * 1e-13 == pytest.approx(k_true, rel=1e-9)


def test_a_column_zero_at_the_start_gets_its_own_scale():
    """A shape parameter whose strength starts off has a zero column: the damping's scale
    stands in the largest norm for it only until its own first nonzero norm, which then
    replaces the stand-in even where it is smaller (the scale otherwise only grows)."""
    from jaxwear._inference.lsq._solve import _column_scale, _scaling

    J0 = np.array([[3.0, 0.0], [4.0, 0.0]])  # norms 5 and 0
    D = _column_scale(J0, None)
    assert D.tolist() == [5.0, 0.0]
    assert _scaling(D).tolist() == [5.0, 5.0]  # the stand-in
    J1 = np.array([[3.0, 0.6], [4.0, 0.8]])  # the second column's own norm: 1
    D = _column_scale(J1, D)
    assert _scaling(D).tolist() == [5.0, 1.0]
    J2 = np.array([[0.3, 0.06], [0.4, 0.08]])  # both smaller: the scale only grows
    assert _scaling(_column_scale(J2, D)).tolist() == [5.0, 1.0]


def test_a_gauss_newton_step_the_projection_alters_is_not_taken_whole():
    """Near the answer the core takes the full Gauss-Newton step, the step its quadratic
    model judged. Where `project` (a constraint the box cannot state) moves that step, the
    trial would be another point: the damped step is proposed instead. Linear model, answer
    u* = (2, 0), `project` caps u[0] at 1.5: the full step from anywhere is u*, projected
    (1.5, 0); it is never a trial."""
    X = np.stack([np.ones_like(T), T], 1)
    y = X @ np.array([2.0, 0.0])
    calls = []

    def evaluate(u):
        calls.append(np.array(u))
        m = X @ u
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=X,
                         r_prior=np.zeros(0), J_prior=np.zeros((0, 2)), usable=True)

    def project(u):
        return np.array([min(u[0], 1.5), u[1]])

    # a large σ: the start is within a standard error, where the full step would be taken
    lsq.solve(evaluate, np.array([1.0, 0.5]), noise_um=50.0, max_evaluations=6,
              project=project)
    assert len(calls) > 1
    assert not any(np.allclose(c, [1.5, 0.0], atol=1e-9) for c in calls[1:]), calls


def test_robust_start_without_the_scale_column_rescales_by_the_factor_alone():
    """A Jacobian whose K_d column was not computed (zero: a fit computing only some
    columns) says nothing about depth's elasticity: the rescale is K·a, not K·a^(1/0.25)."""
    shape = 1.0 + 0.3 * T
    y = 2.0 * shape

    def evaluate(u):
        m = math.exp(u[0]) * shape
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m,
                         J=np.zeros((T.size, 1)), r_prior=np.zeros(0),
                         J_prior=np.zeros((0, 1)), usable=True)

    u, pt, evals, why = lsq.robust_start(evaluate, np.array([0.0]), 0, measured=y)
    assert why is None and evals == 2
    assert math.exp(u[0]) == pytest.approx(2.0, rel=1e-12)


def test_a_start_evaluated_elsewhere_counts_to_the_budget_where_asked():
    """`point0_counts` (the shape refit's start evaluated in a thread ahead of it): the
    same fit, evaluation for evaluation, as the one that evaluates its start itself, and
    the same budget; without it a given start is free (a fit continued from another)."""
    y = data(6)
    u0 = np.array([1.5, 0.1])
    own_calls, given_calls = [], []
    own = lsq.solve(exp_model(y, calls=own_calls), u0, max_evaluations=4)
    pt0 = exp_model(y)(u0)
    given = lsq.solve(exp_model(y, calls=given_calls), u0, point0=pt0, point0_counts=True,
                      max_evaluations=4)
    assert own.status == given.status == "budget"
    assert given.evaluations == own.evaluations == 4
    assert np.array_equal(given.u, own.u)
    assert len(given_calls) == len(own_calls) - 1  # its start was not evaluated again
    free = lsq.solve(exp_model(y), u0, point0=pt0, max_evaluations=4)
    assert free.evaluations == 4 and not np.array_equal(free.u, own.u)
