"""The importance sampler of `predict --method importance` (`_predict_importance`) on a
problem whose posterior is known in closed form: a linear model y = A θ + ε, ε ~ N(0, σ²I),
prior θ ~ N(0, τ²I), posterior N(μ, Σ) with Σ = (AᵀA/σ² + I/τ²)⁻¹, μ = Σ Aᵀy/σ². No wear
model: the sampler's own arithmetic (proposal density, PSIS weights, k̂, ESS, weighted
quantiles, the adaptive round) against the closed form and scipy.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from jaxwear._analyses.predict.importance import (
    ESS_SHARE_GOOD,
    GROW_MIN,
    K_GOOD,
    K_USABLE,
    ess_of,
    importance_sample,
    t_logpdf,
    t_sample,
    weighted_quantile,
)

D = 3


@pytest.fixture(scope="module")
def gaussian():
    """(log density of θ, μ, Σ) of the linear-Gaussian posterior (20 rows, 3 parameters)."""
    rng = np.random.default_rng(1)
    A = rng.standard_normal((20, D))
    sigma, tau = 0.5, 3.0
    y = A @ np.array([1.0, -2.0, 0.5]) + sigma * rng.standard_normal(20)
    prec = A.T @ A / sigma ** 2 + np.eye(D) / tau ** 2
    cov = np.linalg.inv(prec)
    mu = cov @ A.T @ y / sigma ** 2

    def logp(x):
        r = x @ A.T - y
        return -0.5 * np.sum(r ** 2, axis=1) / sigma ** 2 - 0.5 * np.sum(x ** 2, axis=1) / tau ** 2

    return logp, mu, cov


def test_proposal_density_is_scipys_multivariate_t():
    rng = np.random.default_rng(0)
    mean = np.array([0.3, -1.0, 2.0])
    L = np.array([[1.0, 0, 0], [0.4, 0.7, 0], [-0.2, 0.1, 1.5]])
    x = t_sample(rng, mean, L, 5, nu=7.0)
    ref = stats.multivariate_t(loc=mean, shape=L @ L.T, df=7.0).logpdf(x)
    np.testing.assert_allclose(t_logpdf(x, mean, L, nu=7.0), ref, rtol=1e-12)


def test_laplace_proposal_recovers_the_closed_form_posterior(gaussian):
    """The proposal a Laplace fit gives (centre and covariance of the posterior, t tails):
    k̂ well below 0.5, the weighted means within 4 Monte Carlo errors (σ/√ESS) of μ, the
    90 % interval's ends within 0.1 σ of the normal quantiles, and the ESS of each mean
    within a factor 2 of the weights' ESS (the same weights)."""
    logp, mu, cov = gaussian
    L = np.linalg.cholesky(cov)
    x, w, hist = importance_sample(logp, mu, L, 1000, 2, np.random.default_rng(2), rounds=2)
    assert len(hist) == 1 and max(hist[0]["k_hat"]) < K_GOOD, hist
    # the pilot was good: the round completed from the same proposal, no draw lost
    assert hist[0]["pilot"]["draws"] == 250 and hist[0]["draws"] == 1000 == x.shape[1], hist
    xf, wp = x.reshape(-1, D), (w / 2).reshape(-1)
    sd = np.sqrt(np.diag(cov))
    for i in range(D):
        ess = ess_of(wp, xf[:, i])
        assert 0.5 * ess_of(wp) < ess < 2 * ess_of(wp)
        assert abs(wp @ xf[:, i] - mu[i]) < 4 * sd[i] / math.sqrt(ess)
        for q in (0.05, 0.95):
            ref = mu[i] + sd[i] * stats.norm.ppf(q)
            assert abs(weighted_quantile(xf[:, i], wp, q) - ref) < 0.1 * sd[i]


