"""Bands and the assembled answer: prediction intervals from the covariance (Laplace) or the
draws, and the `PredictResult` with its tables."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from jaxwear._analyses.predict.grid import _last_count, measured_max
from jaxwear._analyses.predict.life import LIFE_HORIZON, life_of
from jaxwear._analyses.predict.result import Curve, Prediction, PredictResult, _jf
from jaxwear._inference.result import FitResult
from jaxwear._study.study import Study


def draw_quantile(y, q: float):
    """Quantile `q` over the draws (axis 0) by NumPy's default linear interpolation, where
    +inf (a draw past the limit) is allowed: between two +inf order statistics it is +inf
    (np.quantile gives NaN from inf - inf), at an exact order statistic it is that one."""
    s = np.sort(np.asarray(y, float), axis=0)
    pos = q * (s.shape[0] - 1)
    k = int(math.floor(pos))
    g = pos - k
    lo, hi = s[k], s[min(k + 1, s.shape[0] - 1)]
    with np.errstate(invalid="ignore"):
        return np.where((g == 0) | (lo == hi), lo, lo + g * (hi - lo))


def predictive_quantile(max_um, past, noise_um, q: float, iters: int = 80):
    """Quantile `q` at each point of the posterior predictive of a new measurement: the
    mixture over the D draws of N(max_d, σ_d²), a draw `past` the limit (or not finite)
    counting as +inf (`draws.new_measurements`). `max_um` (D, S) [µm], `past` (D, S) bool,
    `noise_um` (D,) [µm] → (S,) [µm], +inf where more than 1 − q of the draws are past.

    Why not the quantile of one noisy measurement per draw (`new_um`): the noise is
    integrated exactly here, so only the draws' own Monte Carlo error is left. Simulated at
    the boom's 25 h band (draws' sd 10.6 µm, σ = 5 µm, 200 draws), the 5 % edge's sd over
    repetitions 1.72 µm one noise value per draw, 1.21 µm integrated: the same as twice
    the draws (each a forecast run). Found by bisection on the mixture's CDF (`iters`
    halvings of a bracket ±10 σ around the draws: below 1e-12 µm)."""
    from scipy import special

    m = np.asarray(max_um, np.float64)
    sig = np.asarray(noise_um, np.float64)[:, None] * np.ones_like(m)
    out_ = np.asarray(past, bool) | ~np.isfinite(m)
    mf = np.where(out_, np.nan, m)
    with np.errstate(invalid="ignore"):
        lo = np.nanmin(mf - 10.0 * sig, axis=0)
        hi = np.nanmax(mf + 10.0 * sig, axis=0)
    reach = np.mean(~out_, axis=0)  # the CDF's limit at +inf
    ok = reach >= q
    lo, hi = np.where(ok, lo, 0.0), np.where(ok, hi, 0.0)

    def cdf(x):
        z = (x[None, :] - m) / np.where(sig > 0, sig, 1.0)
        c = np.where(sig > 0, special.ndtr(z), (x[None, :] >= m).astype(float))
        return np.mean(np.where(out_, 0.0, c), axis=0)

    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        below = cdf(mid) < q
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return np.where(ok, 0.5 * (lo + hi), np.inf)


def t_quantile(level: float, dof: float) -> float:
    """Two-sided central quantile: Student-t with `dof` (normal when dof is inf)."""
    from scipy import stats  # here: scipy.stats costs ~0.4 s of `import jaxwear`

    p = 0.5 + level / 2
    return float(stats.norm.ppf(p) if not math.isfinite(dof) else stats.t.ppf(p, dof))


def _band(g, cov, null_dirs, noise, q):
    """(sd_model, sd_prediction) for gradient rows g (..., p)."""
    var = np.einsum("...i,ij,...j->...", g, cov, g)
    sd = np.sqrt(np.clip(var, 0, None))
    if null_dirs.shape[1]:
        # A forecast that moves along an undetermined direction has no finite band. "Moves":
        # by more than 1 % of the noise level per unit step along it (u's units are a
        # typical change: a factor e of a log parameter, `scale` of a linear one). A
        # relative test alone flagged forecasts whose derivative along it is the
        # integrator's round-off: the boom's running-in distance S_r, once running-in ends
        # before the first measurement, fixes nothing the forecast at 20 h depends on.
        along = np.linalg.norm(g @ null_dirs, axis=-1)
        leak = along > np.maximum(1e-6 * np.linalg.norm(g, axis=-1), 0.01 * noise)
        sd = np.where(leak, np.inf, sd)
    return sd, np.sqrt(sd ** 2 + noise ** 2)


def _param_table(result: FitResult, cov, q, null_dirs):
    prob = result.problem
    vals = np.asarray(result.values)
    # a parameter with a component along an undetermined direction has no standard error
    unknown = np.sum(null_dirs ** 2, axis=1) > 1e-6
    G = prob.packing.value_jacobian(result.u)  # diagonal but for product pairs
    out = {}
    for i, (name, f) in enumerate(zip(result.names, prob.columns)):
        touches = np.any((np.abs(G[i]) > 0) & unknown)
        se_u = math.inf if unknown[i] else math.sqrt(max(cov[i, i], 0.0))
        if f.log:
            # a band wider than exp's range (a factor beyond e^700: a finite standard error
            # of a barely determined parameter) is no bound: 0 and inf, not an overflow
            z = q * se_u
            se = vals[i] * se_u
            lo, hi = ((vals[i] * math.exp(-z), vals[i] * math.exp(z)) if z < 700.0
                      else (0.0, math.inf))
        else:
            se = math.inf if touches else math.sqrt(max(float(G[i] @ cov @ G[i]), 0.0))
            lo, hi = vals[i] - q * se, vals[i] + q * se
        out[name] = {"value": float(vals[i]), "stderr": _jf(se), "lower": _jf(lo),
                     "upper": _jf(hi)}
    return out


@dataclass(frozen=True)
class Asked:
    """What a forecast was asked: the `study` and its `train`ing part (measurements up to
    `train_until`, in `unit`: "rev" or "h"), the points `at`, the depth limit `limit_um`
    [µm] (None: no life), the band's `level`, the `method` and whether to look for the
    `life`."""

    study: Study
    train: Study
    at: list
    limit_um: float | None
    level: float
    method: str
    unit: str
    train_until: float | None
    life: bool = True


@dataclass(frozen=True)
class Fitted:
    """What the training fit gives a band: the fit's `result`, the covariance `cov` of its
    free parameters with its undetermined directions `null_dirs`, the noise σ `noise`
    [µm] (`noise_given`: stated, not estimated) with its degrees of freedom `dof`, and the
    band's quantile `q` (Student-t at `dof`)."""

    result: FitResult
    cov: object
    null_dirs: object
    noise: float
    noise_given: bool
    dof: float
    q: float


