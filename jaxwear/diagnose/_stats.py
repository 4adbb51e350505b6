"""Noise level from the data alone, and the tests of "systematic or noise"."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ._model import Model


def measurement_series(model: Model) -> list:
    """The data as ordered series: (row indices, coordinate, largest neighbour spacing).

    A profile (one experiment at one revolution count) is ordered by angle, and points
    further apart than 2.5 times its median spacing are not neighbours (the ends of a
    scar, unmeasured arcs); a depth history (one experiment) is ordered by time.
    """
    return _series(np.asarray(model.row_exp), np.asarray(model.row_time),
                   np.asarray(model.row_x), np.asarray(model.is_max, bool))


def _series(row_exp, row_time, row_x, is_max) -> list:
    out = []
    for e in sorted(set(row_exp.tolist())):
        hist = np.flatnonzero((row_exp == e) & is_max)
        if len(hist):
            order = np.argsort(row_time[hist])
            out.append((hist[order], row_time[hist][order], math.inf))
        prof = (row_exp == e) & ~is_max
        for t in sorted(set(row_time[prof].tolist())):
            rows = np.flatnonzero(prof & (row_time == t))
            order = np.argsort(row_x[rows])
            x = row_x[rows][order]
            gap = 2.5 * float(np.median(np.diff(x))) if len(x) > 1 else math.inf
            out.append((rows[order], x, gap))
    return out


def noise_triples(study) -> tuple[int, int]:
    """(neighbour triples that estimate the noise, data rows) of a study's measurements, as
    `neighbour_differences` will find them, from the files alone (before any model is
    built): an interior point of a series and its two neighbours, within the spacing."""
    exp, time, x, hist = [], [], [], []
    for i, e in enumerate(study.experiments):
        if e.profile is not None:
            n = len(e.profile.angle)
            exp += [i] * n
            time += list(e.profile.revolutions)
            x += list(np.degrees(e.profile.angle))
            hist += [False] * n
        if e.history is not None:
            n = len(e.history.hours)
            exp += [i] * n
            time += list(e.history.hours)
            x += list(e.history.hours)
            hist += [True] * n
    if not exp:
        return 0, 0
    series = _series(np.asarray(exp), np.asarray(time, float), np.asarray(x, float),
                     np.asarray(hist, bool))
    return sum(len(line_residuals(xs, np.zeros(len(xs)), gap)[0]) for _, xs, gap in series
               ), len(exp)


def line_residuals(x, y, gap=math.inf):
    """Each interior point of one series minus the straight line through its two
    neighbours, normalised: for white noise of level σ, e_i = y_i - (w y_{i-1} +
    (1-w) y_{i+1}) has variance σ² (1 + w² + (1-w)²), and a smooth curve (a wear profile,
    or a smooth misfit) nearly cancels. Triples with a spacing > `gap` are skipped.

    Returns (e_i / sqrt(1 + w² + (1-w)²), index of the middle point).
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 3:
        return np.zeros(0), np.zeros(0, int)
    a, b = np.diff(x)[:-1], np.diff(x)[1:]
    ok = (a > 0) & (b > 0) & (a <= gap) & (b <= gap)
    w = np.where(ok, b / np.where(ok, a + b, 1.0), 0.5)
    e = y[1:-1] - (w * y[:-2] + (1 - w) * y[2:])
    e = e / np.sqrt(1 + w * w + (1 - w) ** 2)
    mid = np.arange(1, len(x) - 1)
    return e[ok], mid[ok]


def neighbour_differences(model: Model, values=None):
    """`line_residuals` of every measurement series of `values` (default: the data).
    Returns (normalised differences, row index of each middle point)."""
    y = model.measured if values is None else np.asarray(values)
    es, mids = [np.zeros(0)], [np.zeros(0, int)]
    for rows, x, gap in measurement_series(model):
        e, mid = line_residuals(x, y[rows], gap)
        es.append(e)
        mids.append(rows[mid])
    return np.concatenate(es), np.concatenate(mids)


# For equally spaced white noise the normalised second differences have lag-1 and lag-2
# correlations -2/3 and 1/6, so the mean of their squares has the variance of
# n / (1 + 2 (4/9 + 1/36)) = n / 1.944 independent squares.
_D2_DOF_FACTOR = 1.0 + 2.0 * (4.0 / 9.0 + 1.0 / 36.0)


def noise_level(e) -> tuple[float, float]:
    """Noise level σ = rms of normalised neighbour differences, and its degrees of freedom
    (for an equally spaced series, see `_D2_DOF_FACTOR`)."""
    e = np.asarray(e, float)
    if len(e) == 0:
        return math.nan, 0.0
    return float(np.sqrt(np.mean(e ** 2))), len(e) / _D2_DOF_FACTOR