def test_too_narrow_a_proposal_is_caught_and_moved(gaussian):
    """A proposal a third of the posterior's width, off centre: the first round's k̂ says
    the weights are unreliable (> 0.7, Vehtari et al.: the tail of p/q is too heavy); the
    second round, moved to the draws' weighted moments, is good (k̂ ≤ 0.5) and recovers μ."""
    logp, mu, cov = gaussian
    L = np.linalg.cholesky(cov)
    x, w, hist = importance_sample(logp, mu + 1.0 * np.sqrt(np.diag(cov)), L / 3, 1000, 2,
                                   np.random.default_rng(3), rounds=3)
    assert max(hist[0]["k_hat"]) > K_USABLE, hist
    assert max(hist[-1]["k_hat"]) <= K_GOOD, hist
    xf, wp = x.reshape(-1, D), (w / 2).reshape(-1)
    sd = np.sqrt(np.diag(cov))
    for i in range(D):
        assert abs(wp @ xf[:, i] - mu[i]) < 4 * sd[i] / math.sqrt(ess_of(wp, xf[:, i]))


def _truncated_at_mean(gaussian):
    """The posterior with θ₀ truncated at its mean μ₀ (uniform-bounded strengths are such
    priors): (log density, cut, Cholesky factor of Σ, sd of θ₀, the exact mean of θ₀)."""
    logp, mu, cov = gaussian
    cut = mu[0]

    def truncated(x):
        return np.where(x[:, 0] > cut, logp(x), -np.inf)

    s0 = math.sqrt(cov[0, 0])
    exact = mu[0] + s0 * math.sqrt(2 / math.pi)  # half-normal mean above the cut
    return truncated, cut, np.linalg.cholesky(cov), s0, exact


def test_draws_outside_the_support_weigh_nothing(gaussian):
    """A prior truncated at θ₀ > μ₀: draws beyond it get weight 0 and the weighted mean of
    θ₀ is the truncated normal's."""
    truncated, cut, L, s0, exact = _truncated_at_mean(gaussian)
    mu = gaussian[1]
    x, w, hist = importance_sample(truncated, mu, L, 2000, 2, np.random.default_rng(4),
                                   rounds=1)
    xf, wp = x.reshape(-1, D), (w / 2).reshape(-1)
    assert np.all(wp[xf[:, 0] <= cut] == 0) and hist[0]["outside_support"] > 0
    assert abs(wp @ xf[:, 0] - exact) < 4 * s0 / math.sqrt(ess_of(wp, xf[:, 0]))


def test_proposal_restricted_to_the_support_gives_the_same_posterior(gaussian):
    """The same truncated prior with the support given: every draw lies inside it (the
    model would run only there), the weights are unchanged in law (q restricted to the
    support differs from q by a constant), so the weighted mean is again the truncated
    normal's, with a larger effective sample from the same number of draws."""
    truncated, cut, L, s0, exact = _truncated_at_mean(gaussian)
    mu = gaussian[1]
    x, w, hist = importance_sample(truncated, mu, L, 2000, 2, np.random.default_rng(4),
                                   rounds=1, support=lambda x: x[:, 0] > cut)
    xf, wp = x.reshape(-1, D), (w / 2).reshape(-1)
    assert np.all(xf[:, 0] > cut) and hist[0]["outside_support"] == 0
    assert 3000 < hist[0]["proposals_rejected"] < 5000  # about half of ~8000 proposals
    assert abs(wp @ xf[:, 0] - exact) < 4 * s0 / math.sqrt(ess_of(wp, xf[:, 0]))
    plain = importance_sample(truncated, mu, L, 2000, 2, np.random.default_rng(4), rounds=1)
    assert min(hist[0]["ess"]) > 1.5 * min(plain[2][0]["ess"])


