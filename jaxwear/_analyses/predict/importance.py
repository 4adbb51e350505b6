"""`predict(method="importance")`: the posterior by importance sampling from the Laplace fit,
Pareto-smoothed (PSIS), with its diagnostics.

The posterior is the one NUTS samples (`_predict_nuts.log_density`: the same priors,
likelihood and whitened coordinates z = (v, ln σ), u = û + (σ/σ̂) L v). Proposal: a
multivariate Student-t with `NU` degrees of freedom centred at the fit, unit scale in v
(the Laplace approximation is N(0, I) there) and, when the noise is estimated, scale
1/√(2ν_σ) in ln σ (ν_σ its degrees of freedom): heavier tails than the posterior's where
the Laplace approximation is right, so that the weights p/q stay bounded. Where the prior
bounds parameters, the proposal lives in coordinates where it does not
(`SupportCoordinates.laplace_start`: the Laplace t carried there, each bounded direction
combined with its box; a direction the data leave to its prior then starts as that box, not
as the linearisation's spread, of which 7 % fell inside the box on the boom). Each draw costs
one forward run of the wear model (no gradient: a fifth to a third of NUTS's cost per
evaluation, and ~7 evaluations per NUTS step saved), on `workers` threads.

Weights are smoothed by PSIS (Vehtari et al. 2024, `arviz.psislw`) per batch; its k̂ says
whether they can be trusted: k̂ ≤ 0.5 good, ≤ 0.7 usable (the estimates' error then
converges, slowly), > 0.7 unreliable (flagged). When the first round's k̂ exceeds 0.5 the
proposal is moved to the weighted moments of the draws (mean and covariance, t tails
kept) and sampled again (`rounds`), in coordinates where the prior's bounds are none
(`SupportCoordinates`: a bounded parameter's logit; a posterior that is its prior's box,
as the boom's running-in amplitude, is a logistic there, which the t fits, where in the
whitened coordinates it fitted the box's edges badly); so it is where the weights' ESS is below
`ESS_SHARE_GOOD` of the draws (a proposal far wider than the posterior: reliable weights,
carried by few draws). A round that may move the proposal for its few effective draws
decides on a pilot of a quarter of them. The last round is the answer; it grows from its
pilot until every parameter's ESS reaches `ess_target` with R-hat ≤ `R_HAT_OK` and
k̂ ≤ `K_GOOD` (at most `draws` per batch). The densities and the draws' forecasts run at
the tolerance the noise allows (`_predict_nuts.sampling_tolerance_m`) and, where
`_predict.sampling_level` gives one, at a coarser level with the rows corrected at the
answer, checked at posterior draws after sampling (`check_level`; the fit's level again
where it fails).

Diagnostics per parameter (in the values' units): weighted mean, sd and quantiles; the
effective sample size of its mean, ESS_h = Σw(h − h̄)² / Σw²(h − h̄)² (w normalised,
Vehtari et al., eq. 6), and R-hat between the `chains` independent batches (each resampled
to equal weights, ArviZ's rank-normalised split R-hat). Overall: k̂ per batch and the
weights' ESS = 1/Σw².

When to use which (docs/guide/predict.md): `importance` when the Laplace fit is close to the
posterior (k̂ ≤ 0.7: the usual case with informative data, and minutes where NUTS takes
tens); `nuts` where k̂ says it is not (a posterior with a long tail or a curved valley, e.g.
the noise level estimated from three rows).
"""

from __future__ import annotations

import math
import time
import warnings
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np
from scipy import special

from jaxwear._analyses.predict.draws import DrawForecasts, new_measurements, run_forward
from jaxwear._analyses.predict.nuts import (
    _arviz,
    prior_density,
    sampling_setup,
    sampling_tolerance_m,
    with_tolerance,
)
from jaxwear._core.errors import InputError
from jaxwear._core.jit import jit
from jaxwear._core.log import log as _log
from jaxwear._inference.evaluation import forward_run
from jaxwear._physics.effects import product_pairs

NU = 7.0  # the proposal's Student-t degrees of freedom
K_GOOD, K_USABLE = 0.5, 0.7  # PSIS k̂ thresholds (Vehtari et al. 2024)
ESS_SHARE_GOOD = 0.25  # below this share of the draws, the weights' ESS moves the proposal
ESS_TARGET = 400  # the answer's round stops growing once every parameter's ESS reaches this
R_HAT_OK = 1.01  # ... and R-hat between the batches is at most this


def t_sample(rng, mean, chol, n: int, nu: float = NU) -> np.ndarray:
    """n draws (n, d) of the multivariate t_ν(mean, chol cholᵀ)."""
    d = len(mean)
    g = rng.standard_normal((n, d)) @ np.asarray(chol).T
    w = np.sqrt(rng.chisquare(nu, n) / nu)
    return np.asarray(mean)[None, :] + g / w[:, None]


def t_logpdf(x, mean, chol, nu: float = NU) -> np.ndarray:
    """Log density of the multivariate t_ν(mean, chol cholᵀ) at x (n, d)."""
    x = np.atleast_2d(x)
    d = x.shape[1]
    y = np.linalg.solve(np.asarray(chol), (x - np.asarray(mean)[None, :]).T)  # (d, n)
    q = np.sum(y ** 2, axis=0)
    logdet = float(np.sum(np.log(np.abs(np.diag(chol)))))
    return (special.gammaln((nu + d) / 2) - special.gammaln(nu / 2)
            - 0.5 * d * math.log(nu * math.pi) - logdet
            - 0.5 * (nu + d) * np.log1p(q / nu))