def _assemble(asked: Asked, fitted: Fitted, points, flags, snaps, J, draws, extra):
    """The `PredictResult`: each experiment's curve and band at `points` from the Laplace
    linearisation (`snaps` (E, S, N) [µm] and their Jacobian `J`) or from posterior
    `draws`, lives, the parameter table and `flags`; `extra` goes to its JSON."""
    study, train, at, limit_um, level, method, unit, train_until, life = (
        asked.study, asked.train, asked.at, asked.limit_um, asked.level, asked.method,
        asked.unit, asked.train_until, asked.life)
    result, cov, null_dirs, noise, noise_given, dof, q = (
        fitted.result, fitted.cov, fitted.null_dirs, fitted.noise, fitted.noise_given,
        fitted.dof, fitted.q)
    preds, lives, curves, profiles, measured = [], [], {}, {}, {}
    trained_on = []
    alpha = (1 - level) / 2
    for ei, e in enumerate(study.experiments):
        pts = points[ei]
        S = len(pts)
        if draws is None:
            s = snaps[ei, :S]  # (S, N)
            k = np.argmax(s, axis=1)
            depth = s[np.arange(S), k]
            g = J[ei, np.arange(S), k]  # (S, p)
            sd_m, sd_p = _band(g, cov, null_dirs, noise, q)
            c_lo, c_hi = depth - q * sd_m, depth + q * sd_m
            p_lo, p_hi = depth - q * sd_p, depth + q * sd_p
        else:
            d = draws["max_um"][:, ei, :S]  # (draws, S)
            y = draws["new_um"][:, ei, :S]
            depth = np.median(d, axis=0)
            c_lo, c_hi = np.quantile(d, alpha, axis=0), np.quantile(d, 1 - alpha, axis=0)
            # the noise integrated (`predictive_quantile`); `new_um` is +inf past the limit
            past = np.isposinf(y)
            p_lo, p_hi = (predictive_quantile(d, past, draws["noise"], a)
                          for a in (alpha, 1 - alpha))
            with np.errstate(invalid="ignore"):  # NaN past worn-through draws (unused)
                sd_m, sd_p = np.std(d, axis=0), np.std(y, axis=0)
        layer = float(study.params(e).layer_thickness) * 1e6
        valid = np.isfinite(depth) & (np.maximum.accumulate(np.nan_to_num(depth, nan=np.inf))
                                      < layer)
        curves[e.name] = Curve(pts, depth, p_lo, p_hi, c_lo, c_hi, valid)
        mpts, mmax = measured_max(e)
        te = train.experiments[ei]
        tpts = set(te.snapshot_points)
        measured[e.name] = (mpts, mmax, np.array([m in tpts for m in mpts], bool))
        if tpts:
            trained_on.append({"experiment": e.name, "unit": unit, "points": sorted(tpts),
                               "rows": int(np.sum(np.asarray(result.problem.data.exp) == ei))})
        for a in at:
            j = int(np.argmin(np.abs(pts - a)))
            hit = np.isclose(mpts, a, rtol=1e-9, atol=1e-9)
            meas = float(mmax[hit][0]) if hit.any() else None
            bad = not valid[j]
            preds.append(Prediction(
                e.name, float(a), unit, np.inf if bad else float(depth[j]),
                *(np.nan if bad else float(v) for v in (p_lo[j], p_hi[j])), meas,
                *(np.nan if bad else float(v) for v in (c_lo[j], c_hi[j], sd_m[j], sd_p[j]))))
            if bad:
                flags.append(f"{e.name} at {a:g} {unit}: the layer is worn through (no forecast)")
        horizon = LIFE_HORIZON * _last_count(te if te.snapshot_points else e)
        life_mask = pts <= horizon * (1 + 1e-12)
        # Past the central forecast's wear-through the model is extrapolated (first point
        # beyond the layer): its values still place the crossing between two grid points.
        def fin(v):
            # NaN (worn through) counts as reached; a band of ±inf (no band: an
            # undetermined direction) stays as it is: the upper reaches at once, the lower
            # never
            return np.where(np.isnan(v), np.inf, v)[life_mask]

        if life:
            lives.append(life_of(e.name, pts[life_mask], fin(depth), fin(p_lo), fin(p_hi),
                                 limit_um, unit, horizon))
        j = int(np.argmin(np.abs(pts - max(at))))
        if draws is None:
            prof = snaps[ei, j]
            sdm, sdp = _band(J[ei, j], cov, null_dirs, noise, q)
            plo, phi, clo, chi = prof - q * sdp, prof + q * sdp, prof - q * sdm, prof + q * sdm
        else:
            pr = draws["snapshots_um"][:, ei, j]  # (draws, N)
            prof = np.median(pr, axis=0)
            clo, chi = np.quantile(pr, alpha, axis=0), np.quantile(pr, 1 - alpha, axis=0)
            yy = pr + draws["noise"][:, None] * np.random.default_rng(ei).standard_normal(
                pr.shape)
            plo, phi = np.quantile(yy, alpha, axis=0), np.quantile(yy, 1 - alpha, axis=0)
        if prof is not None:
            n = len(prof)
            profiles[e.name] = {"at": float(pts[j]), "angle_deg": np.arange(n) * 360.0 / n,
                                "depth_um": prof, "lower_um": plo, "upper_um": phi,
                                "conf_lower_um": clo, "conf_upper_um": chi}
    return PredictResult(level=float(level), method=method, unit=unit,
                         train_until=None if train_until is None else float(train_until),
                         trained_on=trained_on, predictions=preds, life=lives,
                         parameters=_param_table(result, cov, q, null_dirs), noise_um=float(noise),
                         noise_given=noise_given, dof=float(dof), quantile=float(q),
                         fit_converged=bool(result.converged), fit_message=result.message,
                         fit_resolution=result.resolution,
                         fit_evaluations=int(result.iterations),
                         noise_source=(result.noise.describe() if result.noise else ""),
                         flags=flags, curves=curves, profiles=profiles, measured=measured,
                         extra=extra)