def test_too_wide_a_proposal_is_moved_for_its_few_weights(gaussian):
    """A proposal 2.5 times the posterior's width: the weights are reliable (k̂ ≤ 0.5: p/q
    is bounded) but carried by few draws (ESS below ESS_SHARE_GOOD of them: for a normal
    proposal of s times the width, ESS/n = (√(2s² − 1)/s²)^d = 0.16 at s = 2.5, d = 3, less
    with the t's tails); the second round, moved to the weighted moments, has at least
    twice the ESS and recovers μ."""
    logp, mu, cov = gaussian
    L = np.linalg.cholesky(cov)
    x, w, hist = importance_sample(logp, mu, 2.5 * L, 1000, 2, np.random.default_rng(5),
                                   rounds=2)
    assert max(hist[0]["k_hat"]) <= K_GOOD, hist
    # decided on the pilot (a quarter of the draws), the second round a full one
    pilot = hist[0]["draws"]
    assert pilot == 250 and hist[1]["draws"] == 1000, hist
    assert min(hist[0]["ess"]) < ESS_SHARE_GOOD * pilot and len(hist) == 2, hist
    assert min(hist[1]["ess"]) / 1000 > 2 * min(hist[0]["ess"]) / pilot, hist
    xf, wp = x.reshape(-1, D), (w / 2).reshape(-1)
    sd = np.sqrt(np.diag(cov))
    for i in range(D):
        assert abs(wp @ xf[:, i] - mu[i]) < 4 * sd[i] / math.sqrt(ess_of(wp, xf[:, i]))


def test_the_answers_round_grows_until_every_mean_has_its_ess(gaussian):
    """The answer's round stops once every coordinate's ESS reaches a target (the CLI's
    `--ess`): from a proposal 1.6x too wide (weights' ESS ~50 % of the draws, above the
    share that would move it, so the pilot's round answers), 600 effective draws need ~2 x
    420 of the 2 x 1000 allowed; the round stops with every ESS at or above 600, well
    before 1 000 per batch, the means
    within 4 Monte Carlo errors of μ; a target no draw count reaches takes all the draws."""
    logp, mu, cov = gaussian
    L = np.linalg.cholesky(cov)
    calls = []

    def enough(x, w, k):
        xf, wp = x.reshape(-1, D), (w / 2).reshape(-1)
        ess = min(ess_of(wp, xf[:, i]) for i in range(D))
        calls.append((x.shape[1], ess))
        return ess >= target, x.shape[1] * 1.1 * target / ess, f"ESS {ess:.0f}"

    target = 600
    x, w, hist = importance_sample(logp, mu, 1.6 * L, 1000, 2, np.random.default_rng(6),
                                   rounds=2, enough=enough)
    assert len(hist) == 1 and hist[0]["pilot"]["draws"] == 250, hist
    m = x.shape[1]
    assert m == hist[0]["draws"] < 1000 and len(calls) >= 2, (hist, calls)
    xf, wp = x.reshape(-1, D), (w / 2).reshape(-1)
    sd = np.sqrt(np.diag(cov))
    for i in range(D):
        ess = ess_of(wp, xf[:, i])
        assert ess >= target
        assert abs(wp @ xf[:, i] - mu[i]) < 4 * sd[i] / math.sqrt(ess)
    # every growth step drew at least GROW_MIN more
    assert all(b - a >= GROW_MIN for (a, _), (b, _) in zip(calls, calls[1:])), calls
    calls.clear()
    target = 10 ** 6
    x, _, hist = importance_sample(logp, mu, 1.6 * L, 1000, 2, np.random.default_rng(6),
                                   rounds=2, enough=enough)
    assert x.shape[1] == 1000 == hist[-1]["draws"], hist