def psis(log_w):
    """(normalised smoothed weights (n,), k̂) of raw log weights (n,); -inf weights (outside
    the prior's support) stay zero."""
    az = _arviz()
    log_w = np.asarray(log_w, np.float64)
    ok = np.isfinite(log_w)
    w = np.zeros_like(log_w)
    if ok.sum() < 2:
        return w, math.inf
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lw, k = az.psislw(log_w[ok] - np.max(log_w[ok]))
    w[ok] = np.exp(np.asarray(lw) - np.max(lw))
    return w / w.sum(), float(k)


def ess_of(w, h=None) -> float:
    """Effective sample size of normalised weights w (n,): 1/Σw²; with values h (n,), of
    the weighted mean of h, Σw(h − h̄)² / Σw²(h − h̄)²."""
    w = np.asarray(w, np.float64)
    if h is None:
        return float(1.0 / np.sum(w ** 2))
    h = np.asarray(h, np.float64)
    dev2 = (h - np.sum(w * h)) ** 2
    den = float(np.sum(w ** 2 * dev2))
    return float(np.sum(w * dev2) / den) if den > 0 else float(1.0 / np.sum(w ** 2))


def weighted_quantile(h, w, q: float) -> float:
    """The q-quantile of values h (n,) with normalised weights w (n,) (linear between the
    mid-points of the weights' cumulative sum)."""
    order = np.argsort(h)
    h, w = np.asarray(h)[order], np.asarray(w)[order]
    c = np.cumsum(w) - 0.5 * w
    return float(np.interp(q, c, h))


def systematic_resample(w, n: int, rng) -> np.ndarray:
    """n indices drawn by systematic resampling of normalised weights w (n_draws,)."""
    pos = (rng.uniform() + np.arange(n)) / n
    return np.minimum(np.searchsorted(np.cumsum(w), pos), len(w) - 1)