# Tail probabilities from scipy.stats (imported on first use: it adds over a second to
# `import jaxwear`, and only diagnose needs it).


def f_sf(F: float, d1: float, d2: float) -> float:
    """P(X > F) for X ~ F(d1, d2); d2 = inf (noise level known) is chi-square(d1)/d1."""
    from scipy import stats

    if not F > 0:
        return 1.0
    if not math.isfinite(d2):
        return chi2_sf(F * d1, d1)
    return float(stats.f.sf(F, d1, d2))


def chi2_sf(x: float, k: float) -> float:
    """P(X > x) for X ~ chi-square(k)."""
    from scipy import stats

    return float(stats.chi2.sf(x, k)) if x > 0 else 1.0


def norm_sf(z: float) -> float:
    """P(Z > z) for a standard normal Z."""
    from scipy import stats

    return float(stats.norm.sf(z))


ALPHA = 1e-3  # level of every "is it noise?" decision (family-wise, Bonferroni inside)


@dataclass(frozen=True)
class Tests:
    """Is the misfit noise? Two omnibus tests on the data residuals, and (optional) the
    score tests of the candidates not in the model.

    - chi-square (F form): (RSS/(n-k)) / σ̂², σ̂ from neighbour differences with ν degrees
      of freedom; p = P(F(n-k, ν) > observed).
    - lag-1 autocorrelation of the angle-ordered residuals (pairs of neighbouring points,
      same gap rule as the noise estimate): ρ̂ = Σ r_i r_{i+1} / Σ r_i², z = ρ̂ √pairs,
      one-sided p (smooth misfit correlates neighbours; white noise does not). This is the
      Durbin-Watson statistic in another form: DW ≈ 2 (1 - ρ̂).
    """

    rmse_um: float
    noise_um: float
    ratio: float  # (RSS/(n-k))/σ̂²
    p_chi2: float
    rho: float
    z_autocorr: float
    p_autocorr: float
    p_score: float = 1.0  # smallest Bonferroni-corrected score-test p of the candidates left
    score_effect: str | None = None

    @property
    def p_min(self) -> float:
        """Bonferroni over the three tests."""
        return min(1.0, 3 * min(self.p_chi2, self.p_autocorr, self.p_score))

    @property
    def systematic(self) -> bool:
        return self.p_min < ALPHA

    def to_json(self) -> dict:
        return {"rmse_um": self.rmse_um, "noise_um": self.noise_um,
                "chi2_ratio": self.ratio, "p_chi2": self.p_chi2,
                "lag1_autocorrelation": self.rho, "durbin_watson": 2 * (1 - self.rho),
                "z_autocorrelation": self.z_autocorr, "p_autocorrelation": self.p_autocorr,
                "p_score_min": self.p_score, "score_effect": self.score_effect,
                "p_combined": self.p_min, "systematic": self.systematic, "alpha": ALPHA}


def neighbour_pairs(model: Model):
    """Index pairs (i, j) of neighbouring rows of one series (`measurement_series`)."""
    pairs = [np.zeros((0, 2), int)]
    for rows, x, gap in measurement_series(model):
        dx = np.diff(x)
        ok = (dx > 0) & (dx <= gap)
        pairs.append(np.stack([rows[:-1][ok], rows[1:][ok]], axis=1))
    return np.concatenate(pairs)


def lag1_autocorrelation(r, pairs) -> tuple[float, float]:
    """ρ̂ = Σ r_i r_j / Σ r² over neighbouring pairs (i, j), and z = ρ̂ √pairs, which is
    standard normal for white residuals (Durbin-Watson: DW ≈ 2(1 - ρ̂))."""
    r = np.asarray(r, float)
    if len(pairs) == 0:
        return 0.0, 0.0
    used = np.unique(pairs)
    rho = float(r[pairs[:, 0]] @ r[pairs[:, 1]]) / max(float(r[used] @ r[used]), 1e-300)
    return rho, rho * math.sqrt(len(pairs))


def run_tests(model: Model, r, k: int, noise_um: float, nu: float, pairs) -> Tests:
    n = len(r)
    rss = float(r @ r)
    ratio = rss / max(n - k, 1) / noise_um ** 2
    p_chi2 = f_sf(ratio, max(n - k, 1), nu)
    rho, z = lag1_autocorrelation(r, pairs)
    return Tests(rmse_um=math.sqrt(rss / n), noise_um=noise_um, ratio=ratio, p_chi2=p_chi2,
                 rho=rho, z_autocorr=z, p_autocorr=norm_sf(z))