def test_sampling_tolerance_bounds_the_log_likelihoods_error():
    """The samplers' wear tolerance (`sampling_tolerance_m`): a depth error of at most tol
    on each row moves the Gaussian log likelihood by at most LOGP_ERROR at any residual
    vector with χ² ≤ 2(n + d), worst case (every error along its residual's sign); where
    the noise is small against the study's tolerance (a long rig profile), the study's
    stays."""
    from types import SimpleNamespace

    from jaxwear._analyses.predict.nuts import LOGP_ERROR, sampling_tolerance_m

    def problem(n, p, tol_m=2e-9):
        sched = SimpleNamespace(adaptive=True, tolerance=np.asarray(tol_m))
        return SimpleNamespace(schedule=sched, n_data=n, names=[f"p{i}" for i in range(p)])

    rng = np.random.default_rng(7)
    for n, p, sigma in [(3, 4, 5.0), (10, 3, 4.0), (1, 1, 50.0)]:
        tol = sampling_tolerance_m(problem(n, p), None, noise_um=sigma) * 1e6  # µm
        assert tol > 0.002
        r = rng.standard_normal((2000, n))
        r *= (np.sqrt(2 * (n + p)) * sigma / np.linalg.norm(r, axis=1))[:, None]
        dl = 0.5 * (np.sum((r + tol * np.sign(r)) ** 2, 1) - np.sum(r ** 2, 1)) / sigma ** 2
        # (the second-order term n tol²/(2σ²) adds < 1 % of the bound)
        assert np.max(np.abs(dl)) <= LOGP_ERROR * 1.01, (n, p, np.max(dl))
        assert np.max(np.abs(dl)) > 0.5 * LOGP_ERROR  # and not far looser than it needs
    # 180 rows at σ = 0.1 µm: far below the study's 0.002 µm, which stays
    assert sampling_tolerance_m(problem(180, 6), None, noise_um=0.1) == 2e-9
    # σ estimated: the bound at σ̂'s lower edge, a smaller σ than σ̂
    fit = SimpleNamespace(noise_um=5.0, error_dof=10.0)
    assert sampling_tolerance_m(problem(3, 4), fit) < sampling_tolerance_m(
        problem(3, 4), None, noise_um=5.0)


def _running_in_packing():
    """A packing as the boom's with running-in: K_d (log, unbounded), a clearance (linear,
    Gaussian prior truncated to [0, 1] mm), the running-in amplitude (linear, uniform on
    [0, 100], a product strength: value = linear · e^(−u_distance)) and its distance (log,
    log-uniform on [1e-3, 1e5] m)."""
    from jaxwear._inference.packing import Column, packing_of

    return packing_of([
        (Column("K_d_per_Pa", "K_d_per_Pa", None, True, 1.0, 1.0, 0.0, math.inf), 1.5e-14),
        (Column("clearance_mm/b", "clearance_mm", 0, False, 0.01, 1e-3, 0.0, 1.0,
                prior_sd=0.005, prior_centre=0.1), 0.1),
        (Column("running_in_amplitude", "running_in_amplitude", None, False, 1.0, 1.0, 0.0,
                100.0, strength=True), 1.0),
        (Column("running_in_distance_m", "running_in_distance_m", None, True, 1.0, 1.0, 1e-3,
                1e5), 20.0)])