class SupportCoordinates:
    """Coordinates y in which the prior's bounds are no bounds, for the proposals
    (`importance_sample`'s `coords`, `laplace_start`): a bounded parameter's value a (its
    logarithm for a log-fitted column, whose prior is then log-uniform) mapped by
    logit((a − lo)/(hi − lo)) (one bound: ln(a − lo) or ln(hi − a)); unbounded columns and
    ln σ kept. A product
    strength (value = linear · e^(−u_partner), `Packing`) keeps its linear coordinate,
    the product the data see, and its value's map takes the partner's place (the partner's
    own bounds are left to the support's rejection).

    Why: where the data leave a parameter to its prior, its posterior is nearly that prior,
    a box: the boom with running-in (3 rows for 4 parameters) determines the running-in
    product a·S_r, while the amplitude a is uniform on [0, 100] (posterior mean 50.6, sd 29.0
    against the box's 50, 28.9) and the distance follows as S_r ∝ 1/a. A t moment-matched to
    that in the whitened x underweights the box's edges (there the weights concentrate: the
    distance's ESS was a third of the draws); uniform on the box is the logistic
    distribution in y, which a t₇ fits closely, and no draw falls outside the box.

    x = (v, ln σ) are the sampler's whitened coordinates (u = û + f L v, f = σ/σ̂ where the
    noise is estimated, else 1; `_predict_nuts.Whitening`). `y(x)` gives (y (n, d),
    log |det ∂y/∂x| (n,)), NaN outside the bounds; `x(y)` its inverse (NaN where none)."""

    def __init__(self, packing, u_hat, L, log_noise_hat, scaled: bool, given: bool):
        self.packing = packing
        self.u_hat = np.asarray(u_hat, np.float64)
        self.L = np.asarray(L, np.float64)
        self.log_noise_hat = float(log_noise_hat)
        self.scaled, self.given = bool(scaled), bool(given)
        self.p = len(self.u_hat)
        self.start = np.asarray(packing.start, np.float64)
        cols = packing.columns
        self.scale = np.array([c.scale for c in cols], np.float64)
        self.pairs = list(product_pairs(packing.keys))
        strengths = {i for i, _ in self.pairs}
        partners = [j for _, j in self.pairs]
        if any(j in strengths for j in partners) or len(set(partners)) < len(partners):
            raise ValueError("a product strength's partner is itself paired")
        lo = np.array([c.lower for c in cols], np.float64)
        hi = np.array([c.upper for c in cols], np.float64)
        self.log = np.array([c.log for c in cols], bool)
        with np.errstate(divide="ignore", invalid="ignore"):
            self.lo = np.where(self.log, np.where(lo > 0, np.log(np.where(lo > 0, lo, 1.0)),
                                                  -np.inf), lo)
            self.hi = np.where(self.log, np.where(np.isfinite(hi) & (hi > 0), np.log(
                np.where(np.isfinite(hi) & (hi > 0), hi, 1.0)), np.inf), hi)
        bounded = [c.bounded for c in cols]
        # slot k of y: ("u", k) keeps u_k; ("a", i) maps column i's bounded a
        self.slots = [("a", k) if bounded[k] else ("u", k) for k in range(self.p)]
        for i, j in self.pairs:
            self.slots[i] = ("u", i)
            self.slots[j] = ("a", i) if bounded[i] else ("a", j) if bounded[j] else ("u", j)
        self.logdet_L = float(np.sum(np.log(np.abs(np.diag(self.L)))))

    @property
    def any_bounded(self) -> bool:
        return any(kind == "a" for kind, _ in self.slots)

    def laplace_start(self, mean, chol):
        """(centre (d,), Cholesky factor (d, d)) in y of the Laplace proposal t(mean, chol
        cholᵀ) in x, its covariance carried by the Jacobian at the centre and combined with
        each two-sided bounded slot's box prior moment-matched in y (the logistic's
        variance π²/3, centre 0) as a Gaussian's precisions add: the Laplace fit has no row
        for a uniform prior, so where the data leave a direction to the box (the boom's
        running-in amplitude: a standard error of 494 on [0, 100]) its Laplace spread is the
        linearisation's, not the posterior's; where the data determine it the box adds
        little. None where the centre has no y (a fit held at a bound)."""
        mean, chol = np.asarray(mean, np.float64), np.asarray(chol, np.float64)
        y0 = self.y(mean[None, :])[0][0]
        if not np.all(np.isfinite(y0)):
            return None
        h = 1e-5
        B = np.stack([(self.y((mean + h * c)[None, :])[0][0]
                       - self.y((mean - h * c)[None, :])[0][0]) / (2 * h) for c in chol.T],
                     axis=1)  # ∂y/∂x chol: cov_y = B Bᵀ
        prec_box = np.zeros(len(y0))
        for k, (kind, i) in enumerate(self.slots):
            if kind == "a" and math.isfinite(self.lo[i]) and math.isfinite(self.hi[i]):
                prec_box[k] = 3.0 / math.pi ** 2
        try:
            prec = np.linalg.inv(B @ B.T)
            cov = np.linalg.inv(0.5 * (prec + prec.T) + np.diag(prec_box))
            cov = 0.5 * (cov + cov.T)
            centre = cov @ (prec @ y0)
            L = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            return None
        if not (np.all(np.isfinite(centre)) and np.all(np.isfinite(L))):
            return None
        return centre, L

    def _f(self, x):
        return np.exp(x[:, self.p] - self.log_noise_hat) if self.scaled and not self.given \
            else np.ones(len(x))

    def _g(self, i, a):
        """(y, ∂y/∂a) of column i's bounded quantity a (n,)."""
        lo, hi = self.lo[i], self.hi[i]
        if math.isfinite(lo) and math.isfinite(hi):
            t = (a - lo) / (hi - lo)
            return (np.where((t > 0) & (t < 1), np.log(t) - np.log1p(-t), np.nan),
                    1.0 / (t * (1 - t) * (hi - lo)))
        if math.isfinite(lo):
            return np.where(a > lo, np.log(a - lo), np.nan), 1.0 / (a - lo)
        return np.where(a < hi, np.log(hi - a), np.nan), -1.0 / (hi - a)

    def _g_inv(self, i, y):
        lo, hi = self.lo[i], self.hi[i]
        if math.isfinite(lo) and math.isfinite(hi):
            return lo + (hi - lo) * special.expit(y)
        return lo + np.exp(y) if math.isfinite(lo) else hi - np.exp(y)

    def y(self, x):
        x = np.atleast_2d(np.asarray(x, np.float64))
        f = self._f(x)
        u = self.u_hat[None, :] + f[:, None] * (x[:, :self.p] @ self.L.T)
        y = np.array(x, np.float64)
        y[:, :self.p] = u
        logdet = np.full(len(x), self.logdet_L) + self.p * np.log(f)
        s, sc = self.start, self.scale
        partner = dict(self.pairs)
        with np.errstate(all="ignore"):
            for k, (kind, i) in enumerate(self.slots):
                if kind == "u":
                    continue
                # a = ln value (log column) or the value; ∂a/∂u_k, u_k the slot's own
                if self.log[i]:
                    a = math.log(s[i]) + u[:, i]
                    da = np.ones(len(x))
                else:
                    a = s[i] + sc[i] * u[:, i]
                    da = np.full(len(x), sc[i])
                if i in partner:  # value · e^(−u_partner): the slot is the partner's
                    j = partner[i]
                    if self.log[i]:
                        a = a - u[:, j]
                        da = -np.ones(len(x))
                    else:
                        a = a * np.exp(-u[:, j])
                        da = -a
                y[:, k], dy = self._g(i, a)
                # ∂y/∂u is triangular (a slot reads its own u and, for a strength's value,
                # the kept linear coordinate, whose row reads nothing else): its
                # determinant is the diagonal's product
                logdet += np.log(np.abs(dy * da))
        bad = ~np.all(np.isfinite(y), axis=1) | ~np.isfinite(logdet)
        y[bad] = np.nan
        logdet[bad] = np.nan
        return y, logdet

    def x(self, y):
        y = np.atleast_2d(np.asarray(y, np.float64))
        x = np.array(y, np.float64)
        u = x[:, :self.p]  # a view: the "u" slots are u already; the others filled below
        s, sc = self.start, self.scale
        partner = dict(self.pairs)
        with np.errstate(all="ignore"):
            for k, (kind, i) in enumerate(self.slots):
                if kind == "u":
                    continue
                a = self._g_inv(i, y[:, k])
                if i in partner:  # solve a(u_i, u_k) for the partner's u_k
                    if self.log[i]:
                        u[:, k] = math.log(s[i]) + u[:, i] - a
                    else:
                        u[:, k] = np.log((s[i] + sc[i] * u[:, i]) / a)
                else:
                    u[:, k] = a - math.log(s[i]) if self.log[i] else (a - s[i]) / sc[i]
        f = self._f(x)
        x[:, :self.p] = np.linalg.solve(self.L, (u - self.u_hat[None, :]).T).T / f[:, None]
        x[~np.all(np.isfinite(x), axis=1)] = np.nan
        return x


MAX_OVERSAMPLE = 1000  # proposal draws per kept draw at most, where a support is given


