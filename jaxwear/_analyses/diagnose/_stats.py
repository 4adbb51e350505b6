"""Noise level from the data alone, and the tests of "systematic or noise"."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

from jaxwear._core import noise as _noise
from jaxwear._core.noise import line_residuals

if TYPE_CHECKING:
    from jaxwear._analyses.diagnose._model import Model


def measurement_series(model: Model) -> list:
    """The data as ordered series (`_noise.series`): (row indices, coordinate, largest
    neighbour spacing)."""
    return model.series


def neighbour_differences(model: Model, values=None):
    """`_noise.line_residuals` of every measurement series of `values` (default: the
    data). Returns (normalised differences, row index of each middle point)."""
    return _noise.neighbour_differences(model.series,
                                        model.measured if values is None else values)


def noise_triples(study) -> tuple[int, int]:
    """(neighbour triples that estimate the noise, data rows) of a study's measurements, as
    `neighbour_differences` will find them, from the files alone (before any model is
    built): an interior point of a series and its two neighbours, within the spacing."""
    exp, snap, x, hist = [], [], [], []
    for i, e in enumerate(study.experiments):
        if e.profile is not None:
            n = len(e.profile.angle)
            exp += [i] * n
            snap += list(e.profile.revolutions)
            x += list(np.degrees(e.profile.angle))
            hist += [False] * n
        if e.history is not None:
            n = len(e.history.hours)
            exp += [i] * n
            snap += [0.0] * n
            x += list(e.history.hours)
            hist += [True] * n
    if not exp:
        return 0, 0
    series = _noise.series(np.asarray(exp), np.asarray(snap, float), np.asarray(hist, bool),
                           np.asarray(x, float))
    return sum(len(line_residuals(xs, np.zeros(len(xs)), gap)[0]) for _, xs, gap in series
               ), len(exp)


def neighbour_pairs(model: Model):
    """Index pairs (i, j) of neighbouring rows of one series."""
    return _noise.neighbour_pairs(model.series)


# Tail probabilities from scipy.stats (imported on first use: it adds over a second to
# `import jaxwear`, and only diagnose needs it).


def f_sf(F: float, d1: float, d2: float) -> float:
    """P(X > F) for X ~ F(d1, d2); d2 = inf (noise level known) is chi-square(d1)/d1."""

    if not F > 0:
        return 1.0
    if not math.isfinite(d2):
        return chi2_sf(F * d1, d1)
    return float(stats.f.sf(F, d1, d2))


def chi2_sf(x: float, k: float) -> float:
    """P(X > x) for X ~ chi-square(k)."""

    return float(stats.chi2.sf(x, k)) if x > 0 else 1.0


def norm_sf(z: float) -> float:
    """P(Z > z) for a standard normal Z."""

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