@pytest.mark.parametrize("given", [True, False])
def test_support_coordinates_invert_and_their_jacobian_is_the_finite_differences(given):
    """x ↦ y ↦ x is the identity to round-off, and log |det ∂y/∂x| (which enters the moved
    proposal's density) agrees with a central-difference Jacobian's; with the noise
    estimated, x's last coordinate ln σ scales u = û + (σ/σ̂) L v."""
    from jaxwear._analyses.predict.importance import SupportCoordinates

    pk = _running_in_packing()
    assert pk._pairs() == [(2, 3)]
    L = np.linalg.cholesky(np.array([[1, 0.3, 0, 0], [0.3, 1, 0, 0.2], [0, 0, 2, 0.5],
                                     [0, 0.2, 0.5, 1.5]])) * 0.3
    c = SupportCoordinates(pk, np.array([0.1, 0.2, 1.0, 0.5]), L, math.log(2.0),
                           scaled=not given, given=given)
    d = 4 + (0 if given else 1)
    x = np.random.default_rng(0).standard_normal((40, d)) * 0.5
    y, logdet = c.y(x)
    assert np.all(np.isfinite(y)) and np.all(np.isfinite(logdet))
    np.testing.assert_allclose(c.x(y), x, atol=1e-10)
    h = 1e-6
    for k in range(5):
        J = np.stack([(c.y(x[k] + h * e)[0][0] - c.y(x[k] - h * e)[0][0]) / (2 * h)
                      for e in np.eye(d)], axis=1)
        assert abs(np.linalg.slogdet(J)[1] - logdet[k]) < 1e-6
    # outside the amplitude's box (value < 0): no y
    u_out = np.array([0.1, 0.2, -1.5, 0.5])  # linear coordinate 1 − 1.5 < 0
    x_out = np.linalg.solve(L, u_out - np.array([0.1, 0.2, 1.0, 0.5]))
    if not given:
        x_out = np.append(x_out, math.log(2.0))
    assert np.all(np.isnan(c.y(x_out[None, :])[0]))


def test_a_moved_proposal_in_the_supports_coordinates_fits_a_prior_box():
    """The boom's running-in posterior in miniature: the data determine the product a·S_r
    (the amplitude's linear coordinate, N(2, 0.2²)), K_d and the clearance, not a, whose
    posterior is then its prior, uniform on [0, 100] (mean 50, sd 100/√12; S_r ∝ 1/a stays
    inside its own bounds for every a above 6e-4). From a Laplace proposal far wider than the
    posterior along the undetermined direction (as the boom's), the second round's
    proposal moved in the support's coordinates has ≥ 1.25x the weights' ESS of the one
    moved in the whitened x (measured 1.4-1.6x over three seeds, 0.71-0.84 of the draws),
    and both recover the box's mean and sd within 4 Monte Carlo errors."""
    from jaxwear._analyses.predict.importance import SupportCoordinates

    pk = _running_in_packing()
    u_hat = np.array([0.0, 0.0, 2.0, 0.0])
    L = np.diag([0.05, 0.5, 0.2, 4.0])

    def logp(x):
        u = u_hat + x @ L.T
        v = np.array([pk.values_np(ui) for ui in u])
        # likelihood on K_d and the product, the clearance's prior, the amplitude's uniform
        # prior in its value (− u_distance: the pair's Jacobian), S_r's log-uniform (flat)
        lp = (-0.5 * (u[:, 0] / 0.05) ** 2 - 0.5 * ((v[:, 1] - 0.1) / 0.005) ** 2
              - 0.5 * ((u[:, 2] - 2.0) / 0.2) ** 2 - u[:, 3])
        ok = ((v[:, 1] >= 0) & (v[:, 1] <= 1) & (v[:, 2] >= 0) & (v[:, 2] <= 100)
              & (v[:, 3] >= 1e-3) & (v[:, 3] <= 1e5))
        return np.where(ok, lp, -np.inf)

    coords = SupportCoordinates(pk, u_hat, L, 0.0, scaled=False, given=True)
    share = {}
    for name, cc in (("x", None), ("y", coords)):
        x, w, hist = importance_sample(logp, np.zeros(4), np.eye(4), 1000, 2,
                                       np.random.default_rng(0), rounds=2,
                                       support=lambda x_: np.isfinite(logp(x_)), coords=cc)
        assert len(hist) == 2 and hist[1]["draws"] == 1000, hist
        assert hist[1]["proposal"] == ("support coordinates" if cc else "whitened"), hist
        assert max(hist[1]["k_hat"]) <= K_GOOD, hist
        share[name] = min(hist[1]["ess"]) / 1000
        xf, wp = x.reshape(-1, 4), (w / 2).reshape(-1)
        a = np.array([pk.values_np(u) for u in u_hat + xf @ L.T])[:, 2]
        ess = ess_of(wp, a)
        sd = 100 / math.sqrt(12)
        assert abs(wp @ a - 50.0) < 4 * sd / math.sqrt(ess), name
        # the sd's Monte Carlo error: that of the mean of (a − 50)², var 100⁴/180
        assert abs(wp @ (a - 50.0) ** 2 - sd ** 2) < 4 * 100 ** 2 / math.sqrt(180 * ess), name
    assert share["y"] >= 1.25 * share["x"], share