def truncated_sample(rng, mean, chol, n: int, nu: float, support=None, to_x=None):
    """n draws of the t proposal restricted to `support` (x (m, d) ↦ bool (m,), cheap: no
    model run), by rejection; and how many were rejected. Self-normalised importance
    weights are unchanged by the restriction (q/Z instead of q: a constant factor), so the
    model runs only where the density can be finite. Past `MAX_OVERSAMPLE` x n proposals
    the rest are plain proposal draws (their weights are 0). `to_x`: the t is drawn in
    other coordinates (`SupportCoordinates.x`): returns (x, the t's draws, rejected)."""
    conv = (lambda t: t) if to_x is None else to_x
    if support is None:
        t = t_sample(rng, mean, chol, n, nu)
        return (conv(t), 0) if to_x is None else (conv(t), t, 0)
    kept, kept_t, tried, have = [], [], 0, 0
    while have < n and tried < MAX_OVERSAMPLE * n:
        t = t_sample(rng, mean, chol, n, nu)
        x = conv(t)
        tried += n
        ok = np.asarray(support(x), bool) & np.all(np.isfinite(x), axis=1)
        kept.append(x[ok])
        kept_t.append(t[ok])
        have += int(ok.sum())
    if have < n:
        t = t_sample(rng, mean, chol, n - have, nu)
        kept.append(conv(t))
        kept_t.append(t)
    x, t = np.concatenate(kept)[:n], np.concatenate(kept_t)[:n]
    return (x, tried - min(have, n)) if to_x is None else (x, t, tried - min(have, n))


PILOT_SHARE = 0.25  # a round that may move the proposal starts with this share of its draws
PILOT_MIN = 200  # draws per batch of a pilot at least (PSIS's k̂ needs a tail to fit)
GROW_MIN = 50  # draws per batch added at least, where the answer's round grows to its ESS
GROW_MARGIN = 1.1  # draws for the ESS still missing: the linear estimate times this


