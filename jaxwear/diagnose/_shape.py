"""The shape of the missing wear: a smooth correction exp(g(z)) of the local wear rate along
each state variable z, learned from the misfit through the wear loop (DESIGN §7, `--shape`).

For a fit (the base model, or the model with the effect diagnose found), every variable of
`effects.shape.VARIABLES` gets g_v(z) = Σ_k c_vk B_k(z) on `SIZE` cubic B-splines. All
coefficients zero is that fit's model exactly, so one forward-mode Jacobian of the model with
every variable's coefficients switched on (one compiled function, one evaluation) linearises
them all. Per variable, on the host:

1. **The fit.** The fit's own free parameters (K_d, clearances, the effect's strengths) are
   refitted with it (Frisch-Waugh: the coefficient columns are projected off theirs), so g
   holds only what no parameter of the model can take up; its constant is K_d's, so g has
   coefficients summing to zero (a level shift is a change of K_d). The roughness penalty
   λ Σ (second difference of c)² (`ShapeVariable.roughness`) is chosen by generalised
   cross-validation over a grid of λ. dof = trace of the smoother (effective parameters).
2. **The decision.** T = (RSS_base − RSS_g)/σ² at the chosen λ; its distribution when the
   variable explains nothing is simulated (`DRAWS` draws: residuals N(0, σ²) projected as
   the base fit projects them, σ̂ with its ν degrees of freedom, and λ chosen by GCV in each
   draw, so that the choice of λ is paid for), p = (1 + #{T* ≥ T}) / (1 + DRAWS). The six
   variables are Bonferroni-combined at α = `ALPHA`, the family-wise level of the candidate
   scores: significant when p < α / 6.
3. **The shape.** ĝ with its Bayesian (Wahba) band, covariance σ²(A'A + λS)⁻¹; `peak_at`, where
   ĝ is largest, and its 90 % band from 4000 posterior draws of the argmax.
4. **Through the loop.** The best variable's correction is refitted by the least-squares core
   with the penalty as prior rows (`lsq.solve`, the Jacobian of step 1 held: a chord method,
   each residual a forward run of the wear loop); the RMSE after it is the real model's.

Cost: one Jacobian evaluation with 6 × `SIZE` more columns, plus a few forward runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import lsq
from .._load import load_history
from .._wear import cycle_increment
from ..effects.shape import VARIABLES, ShapeBasis, ShapeVariable, state_variables
from ._fit import Fit, _log
from ._model import Model
from ._stats import ALPHA

SIZE = 12  # B-splines per variable
DRAWS = 20000  # null simulations per variable (p resolves 5e-5 < ALPHA / 6)
LEVEL = 0.9  # band of g and of its peak
LAMBDAS = np.logspace(-4, 6, 41)  # λ grid, relative to tr(A'A)/tr(S)
RANGE_QUANTILES = (0.005, 0.995)  # of the wear-weighted state: the range met in the data
KNOT_QUANTILES = 32  # pieces of the piecewise-linear quantile coordinate
NONLINEAR_EVALUATIONS = 8


@dataclass(frozen=True)
class VariableShape:
    """The shape along one variable (JSON: `to_json`)."""

    name: str
    unit: str
    explained_fraction: float
    dof: float
    p_value: float
    significant: bool
    peak_at: float
    lower: float
    upper: float
    lam: float
    statistic: float  # T = ΔRSS/σ²
    z: np.ndarray = field(repr=False)  # grid over the range met in the data
    g: np.ndarray = field(repr=False)  # ĝ on the grid
    g_lower: np.ndarray = field(repr=False)
    g_upper: np.ndarray = field(repr=False)
    coef: np.ndarray = field(repr=False)  # c (SIZE,)
    extra_wear_um: np.ndarray = field(repr=False)  # linearised Δdepth over the bore (N,)
    range: tuple = (0.0, 0.0)
    refit_rmse_um: float | None = None  # RMSE with this correction, through the loop

    def to_json(self) -> dict:
        return {"name": self.name, "unit": self.unit,
                "explained_fraction": _num(self.explained_fraction), "dof": _num(self.dof),
                "p_value": _num(self.p_value), "significant": bool(self.significant),
                "peak_at": _num(self.peak_at), "lower": _num(self.lower),
                "upper": _num(self.upper), "range": [_num(self.range[0]), _num(self.range[1])],
                "penalty": _num(self.lam), "statistic": _num(self.statistic),
                "trend": _num(trend(self)), "refit_rmse_um": _num(self.refit_rmse_um)}


@dataclass(frozen=True)
class ShapeResult:
    """The shape analysis on top of one fit (`after`: "base" or the effect's name)."""

    after: str
    best: str | None
    variables: tuple
    alpha: float
    noise_um: float
    rmse_before_um: float
    rmse_after_um: float | None  # with the best variable's correction, through the loop
    evaluations: int
    status: str  # the nonlinear refit's (lsq) status, or "none"
    sentence: str
    phase_load: dict = field(default_factory=dict, repr=False)  # for the phase plot
    bore_deg: np.ndarray = field(default=None, repr=False)
    experiment: str = ""  # whose bore the extra wear is drawn on
    alternatives: tuple = ()  # variables the data cannot tell from `best` (within ln 20)

    def to_json(self) -> dict:
        return {"after": self.after, "best": self.best,
                "alternatives": list(self.alternatives),
                "variables": [v.to_json() for v in self.variables],
                "alpha": self.alpha, "noise_um": _num(self.noise_um),
                "rmse_before_um": _num(self.rmse_before_um),
                "rmse_after_um": _num(self.rmse_after_um),
                "model_evaluations": self.evaluations, "refit_status": self.status,
                "summary": self.sentence}

    def variable(self, name: str) -> VariableShape:
        return next(v for v in self.variables if v.name == name)


def _num(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


# -- the range of each variable met in the data ---------------------------------------------

@eqx.filter_jit
def _cycle_states(p, cfg, hist, regime, h, sliding):
    """Every state variable of one cycle and its wear rate (steps, nodes) [m per step]."""
    _, _, sol = cycle_increment(p, cfg, hist, regime, h, sliding)
    slide, dt = hist.slide[regime], hist.dt[regime]
    z = state_variables(sol.pressure, slide, dt, sliding, hist.angle[regime])
    rate = p.wear_coefficient * sol.pressure * slide[:, None]
    return {k: jnp.broadcast_to(v, sol.pressure.shape) for k, v in z.items()}, rate


def _weighted_quantiles(x, w, qs):
    order = np.argsort(x)
    x, w = x[order], w[order]
    c = np.cumsum(w)
    if c[-1] <= 0:
        return np.interp(qs, [0.0, 1.0], [x[0], x[-1]])
    return np.interp(np.asarray(qs) * c[-1], c, x)


def state_knots(model: Model, fit: Fit):
    """{name: knots} of every non-periodic variable: its wear-weighted quantiles at t = 0,
    1/Q, ..., 1 (`KNOT_QUANTILES` + 1 values, the ends at `RANGE_QUANTILES`), from the
    states of one cycle at the start and at the end of each experiment at the fit (the
    sliding distance: uniform over each experiment's total, weighted by its wear). Also the
    joint load over the cycle of the experiment that wears most (for the phase plot)."""
    ext = model.ext
    cfg = ext.cfg
    P = ext.batched_params(jnp.asarray(fit.ev.u))
    samples = {k: ([], []) for k in VARIABLES}
    snaps = fit.ev.snaps  # (E, S, N) µm
    deepest = int(np.argmax(snaps[:, -1].max(axis=1)))
    load = {}
    distance = ([], [])  # S over each experiment, weighted by its wear
    for e in range(snaps.shape[0]):
        p = jax.tree_util.tree_map(lambda x: x[e], P)
        hist = load_history(p, cfg)
        total = float(fit.ev.sliding_m[e])
        for r in range(hist.load.shape[0]):
            for h, s in ((np.zeros(snaps.shape[2]), 0.0), (snaps[e, -1] * 1e-6, total)):
                z, rate = _cycle_states(p, cfg, hist, r, jnp.asarray(h), jnp.asarray(s))
                w = np.asarray(rate).ravel()
                for k in samples:
                    samples[k][0].append(np.asarray(z[k]).ravel())
                    samples[k][1].append(w)
        distance[0].append(np.linspace(0.0, total, 64))
        distance[1].append(np.full(64, max(float(snaps[e, -1].max()), 1e-12)))
        if e == deepest:
            z0, _ = _cycle_states(p, cfg, hist, 0, jnp.zeros(snaps.shape[2]),
                                  jnp.asarray(0.0))
            n = hist.load.shape[1]
            load = {"phase_deg": np.arange(n) * 360.0 / n,
                    "load_N": np.asarray(hist.load[0]),
                    "turn_rate_deg_per_s": np.asarray(z0["load_turn_rate_deg_per_s"][:, 0])}
    samples["sliding_distance_m"] = distance
    knots = {}
    q0, q1 = RANGE_QUANTILES
    for k, (xs, ws) in samples.items():
        if VARIABLES[k][1]:
            continue
        x, w = np.concatenate(xs), np.concatenate(ws)
        zq = _weighted_quantiles(x, w, np.linspace(q0, q1, KNOT_QUANTILES + 1))
        # strictly increasing (a state met at one value only, e.g. one speed)
        span = max(float(zq[-1] - zq[0]), abs(float(zq[0])) * 1e-3, 1e-12)
        zq = np.maximum.accumulate(zq) + np.arange(len(zq)) * span * 1e-9
        knots[k] = tuple(float(v) for v in zq)
    return knots, load, model.exp_names[deepest], deepest


def make_basis(knots: dict, size: int = SIZE) -> ShapeBasis:
    return ShapeBasis(tuple(ShapeVariable(name, size) if periodic else
                            ShapeVariable(name, size, knots[name])
                            for name, (_, periodic) in VARIABLES.items()))


def trend(v) -> float:
    """Slope of ĝ against the wear-weighted quantile t ∈ [0, 1] of z (least squares over
    the plotting grid, which is uniform in t): > 0 where the extra wear rises with z."""
    t = np.linspace(0.0, 1.0, len(v.g))
    return float(np.polyfit(t, v.g, 1)[0])


# -- the linear algebra of one variable ------------------------------------------------------

def _sum_zero(n: int) -> np.ndarray:
    """Orthonormal basis Z (n, n-1) of the coefficients that sum to zero."""
    q, _ = np.linalg.qr(np.eye(n) - 1.0 / n)
    return q[:, :n - 1]


class _Smoother:
    """min_a ||y - A a||² + λ a'Sa for the (whitened, base-projected) columns A, in the
    coordinates of A's left singular vectors: everything data-dependent is y = U'ρ (m,)
    and ||ρ||² (see the module docstring)."""

    def __init__(self, A: np.ndarray, S: np.ndarray, lambdas: np.ndarray):
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        keep = s > 1e-10 * max(s[0], 1e-300)
        self.U, self.s, self.Vt = U[:, keep], s[keep], Vt[keep]
        AtA = (self.Vt.T * self.s ** 2) @ self.Vt
        scale = np.trace(AtA) / max(np.trace(S), 1e-300)
        self.lambdas = lambdas * scale
        ridge = 1e-12 * np.trace(AtA) * np.eye(len(S))
        self.inv = [np.linalg.inv(AtA + lam * S + ridge) for lam in self.lambdas]
        B = self.Vt.T * self.s  # A'U = V Σ
        # ŷ = M_λ y with M_λ = Σ V' (A'A + λS)⁻¹ V Σ
        self.M = np.stack([B.T @ inv @ B for inv in self.inv])  # (L, m, m)
        self.trace = np.einsum("lii->l", self.M)
        self.AtU = B

    def rss_drop(self, Y):
        """RSS_0 - RSS_λ (..., L) for y's (..., m): 2 y·ŷ - ||ŷ||²."""
        Yh = np.einsum("lij,...j->...li", self.M, Y)
        return 2 * np.einsum("...i,...li->...l", Y, Yh) - np.einsum("...li,...li->...l",
                                                                    Yh, Yh)

    def choose(self, drop, rss0, n_res):
        """GCV: argmin over λ of n RSS_λ / (n - tr)² (rss0, n_res: the base fit's)."""
        rss = rss0[..., None] - drop
        gcv = rss / np.maximum(n_res - self.trace, 1e-9) ** 2
        return np.argmin(gcv, axis=-1)


def _variable_fit(A, S, rho, n_res, nu, rng, draws):
    """(λ index, a, cov, T, p, dof) for one variable: A (rows, m) whitened, base-projected
    columns; rho (rows,) whitened, base-projected misfit to explain (measured - model)."""
    sm = _Smoother(A, S, LAMBDAS)
    y = sm.U.T @ rho
    rss0 = float(rho @ rho)
    drop = sm.rss_drop(y)
    i = int(sm.choose(drop, np.asarray(rss0), n_res))
    T = float(drop[i])
    # the null: y* ~ N(0, I), the rest of the base residual χ²_{n_res - m}, σ̂²/σ² ~ χ²_ν/ν
    m = len(y)
    Y = rng.standard_normal((draws, m))
    rest = rng.chisquare(max(n_res - m, 1), draws)
    s2 = rng.chisquare(nu, draws) / nu if math.isfinite(nu) and nu > 0 else np.ones(draws)
    Y = Y / np.sqrt(s2)[:, None]
    rss0_star = np.einsum("ij,ij->i", Y, Y) + rest / s2
    d_star = sm.rss_drop(Y)
    j = sm.choose(d_star, rss0_star, n_res)
    T_star = d_star[np.arange(draws), j]
    p = (1.0 + float(np.sum(T_star >= T))) / (1.0 + draws)
    a = sm.inv[i] @ (sm.AtU @ y)
    return i, a, sm.inv[i], T, p, float(sm.trace[i]), sm.lambdas[i]


def _peak(z, G, periodic):
    """argmax of each row of G (draws, grid) on z, as values."""
    return z[np.argmax(G, axis=-1)]


def _band_of_peak(z, g_hat, G, periodic, level):
    peak = float(z[int(np.argmax(g_hat))])
    draws = _peak(z, G, periodic)
    q = ((1 - level) / 2, (1 + level) / 2)
    if periodic:
        d = np.mod(draws - peak + 180.0, 360.0) - 180.0
        lo, hi = np.quantile(d, q)
        return peak, float(np.mod(peak + lo, 360.0)), float(np.mod(peak + hi, 360.0))
    lo, hi = np.quantile(draws, q)
    return peak, float(lo), float(hi)


# -- the analysis ---------------------------------------------------------------------------

def shape_analysis(model: Model, fit: Fit, noise_um: float, nu: float, *, after: str = "base",
                   seed: int = 0, draws: int = DRAWS, size: int = SIZE,
                   verbose: bool = False) -> ShapeResult:
    """The shape of the misfit left by `fit` (of `model`) along every state variable (module
    docstring). `noise_um` σ [µm] with `nu` degrees of freedom (diagnose's noise level)."""
    evals0 = Model.evaluations
    _log(verbose, f"  shape of the missing wear after {after}: "
                  f"{len(VARIABLES)} variables x {size} B-splines")
    knots, load, exp_name, deepest = state_knots(model, fit)
    basis = make_basis(knots, size)
    # the fit's own model (its candidates only: every column costs a tangent) with the
    # correction switched on
    smodel = Model(model.study, model.problem,
                   candidates=[g for g in fit.groups if g in model.candidates],
                   contact=model.contact, noise_weight=model.noise_weight, shape=basis)
    u = np.zeros(len(smodel.names))
    for i, name in enumerate(model.names):
        if name in smodel.index:
            u[smodel.index[name]] = fit.ev.u[i]
    _log(verbose, "    one Jacobian with every variable's coefficients (compiles the model "
                  "with the correction)")
    ev = smodel.evaluate(u)
    sigma = max(float(noise_um), 1e-12)
    free_base = [smodel.index[model.names[i]] for i in np.flatnonzero(fit.mask)]
    n = smodel.n
    # whitened system: data rows /σ, prior rows in SD units (as the refits see them)
    Jd, Jp = ev.J / sigma, ev.J_prior / max(smodel.noise_weight, 1e-12)
    rho_full = -np.concatenate([ev.r / sigma, ev.r_prior / max(smodel.noise_weight, 1e-12)])
    Xb = np.vstack([Jd[:, free_base], Jp[:, free_base]])
    Qb = np.linalg.qr(Xb)[0] if Xb.shape[1] else np.zeros((len(rho_full), 0))
    proj = lambda X: X - Qb @ (Qb.T @ X)  # noqa: E731
    rho = proj(rho_full[:, None])[:, 0]
    n_res = n - len(free_base)
    rss0 = float(rho_full @ rho_full)
    excess = rss0 - n_res  # the misfit beyond the noise, in σ² units
    rng = np.random.default_rng(seed)
    Z = _sum_zero(size)
    results = []
    for var in basis.variables:
        cols = [smodel.index[k] for k in var.keys()]
        Xa = np.vstack([Jd[:, cols], Jp[:, cols]]) @ Z
        A = proj(Xa)
        S = Z.T @ var.roughness() @ Z
        i, a, inv, T, p, dof, lam = _variable_fit(A, S, rho, n_res, nu, rng, draws)
        c = Z @ a
        # the plotting grid: uniform in angle, or in the wear-weighted quantile t
        zg = (np.linspace(0.0, 360.0, 181)[:-1] if var.periodic else
              var.at_coordinate(np.linspace(0.0, 1.0, 181)))
        Bg = np.asarray(var.basis(jnp.asarray(zg)))
        g = Bg @ c
        w, V = np.linalg.eigh(0.5 * (inv + inv.T))  # draws of a, then c = Z a
        L = V * np.sqrt(np.clip(w, 0.0, None))
        C = (a + rng.standard_normal((4000, len(a))) @ L.T) @ Z.T
        G = C @ Bg.T
        q = ((1 - LEVEL) / 2, (1 + LEVEL) / 2)
        g_lo, g_hi = np.quantile(G, q, axis=0)
        peak, lo, hi = _band_of_peak(zg, g, G, var.periodic, LEVEL)
        J_snap = None if ev.J_snaps is None else ev.J_snaps[deepest, -1][:, cols]
        extra = (J_snap @ c) if J_snap is not None else np.zeros(0)
        results.append(VariableShape(
            var.name, var.unit, _explained(T, dof, excess, rss0), dof,
            p, False, peak, lo, hi, float(lam), T, zg, g, g_lo, g_hi, c, extra,
            (float(zg[0]), float(zg[-1]))))
        _log(verbose, f"    {var.name}: explains {results[-1].explained_fraction:.0%} of the "
                      f"misfit, dof {dof:.1f}, p {p:.1e}, peak at {peak:.4g} {var.unit}")
    alpha_each = ALPHA / len(results)
    results = [_replace(v, significant=v.p_value < alpha_each) for v in results]
    sig = sorted([v for v in results if v.significant], key=lambda v: -v.explained_fraction)
    rmse_before = float(np.sqrt(np.mean(ev.r ** 2)))
    best, rmse_after, status, alternatives = None, None, "none", []
    if sig:
        # `best` is the significant variable that explains most (DESIGN §7). State
        # variables are correlated (on the rig, speed and load turn rate both follow the
        # crank speed), so shares can nearly tie: significant variables whose AIC (the
        # linearised fit's RSS + 2 effective dof) is within ln 20 of the best's, or lower,
        # are named as alternatives the data cannot tell apart.
        best = sig[0].name
        crit = {v.name: rss0 - v.statistic + 2.0 * v.dof for v in sig}
        alternatives = [k for k in sorted(crit, key=crit.get)
                        if k != best and crit[k] - crit[best] < 2.0 * math.log(20.0)]
        refits = {best: _refit_best(smodel, ev, u, free_base, basis, best, results, sigma,
                                    verbose)}
        rmse_after, status, u_best = refits[best]
        # where the best variable's correction puts its wear, through the loop (the
        # others' are linearised): the deepest experiment at its last measurement
        extra = smodel.snapshots(u_best)[deepest, -1] - ev.snaps[deepest, -1]
        var = basis.variables[[v.name for v in basis.variables].index(best)]
        cols = [smodel.index[k] for k in var.keys()]
        new = []
        for v in results:
            if v.name in refits:
                v = _replace(v, refit_rmse_um=refits[v.name][0])
            if v.name == best:
                c = u_best[cols]
                g = np.asarray(var.basis(jnp.asarray(v.z))) @ c
                # the band of the linearised fit, carried to the refitted ĝ
                v = _replace(v, coef=c, g=g, g_lower=v.g_lower + g - v.g,
                             g_upper=v.g_upper + g - v.g, extra_wear_um=extra,
                             peak_at=float(v.z[int(np.argmax(g))]))
            new.append(v)
        results = new
    sentence = describe(best, results, load, after, alternatives)
    return ShapeResult(after, best, tuple(results), ALPHA, sigma, rmse_before, rmse_after,
                       Model.evaluations - evals0, status, sentence, load,
                       np.arange(smodel.ext.cfg.nodes) * 360.0 / smodel.ext.cfg.nodes,
                       exp_name, tuple(alternatives))


def _explained(drop: float, dof: float, excess: float, rss0: float) -> float:
    """Share of the misfit a correction explains, net of what it would take from noise
    alone (a correction with `dof` effective parameters removes ~dof σ² of pure noise):
    (ΔRSS − dof)⁺ over the misfit beyond the noise level (RSS_base − (n − k)σ², σ² units)
    where there is some, else over the whole residual sum. So a fit at noise level, or a
    history of five points, does not read "100 % explained"."""
    net = max(drop - dof, 0.0)
    if excess > 0.0:
        return float(np.clip(net / max(excess, net, 1e-300), 0.0, 1.0))
    return float(np.clip(net / max(rss0, 1e-300), 0.0, 1.0))


def _replace(v, **kw):
    from dataclasses import replace

    return replace(v, **kw)


def _refit_best(smodel: Model, ev, u, free_base, basis: ShapeBasis, best: str, results,
                sigma, verbose):
    """The best variable's correction refitted with the base parameters by the one
    least-squares core: residuals through the wear loop (forward runs), the Jacobian of
    the linearisation held (chord), the roughness penalty and the zero-sum of the
    coefficients as prior rows (SD units)."""
    var = next(v for v in basis.variables if v.name == best)
    res = next(v for v in results if v.name == best)
    cols = [smodel.index[k] for k in var.keys()]
    lam = res.lam
    D = np.linalg.cholesky(var.roughness() + 1e-12 * np.eye(var.size)).T  # D'D = R
    free = np.zeros(len(u), bool)
    free[free_base] = True
    free[cols] = True
    J = ev.J.copy()
    prior_base = ev.J_prior / max(smodel.noise_weight, 1e-12)
    r_prior0 = ev.r_prior / max(smodel.noise_weight, 1e-12)

    def prior(v):
        c = v[cols]
        rows_pen = math.sqrt(lam) * (D @ c)
        rows_sum = np.array([np.sum(c) / (0.01 * var.size)])
        # the clearance prior rows move linearly with their columns
        rp = r_prior0 + prior_base @ (v - u)
        Jpen = np.zeros((var.size, len(v)))
        Jpen[:, cols] = math.sqrt(lam) * D
        Jsum = np.zeros((1, len(v)))
        Jsum[0, cols] = 1.0 / (0.01 * var.size)
        return (np.concatenate([rp, rows_pen, rows_sum]),
                np.vstack([prior_base, Jpen, Jsum]))

    # Broyden's rank-one update of the held Jacobian from each new residual (the secant
    # along the step just taken): exp(g) is far from linear once g ~ 1, and a held Jacobian
    # alone (a chord method) stalled there
    last = {"u": u.copy(), "r": ev.r.copy(), "J": J.copy()}

    def evaluate(v):
        pred = smodel.predict(v)
        r = pred - smodel.measured
        rp, Jpr = prior(v)
        ok = bool(np.all(np.isfinite(r)))
        if ok:
            du = (v - last["u"]) * free
            nrm = float(du @ du)
            if nrm > 0:
                last["J"] = last["J"] + np.outer(r - last["r"] - last["J"] @ du, du) / nrm
            last.update(u=v.copy(), r=r.copy())
        return lsq.Point(u=v, r=r, predicted=pred, J=last["J"].copy(), r_prior=rp,
                         J_prior=Jpr, usable=ok)

    rp0, Jp0 = prior(u)
    pt0 = lsq.Point(u=u, r=ev.r, predicted=ev.pred, J=J, r_prior=rp0, J_prior=Jp0,
                    usable=True)
    u1 = u.copy()
    u1[cols] = res.coef
    # the base parameters move with the correction (the joint linearised answer)
    Xb = np.vstack([J[:, free_base] / sigma, prior_base[:, free_base]])
    rho = -np.concatenate([ev.r / sigma, r_prior0])
    Xa = np.vstack([J[:, cols] / sigma, prior_base[:, cols]])
    if free_base:
        u1[free_base] += np.linalg.lstsq(Xb, rho - Xa @ res.coef, rcond=None)[0]
    pt1 = evaluate(u1)  # the linearised answer, through the loop
    start, point0 = (u1, pt1) if pt1.usable else (u, pt0)
    log = (lambda m: _log(True, m)) if verbose else None
    out = lsq.solve(evaluate, start, point0=point0, free=free, noise_um=sigma,
                    max_evaluations=NONLINEAR_EVALUATIONS - 1, se_tol=0.1,
                    label=f"    shape {best}", log=log)
    r = out.point.r
    return float(np.sqrt(np.mean(r ** 2))), out.status, out.u


# -- words --------------------------------------------------------------------------------

# cycle phase: the crank angle, the swing's phase, or the phase within a load file's period
LABELS = {"cycle_phase_deg": "cycle phases", "pressure_MPa": "contact pressures",
          "sliding_speed_m_per_s": "sliding speeds", "sliding_distance_m": "sliding distances",
          "load_turn_rate_deg_per_s": "load turn rates", "bore_angle_deg": "bore angles"}


def _levels(v: VariableShape) -> tuple[float, float]:
    """(low, high) of ĝ where the data determine it: over the grid points whose band is no
    wider than twice its median width (where little wears, g is free to wander)."""
    width = v.g_upper - v.g_lower
    ok = width <= 2.0 * np.median(width)
    g = v.g[ok] if ok.any() else v.g
    return float(g.min()), float(g.max())


def _region(v: VariableShape) -> tuple[float, float]:
    """Where ĝ is above half-way between its low and high levels (`_levels`), around the
    peak: for a step, from the step on."""
    g = v.g
    low, high = _levels(v)
    half = low + 0.5 * (high - low)
    k = int(np.argmax(g))
    n = len(g)
    lo = hi = k
    step = (lambda i: i % n) if v.name in ("cycle_phase_deg", "bore_angle_deg") else (
        lambda i: min(max(i, 0), n - 1))
    for _ in range(n):
        nxt = step(lo - 1)
        if g[nxt] < half or nxt == lo:
            break
        lo = nxt
    for _ in range(n):
        nxt = step(hi + 1)
        if g[nxt] < half or nxt == hi:
            break
        hi = nxt
    return float(v.z[lo]), float(v.z[hi])


def threshold(v: VariableShape, rising: bool = True) -> float:
    """Where ĝ steps up (`rising`; else down): the best two-level step fitted to ĝ over the
    plotting grid (uniform in the wear-weighted quantile), each point weighted by 1/(its
    band width)², so that where the data leave g free it counts little. Returns z at the
    first point past the step (for a rate that jumps at a threshold, the threshold)."""
    g = v.g if rising else -v.g
    w = 1.0 / np.maximum(v.g_upper - v.g_lower, 1e-12) ** 2
    best, k_best = math.inf, 1
    for k in range(1, len(g)):
        sse = 0.0
        for part, wp in ((g[:k], w[:k]), (g[k:], w[k:])):
            m = float(np.sum(wp * part) / np.sum(wp))
            sse += float(np.sum(wp * (part - m) ** 2))
        if sse < best:
            best, k_best = sse, k
    return float(v.z[k_best])


def p_text(p: float) -> str:
    """"p 3.1e-03", or "p ≤ 5.0e-05" where no simulated draw reached the statistic (the
    p-value (1 + 0)/(1 + draws) is then a bound)."""
    return f"p ≤ {p:.1e}" if p <= 1.5 / (1.0 + DRAWS) else f"p {p:.1e}"


def describe(best, results, load, after, alternatives=()) -> str:
    on_top = "" if after == "base" else f" on top of {after}"
    if best is None:
        return (f"No state variable explains the misfit{on_top} beyond noise "
                f"(family-wise α = {ALPHA:g} over {len(results)} variables).")
    v = next(r for r in results if r.name == best)
    lo, hi = _region(v)
    rising = trend(v) > 0
    unit = v.unit
    if v.name in ("cycle_phase_deg", "bore_angle_deg"):
        where = f"at {LABELS[v.name]} {lo:.0f}-{hi:.0f}°"
    elif rising and hi >= v.z[int(0.85 * (len(v.z) - 1))]:
        where = f"above {LABELS[v.name][:-1]} {threshold(v):.3g} {unit}, rising with it"
    elif not rising and lo <= v.z[int(0.15 * (len(v.z) - 1))]:
        where = (f"below {LABELS[v.name][:-1]} {threshold(v, rising=False):.3g} {unit}, "
                 f"falling with it")
    else:
        where = f"at {LABELS[v.name]} {lo:.3g}-{hi:.3g} {unit}"
    s = (f"The missing wear{on_top} follows {best} (explains {v.explained_fraction:.0%} of "
         f"the misfit, {p_text(v.p_value)}): it concentrates {where}")
    if v.name == "cycle_phase_deg" and load:
        fast = float(load["phase_deg"][int(np.argmax(load["turn_rate_deg_per_s"]))])
        d = abs((fast - v.peak_at + 180.0) % 360.0 - 180.0)
        if d <= 20.0:
            s += f", where the joint load turns fastest ({fast:.0f}°)"
    s += "."
    if alternatives:
        s += (f" The data cannot tell it from {', '.join(alternatives)} (AIC within ln 20: "
              f"the experiments vary them together).")
    return s