def test_the_laplace_proposal_in_the_supports_coordinates_starts_on_the_box():
    """The same miniature, its Laplace fit far wider than the box along the undetermined
    direction (the amplitude's linearised spread): carried to the support's coordinates and
    combined with the box (`laplace_start`), the first round is already the answer (k̂ ≤
    0.5, weights' ESS over ESS_SHARE_GOOD of its draws), every value's ESS reaches 400 in
    fewer draws than from the Laplace t in x (which must move first: measured 250-408
    against 550-1418 per batch over three cases and four seeds), and the box's mean and sd
    are recovered within 4 Monte Carlo errors."""
    from jaxwear._analyses.predict.importance import SupportCoordinates

    pk = _running_in_packing()
    u_hat = np.array([0.0, 0.0, -0.78, 0.0])  # the product's linear coordinate 0.22
    L = np.array([[0.05, 0, 0, 0], [0, 0.5, 0, 0], [0, 0, 0.02, 0], [0.1, 0, 0.3, 4.0]])

    def values(x):
        return np.array([pk.values_np(u) for u in u_hat + x @ L.T])

    def logp(x):
        u, v = u_hat + x @ L.T, values(x)
        lp = (-0.5 * (u[:, 0] / 0.05) ** 2 - 0.5 * ((v[:, 1] - 0.1) / 0.005) ** 2
              - 0.5 * ((u[:, 2] + 0.78) / 0.02) ** 2 - u[:, 3])
        ok = ((v[:, 1] >= 0) & (v[:, 1] <= 1) & (v[:, 2] >= 0) & (v[:, 2] <= 100)
              & (v[:, 3] >= 1e-3) & (v[:, 3] <= 1e5))
        return np.where(ok, lp, -np.inf)

    def enough(x, w, k):
        v, wp = values(x.reshape(-1, 4)), (w / 2).reshape(-1)
        ess = min(ess_of(wp, v[:, i]) for i in range(4))
        return ess >= 400 and max(k) <= K_GOOD, x.shape[1] * 1.1 * 400 / ess, f"ESS {ess:.0f}"

    coords = SupportCoordinates(pk, u_hat, L, 0.0, scaled=False, given=True)
    start = coords.laplace_start(np.zeros(4), np.eye(4))
    assert start is not None
    total = {}
    for name, (m0, c0) in (("x", (np.zeros(4), np.eye(4))), ("y", start)):
        x, w, hist = importance_sample(logp, m0, c0, 1000, 2, np.random.default_rng(1),
                                       rounds=2, support=lambda x_: np.isfinite(logp(x_)),
                                       enough=enough, coords=coords, start_in_y=name == "y")
        total[name] = sum(h["draws"] for h in hist)
        if name == "y":
            assert len(hist) == 1 and hist[0]["proposal"] == "support coordinates", hist
            assert max(hist[0]["k_hat"]) <= K_GOOD, hist
            assert min(hist[0]["ess"]) >= ESS_SHARE_GOOD * hist[0]["draws"], hist
        a, wp = values(x.reshape(-1, 4))[:, 2], (w / 2).reshape(-1)
        ess, sd = ess_of(wp, a), 100 / math.sqrt(12)
        assert ess >= 400
        assert abs(wp @ a - 50.0) < 4 * sd / math.sqrt(ess), name
        assert abs(wp @ (a - 50.0) ** 2 - sd ** 2) < 4 * 100 ** 2 / math.sqrt(180 * ess), name
    assert total["y"] < total["x"], total