def importance_sample(log_density, mean, chol, draws: int, chains: int, rng, *,
                      rounds: int = 2, nu: float = NU, log=None, support=None, enough=None,
                      coords=None, start_in_y: bool = False):
    """PSIS importance sampling of a density from a multivariate-t proposal (module
    docstring). `log_density`: x (n, d) ↦ log densities (n,) up to a constant (-inf
    outside the support); `mean` (d,), `chol` (d, d): the proposal's centre and scale;
    `support`: x (n, d) ↦ bool (n,), where the density can be finite (the prior's
    support), to draw from the proposal restricted to it (`truncated_sample`).

    Every round starts with a pilot of `PILOT_SHARE` of its draws (at least `PILOT_MIN`
    per batch). Where the pilot's weights are reliable (k̂ ≤ `K_GOOD`) but carried by few
    draws (a proposal far wider than the posterior), the proposal moves after the pilot
    alone (on the boom with running-in, 500 densities where a full first round spent
    2 000, ~0.13 s each, only to move it); unreliable weights (a pilot's, from a proposal
    3x too narrow, had a weights' ESS of 4-33 and two moves left k̂ at 0.6-1.0) complete
    the round from the same proposal (one i.i.d. batch: nothing is lost) and move it on
    the whole round's moments. The round that answers (the last, or one whose pilot is
    good) grows from its pilot until `enough(x, w, k)` says so or `draws` per batch are
    drawn: `enough` maps the draws (chains, m, d), their weights and k̂ per batch to (done,
    draws per batch it expects to need, a line for the log); None: all `draws`.
    `coords`: a `SupportCoordinates`; a moved proposal is then the t moment-matched in its
    coordinates y (q(x) = t(y(x)) |det ∂y/∂x|), x's moments the fallback (a weighted draw
    without y); `start_in_y`: `mean`, `chol` are already in y (`SupportCoordinates.
    laplace_start`). Returns (draws (chains, m, d), normalised smoothed weights (chains, m), each
    batch's normalised on its own, the rounds' history: draws per batch, k̂ and weights'
    ESS per batch, the proposal's coordinates)."""
    mean, chol = np.asarray(mean, np.float64), np.asarray(chol, np.float64)
    d = len(mean)
    history = []
    in_y = bool(start_in_y)  # the proposal's t is in `coords`' y, else in x

    def sample(m):
        """m more draws per batch from the current proposal: (x (chains, m, d), raw log
        weights (chains, m), proposals rejected outside the support)."""
        if in_y:
            x, y, rejected = truncated_sample(rng, mean, chol, chains * m, nu, support,
                                              to_x=coords.x)
            lq = t_logpdf(y, mean, chol, nu) + coords.y(x)[1]
        else:
            x, rejected = truncated_sample(rng, mean, chol, chains * m, nu, support)
            lq = t_logpdf(x, mean, chol, nu)
        lp = np.asarray(log_density(x), np.float64)
        lw = np.where(np.isfinite(lp) & np.isfinite(lq), lp - lq, -np.inf)
        return x.reshape(chains, m, d), lw.reshape(chains, m), rejected

    def weigh(lw):
        per = [psis(lw[c]) for c in range(chains)]
        w = np.stack([a for a, _ in per])
        k = [b for _, b in per]
        ess = [ess_of(w[c]) for c in range(chains)]
        # reliable (k̂) and carried by many draws: a proposal far wider than the posterior
        # has reliable weights on few draws (the boom's undetermined running-in pair:
        # weights' ESS 114-125 of 1000, k̂ -0.05)
        return w, k, ess, max(k) <= K_GOOD and min(ess) >= ESS_SHARE_GOOD * lw.shape[1]

    def more(x, lw, rejected, m):
        x2, lw2, rej2 = sample(m)
        return np.concatenate([x, x2], 1), np.concatenate([lw, lw2], 1), rejected + rej2

    def grow(x, lw, rejected, r):
        """The answer's round: more draws from the same proposal until `enough`."""
        while x.shape[1] < draws:
            if enough is None:
                return more(x, lw, rejected, draws - x.shape[1])
            w, k, _, _ = weigh(lw)
            done, need, line = enough(x, w, k)
            if done:
                break
            m = int(min(draws - x.shape[1], max(GROW_MIN, math.ceil(need) - x.shape[1])))
            if log:
                log(f"predict/importance: round {r + 1}: {x.shape[1]} draws per batch, "
                    f"{line}: {m} more")
            x, lw, rejected = more(x, lw, rejected, m)
        return x, lw, rejected

    for r in range(max(1, rounds)):
        t0 = time.perf_counter()
        last = r + 1 >= rounds
        m = min(draws, max(PILOT_MIN, math.ceil(PILOT_SHARE * draws)))
        x, lw, rejected = sample(m)
        w, k, ess, good = weigh(lw)
        pilot = None
        if m < draws and (good or last or max(k) > K_GOOD):
            pilot = {"draws": m, "k_hat": [float(v) for v in k], "ess": ess}
            if good or last:
                x, lw, rejected = grow(x, lw, rejected, r)
            else:  # unreliable weights: their moments would be too; the whole round's
                x, lw, rejected = more(x, lw, rejected, draws - m)
            w, k, ess, good = weigh(lw)
        history.append({"round": r + 1, "draws": int(x.shape[1]),
                        "proposal": "support coordinates" if in_y else "whitened",
                        "k_hat": [float(v) for v in k], "ess": ess,
                        "outside_support": int(np.sum(~np.isfinite(lw))),
                        "proposals_rejected": int(rejected)})
        if pilot is not None:
            history[-1]["pilot"] = pilot
        moves = not (good or last)
        if log:
            log(f"predict/importance: round {r + 1}: k̂ " + ", ".join(f"{v:.2f}" for v in k)
                + "; weights' ESS " + ", ".join(f"{e:.0f}" for e in ess)
                + f" of {x.shape[1]}" + (" (the proposal moves)" if moves else "")
                + f" ({time.perf_counter() - t0:.0f} s)")
        if not moves:
            break
        # move the proposal to the draws' weighted moments (t tails kept), in the support's
        # coordinates where they are given and every weighted draw has them
        wp = (w / chains).reshape(-1)
        xf = x.reshape(-1, d)
        to_y = False
        if coords is not None:
            yf = coords.y(xf)[0]
            to_y = bool(np.all(np.isfinite(yf[wp > 0])))
            if to_y:
                xf, wp = yf[wp > 0], wp[wp > 0]
        centre = wp @ xf
        c = (xf - centre).T @ ((xf - centre) * wp[:, None])
        c = 0.5 * (c + c.T) + 1e-12 * np.trace(c) * np.eye(d)
        try:
            chol = np.linalg.cholesky(c * (nu - 2) / nu if nu > 2 else c)
            mean = centre
            in_y = to_y
        except np.linalg.LinAlgError:
            # no pilot is an answer: its round grows from the same proposal
            if x.shape[1] < draws:
                x, lw, rej = grow(x, lw, 0, r)
                w, k, ess, _ = weigh(lw)
                history[-1].update(draws=int(x.shape[1]), k_hat=[float(v) for v in k],
                                   ess=ess, proposals_rejected=history[-1]
                                   ["proposals_rejected"] + rej,
                                   outside_support=int(np.sum(~np.isfinite(lw))))
            break
    return x, w, history


LEVEL_CHECK_DRAWS = 16  # posterior draws the sampling level's log density is checked at
LEVEL_FORECAST_DRAWS = 8  # ... and its forecast
LEVEL_LOGP_ERROR = 0.1  # half the spread of the levels' log-density difference, at most
LEVEL_FORECAST_SHARE = 0.1  # the levels' forecast depths apart by this share of σ, at most


def check_level(exact, problem, fprob, fprob_fine, u_fit, u_all, noise, wp, rng, workers,
                verbose) -> dict:
    """The sampling level against the fit's at `LEVEL_CHECK_DRAWS` posterior draws
    resampled by their weights `wp` (n,) (u_all (n, p), noise (n,) [µm]): the log
    likelihoods' difference between the levels (its half spread: a constant difference
    does not change the weights; within ±`LEVEL_LOGP_ERROR`, every weight is within ~10 %)
    and the forecast maxima at `LEVEL_FORECAST_DRAWS` of them (points before each draw's
    early stop; within `LEVEL_FORECAST_SHARE` of σ). `problem`, `fprob`, `fprob_fine`: the
    sampling level's training and forecast problems as the draws ran them; `u_fit` the
    answer, where each level's forecast is corrected to its finer one."""

    t0 = time.perf_counter()
    pick = np.unique(systematic_resample(wp, LEVEL_CHECK_DRAWS, rng))
    u, sig = u_all[pick], noise[pick]
    y = np.asarray(problem.data.depth_um)
    fit = exact["problem"]
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        r_fit = list(pool.map(lambda ui: forward_run(fit, ui).rows, u))
        r_c = list(pool.map(lambda ui: forward_run(problem, ui).rows, u))
    dl = np.array([-0.5 * (np.sum((a - y) ** 2) - np.sum((b - y) ** 2)) / s ** 2
                   for a, b, s in zip(r_fit, r_c, sig)])
    spread = float(0.5 * (np.max(dl) - np.min(dl))) if np.all(np.isfinite(dl)) else math.inf
    k = min(LEVEL_FORECAST_DRAWS, len(u))
    quiet = {"seed": 0, "workers": workers, "verbose": False}
    a = DrawForecasts(u[:k], sig[:k], u_fit, **quiet)(fprob, fprob_fine)
    b = DrawForecasts(u[:k], sig[:k], u_fit, **quiet)(*exact["forecast"])
    both = np.isfinite(a["new_um"]) & np.isfinite(b["new_um"])
    diff = float(np.max(np.abs(a["max_um"] - b["max_um"])[both])) if both.any() else 0.0
    ok = spread <= LEVEL_LOGP_ERROR and diff <= LEVEL_FORECAST_SHARE * float(np.min(sig))
    info = {"nodes": exact["level"][0], "steps_per_rev": exact["level"][1],
            "fit_nodes": exact["fit_level"][0], "fit_steps_per_rev": exact["fit_level"][1],
            "used": bool(ok), "draws_checked": int(len(u)),
            "log_density_spread": spread, "log_density_tolerance": LEVEL_LOGP_ERROR,
            "forecast_draws_checked": int(k), "forecast_difference_um": diff,
            "forecast_tolerance_um": LEVEL_FORECAST_SHARE * float(np.min(sig)),
            "seconds": time.perf_counter() - t0}
    _log(verbose, f"predict/importance: the sampling level against the fit's at {len(u)} "
                  f"posterior draws: log density ±{spread:.3g} (tolerance "
                  f"{LEVEL_LOGP_ERROR:g}), forecast {diff:.3g} µm apart at {k} (tolerance "
                  f"{info['forecast_tolerance_um']:.3g} µm) ({info['seconds']:.0f} s)")
    return info


def batch_r_hat(h, idx) -> float:
    """ArviZ's rank-normalised split R-hat of values h (n,) between the batches whose
    resampled draws are `idx` (a list of index arrays, one per batch); nan where undefined."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return float(_arviz().rhat(np.stack([h[i] for i in idx])))


def _share_in_support(in_support, mean, chol, rng, n: int = 4000, to_x=None) -> float:
    """Share of `n` draws of the proposal t(mean, chol) inside the support (`in_support`:
    x (n, d) ↦ bool (n,)); `to_x`: the t is in other coordinates (`SupportCoordinates.x`)."""
    x = t_sample(rng, mean, chol, n)
    x = x if to_x is None else to_x(x)
    ok = np.all(np.isfinite(x), axis=1)
    return float(np.mean(ok & np.asarray(in_support(jnp.asarray(np.where(ok[:, None], x,
                                                                             0.0))))))


def run_importance(problem, result, fprob, fprob_fine=None, *, noise_um=None, level=0.9,
                   verbose=False, draws: int = 1000, chains: int = 2, seed: int = 0,
                   max_minutes: float = 20.0, n_predictive: int = 200, out=None, cov=None,
                   rounds: int = 2, workers: int = 2, ess_target: int = ESS_TARGET,
                   exact=None):
    """The posterior by PSIS importance sampling (module docstring) and the forecast's
    predictive at `n_predictive` draws resampled by their weights. At most `draws` per
    batch: the answer's round stops once every parameter's ESS reaches `ess_target`, R-hat
    between the batches is at most `R_HAT_OK` and k̂ ≤ `K_GOOD` (0: all `draws`);
    `chains` independent batches (for R-hat), up to `rounds` rounds. Returns what
    `_predict_nuts.run_nuts` returns: (draws dict, extra JSON dict, forecast_draws).

    `exact`: where `problem` and `fprob` are a coarser sampling level (`_predict.
    sampling_level`), {"problem": the fit's training problem, "forecast": its forecast
    problems (fprob, fprob_fine), "level", "fit_level": (nodes, steps)}: after sampling,
    `check_level` compares the levels at posterior draws; where they differ by more than
    `LEVEL_LOGP_ERROR` (log density) or `LEVEL_FORECAST_SHARE` of σ (forecast depth), the
    whole answer is sampled again at the fit's level. The JSON's `level` says which."""
    if exact is not None:
        first = dict(noise_um=noise_um, level=level, verbose=verbose, draws=draws,
                     chains=chains, seed=seed, max_minutes=max_minutes,
                     n_predictive=n_predictive, out=out, cov=cov, rounds=rounds,
                     workers=workers, ess_target=ess_target)
    names = list(problem.names)
    p = len(names)
    given = noise_um is not None
    problem_in = problem
    d = p + (0 if given else 1)

    def z_of(x):
        z = {"v": x[:p]}
        if not given:
            z["log_noise"] = x[p]
        return z

    built = {}

    def compiled(logp_):
        """The program the draws run (x (d,) ↦ log density), compiled by the setup's check
        of the start: one compilation, where a jit of z and another of x compiled the same
        density twice (~6 s of CPU on the boom with running-in, as NUTS found for its
        own)."""
        f = jit(lambda x: logp_(z_of(x)))
        built["f"] = f

        def first_call(z):
            x0 = jnp.concatenate([jnp.ravel(z["v"])] + ([] if given else [
                jnp.ravel(z["log_noise"])]))
            t0_ = time.perf_counter()
            out_ = jax.block_until_ready(f(x0))
            built["t_compile"] = time.perf_counter() - t0_
            return out_

        return first_call

    problem, white, logp, z_fit = sampling_setup(problem, result, noise_um, cov,
                                                 compiled=compiled)
    # the draws' forecasts at the density's tolerance (a depth error far below the noise)
    tol_m = sampling_tolerance_m(problem, result, noise_um)
    fprob = with_tolerance(fprob, tol_m)
    problem_in = with_tolerance(problem_in, tol_m)
    logp_x, t_compile = built["f"], built["t_compile"]
    mean = np.zeros(d)
    scale = np.ones(d)
    if not given:
        mean[p] = float(z_fit["log_noise"])
        # ln σ̂ of a Gaussian sample with ν degrees of freedom has sd ≈ 1/√(2ν)
        scale[p] = 1.0 / math.sqrt(2.0 * max(float(result.error_dof), 1.0))
    chol = np.diag(scale)
    t0 = time.perf_counter()
    for _ in range(3):
        logp_x(jnp.asarray(mean)).block_until_ready()
    t_eval = (time.perf_counter() - t0) / 3
    u_fit = np.asarray(result.u, np.float64)
    _, _, _, fprob = run_forward(fprob, u_fit)  # compiles, settles the attempt count
    t0 = time.perf_counter()
    run_forward(fprob, u_fit)
    t_fc = time.perf_counter() - t0
    n = chains * draws
    n_pred = min(n_predictive, n)  # n: the most the rounds may draw
    par = max(1, min(workers, 2))
    # the proposal is restricted to the prior's support (a cheap check, no model run):
    # every draw then runs the model once; the share inside, for the log
    prior = prior_density(problem, noise_um, white)
    in_support = jit(jax.vmap(lambda xx: jnp.isfinite(prior(z_of(xx))[2])))
    try:  # where the prior bounds a parameter, the proposals live in the support's y
        coords = SupportCoordinates(problem.packing, white.u_hat, white.L, white.log_noise_hat,
                                    white.scaled, given)
        coords = coords if coords.any_bounded else None
    except ValueError:
        coords = None
    start = None if coords is None else coords.laplace_start(mean, chol)
    if start is not None:
        mean, chol = start
    inside = _share_in_support(in_support, mean, chol, np.random.default_rng([seed, 1]),
                               to_x=None if start is None else coords.x)
    est = (n * t_eval + n_pred * t_fc) / par
    _log(verbose, f"predict/importance: {p} parameters{'' if given else ' + noise'}; log "
                  f"density {t_eval * 1e3:.0f} ms (compiled in {t_compile:.0f} s), forecast "
                  f"{t_fc * 1e3:.0f} ms; {inside:.1%} of the proposal inside the prior's "
                  f"support (drawn from there); estimated run time {est / 60:.1f} min "
                  f"({n} draws per round, {n_pred} forecasts, {par} threads)")
    if est > 60 * max_minutes:
        raise InputError(f"<<max_minutes>>: importance sampling would take about "
                         f"{est / 60:.0f} min ({n} log densities of {t_eval:.2g} s) > the "
                         f"limit of {max_minutes:g} min; raise <<max_minutes>>, lower "
                         f"<<draws>>/<<chains>>, or use <<method>> laplace")

    def evaluate(xs):
        with ThreadPoolExecutor(max_workers=par) as pool:
            return np.array(list(pool.map(lambda x: float(logp_x(jnp.asarray(x))), xs)))

    u_of_x = jit(jax.vmap(lambda xx: white.u_of(z_of(xx))))

    def values(xf):
        """(u (n, p), the parameters' values and σ [µm] per draw: name ↦ (n,)) of x (n, d)."""
        u = np.asarray(u_of_x(jnp.asarray(xf)))
        v = np.array([problem.packing.values_np(ui) for ui in u]).reshape(len(u), p)
        post_ = {nm: v[:, i] for i, nm in enumerate(names)}
        if not given:
            post_["noise_um"] = np.exp(xf[:, p])
        return u, post_

    def resampled(w):
        """Each batch resampled to equal weights (for R-hat), the same for the same
        weights: the growth's stop and the answer's report read one R-hat."""
        m = w.shape[1]
        r_ = np.random.default_rng([seed, 2, m])
        return [systematic_resample(w[c], m, r_) + c * m for c in range(chains)]

    def enough(x, w, k):
        """Whether the answer's round has its draws (`importance_sample`)."""
        m = x.shape[1]
        post_ = values(x.reshape(-1, d))[1]
        wp_ = (w / chains).reshape(-1)
        ess = {nm: ess_of(wp_, h) for nm, h in post_.items()}
        low = min(ess, key=ess.get)
        idx = resampled(w)
        rh = max(batch_r_hat(h, idx) for h in post_.values()) if chains > 1 else 1.0
        done = max(k) <= K_GOOD and ess[low] >= ess_target and not rh > R_HAT_OK
        need = m * GROW_MARGIN * ess_target / max(ess[low], 1.0) \
            if ess[low] < ess_target else 1.25 * m
        return done, need, (f"k̂ {max(k):.2f}, ESS {ess[low]:.0f} ({low}) for {ess_target}, "
                            f"R-hat {rh:.4f}")

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    x, w, history = importance_sample(evaluate, mean, chol, draws, chains, rng, rounds=rounds,
                                      log=(lambda m: _log(True, m)) if verbose else None,
                                      support=lambda xs: np.asarray(in_support(jnp.asarray(xs))),
                                      enough=enough if ess_target > 0 else None,
                                      coords=coords, start_in_y=start is not None)
    t_run = time.perf_counter() - t0
    m_drawn = x.shape[1]
    xf = x.reshape(-1, d)
    wp = (w / chains).reshape(-1)  # pooled normalised weights
    u_all, post = values(xf)
    noise = np.full(len(xf), float(noise_um)) if given else post["noise_um"]
    # R-hat between the batches, each resampled to equal weights
    az = _arviz()
    res_idx = resampled(w)
    lo_q, hi_q = (1 - level) / 2, (1 + level) / 2
    diag = {}
    for kname, h in post.items():
        rh = batch_r_hat(h, res_idx) if chains > 1 else math.nan
        m = float(wp @ h)
        diag[kname] = {"r_hat": rh if math.isfinite(rh) else None,
                       "ess": ess_of(wp, h),
                       "mean": m, "sd": float(math.sqrt(max(wp @ (h - m) ** 2, 0.0))),
                       "lower": weighted_quantile(h, wp, lo_q),
                       "upper": weighted_quantile(h, wp, hi_q)}
    k_max = max(history[-1]["k_hat"])
    flags = []
    if not k_max <= K_USABLE:
        flags.append(f"importance: Pareto k̂ {k_max:.2f} > {K_USABLE}: the Laplace proposal "
                     f"misses the posterior's tail; its estimates are unreliable (use "
                     f"--method nuts)")
    elif k_max > K_GOOD:
        flags.append(f"importance: Pareto k̂ {k_max:.2f} in ({K_GOOD}, {K_USABLE}]: usable, "
                     f"its Monte Carlo error converges slowly")
    level_info = None
    if exact is not None:
        level_info = check_level(exact, problem_in, fprob, fprob_fine, u_fit, u_all, noise, wp,
                                 np.random.default_rng([seed, 3]), par, verbose)
        if not level_info["used"]:
            _log(verbose, f"predict/importance: the sampling level is off by "
                          f"{level_info['log_density_spread']:.3g} in log density or "
                          f"{level_info['forecast_difference_um']:.3g} µm in the forecast at "
                          f"posterior draws: sampling again at the fit's level")
            d_, e_, f_ = run_importance(exact["problem"], result, *exact["forecast"],
                                        **first)
            e_["importance"]["level"] = level_info
            e_["importance"]["seconds_at_the_sampling_level"] = t_run
            e_["importance"]["flags"].append(
                f"importance: sampled first at {level_info['nodes']} x "
                f"{level_info['steps_per_rev']} ({t_run:.0f} s), whose check at posterior "
                f"draws failed (log density ±{level_info['log_density_spread']:.3g}, "
                f"tolerance {LEVEL_LOGP_ERROR:g}; forecast "
                f"{level_info['forecast_difference_um']:.3g} µm apart, tolerance "
                f"{level_info['forecast_tolerance_um']:.3g} µm): the answer is the fit "
                f"level's, sampled again")
            return d_, e_, f_
    # posterior predictive at draws resampled by their weights (a draw picked twice is run
    # once)
    pick = systematic_resample(wp, n_pred, rng)
    uniq, inv = np.unique(pick, return_inverse=True)
    _log(verbose, f"predict/importance: sampled in {t_run:.0f} s; forecasting {len(uniq)} "
                  f"distinct draws of {n_pred} resampled")
    forecaster = DrawForecasts(u_all[uniq], noise[uniq], u_fit, seed=seed, workers=par,
                               verbose=verbose, label="predict/importance")

    def forecast_draws(fp, ff=None):
        out_ = forecaster(with_tolerance(fp, tol_m), ff)
        full = {key: val[inv] for key, val in out_.items() if key != "new_um"}
        # each resampled draw its own new measurement noise
        past = ~np.isfinite(out_["new_um"])[inv]
        full["new_um"] = new_measurements(full["max_um"], past, full["noise"],
                                          np.random.default_rng(seed))
        return full

    t0 = time.perf_counter()
    draws_out = forecast_draws(fprob, fprob_fine)
    t_pred = time.perf_counter() - t0
    path = None
    if out is not None:  # resampled, equally weighted draws; raw draws' weights beside
        idata = az.from_dict(
            posterior={kk.replace("/", ":"): np.stack([v[i] for i in res_idx])
                       for kk, v in post.items()},
            sample_stats={"psis_weight": w})
        path = out.write_with("posterior.nc",
                              lambda tmp: idata.to_netcdf(str(tmp), engine="h5netcdf"))
    extra_json = {"integration": forecaster.integration}

    def worst(key, pick):
        vals_ = [v[key] for v in diag.values()]
        return None if not vals_ or any(x_ is None for x_ in vals_) else pick(vals_)

    extra_json["importance"] = {
        "sampler": f"importance sampling, Laplace proposal (multivariate t, {NU:g} dof, in "
                   f"the support's coordinates where the prior bounds a parameter, else the "
                   f"whitened ones), Pareto-smoothed (PSIS)",
        "proposal": history[-1]["proposal"],
        "chains": chains, "draws": m_drawn, "max_draws": draws, "ess_target": ess_target,
        "rounds": len(history), "seed": seed,
        "k_hat": k_max, "k_hat_per_batch": history[-1]["k_hat"],
        "weights_ess": float(1.0 / np.sum(wp ** 2)),
        "min_ess": worst("ess", min), "max_r_hat": worst("r_hat", max),
        "r_hat": "between the independent batches, each resampled to equal weights",
        "history": history, "seconds": t_run, "estimated_seconds": est,
        "log_density_seconds": t_eval, "compile_seconds": t_compile,
        "predictive_draws": int(n_pred), "predictive_seconds": t_pred,
        "posterior": diag, "netcdf": None if path is None else str(path),
        "flags": flags}
    if level_info is not None:
        extra_json["importance"]["level"] = level_info
    return draws_out, extra_json, forecast_draws
