"""The measurement noise: one estimator from the data's own neighbouring points, and the one
rule of which σ a fit weights its rows with.

The estimator. Within one measurement series (a scan: one experiment at one revolution
count, in angle order; a depth history: one experiment, in time order), each interior
point minus the straight line through its two neighbours cancels a smooth profile and any
smooth misfit, and leaves white noise of level σ times a known factor (`line_residuals`).
Its scale is taken robustly: the rms of these differences over those within 3.5 robust
standard deviations (1.4826 × their median absolute value) of zero, corrected for the
truncation (for Gaussian noise it keeps 99.95 % of the points and 99.39 % of the
variance). So a sharp feature the model lacks (a narrow scar edge, an impact bump, a
scratch in the scan) moves a few differences far out, which are dropped, and the estimate
stays at the noise; a plain rms would read the feature as noise (measured on a held-out
study with sharp unmodelled wear and 0.30 µm noise: the residual rms read 0.52 µm).

The rule (`stated_noise`), the same in calibrate, diagnose and predict:
1. σ given (`[fit] noise_um`, `--noise-um`): used, with infinite degrees of freedom;
2. else σ from the data by the estimator, when its degrees of freedom reach `MIN_DOF`:
   used as stated, held fixed in the fit;
3. else (a depth history of a handful of points) σ is re-estimated from the fit's
   residuals, RSS/(n − k_eff), inside the fit (`lsq.solve`).
Standard errors and bands then use the scale the data support (`lsq.error_scale`): σ, or
the residual misfit where it exceeds σ (a model that does not fit gets wider errors, and a
flag), never less than the noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_DOF = 10.0  # σ from the data is used when its degrees of freedom reach this
_CUT = 3.5  # differences beyond this many robust SDs are not noise
# E[e² | |e| < 3.5σ]/σ² for Gaussian e: 1 − 2cφ(c)/(2Φ(c) − 1) at c = 3.5
_TRUNCATED_VARIANCE = 1.0 - 2 * _CUT * math.exp(-0.5 * _CUT ** 2) / math.sqrt(2 * math.pi) / (
    math.erf(_CUT / math.sqrt(2)))
# For equally spaced white noise the normalised second differences have lag-1 and lag-2
# correlations -2/3 and 1/6, so the mean of their squares has the variance of
# n / (1 + 2 (4/9 + 1/36)) = n / 1.944 independent squares.
_D2_DOF_FACTOR = 1.0 + 2.0 * (4.0 / 9.0 + 1.0 / 36.0)


def line_residuals(x, y, gap=math.inf):
    """Each interior point of one series minus the straight line through its two
    neighbours, normalised: for white noise of level σ, e_i = y_i − (w y_{i−1} +
    (1−w) y_{i+1}) has variance σ² (1 + w² + (1−w)²), and a smooth curve (a wear profile,
    or a smooth misfit) nearly cancels. Triples with a spacing > `gap` are skipped.

    Returns (e_i / sqrt(1 + w² + (1−w)²), index of the middle point)."""
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


def series(exp, snap, is_max, x) -> list:
    """The rows as ordered series: (row indices, coordinate, largest neighbour spacing).

    A profile (one experiment at one snapshot) is ordered by angle, and points further
    apart than 2.5 times its median spacing are not neighbours (the ends of a scar,
    unmeasured arcs); a depth history (one experiment) is ordered by time."""
    exp, snap = np.asarray(exp), np.asarray(snap)
    is_max, x = np.asarray(is_max, bool), np.asarray(x, float)
    out = []
    for e in np.unique(exp):
        hist = np.flatnonzero((exp == e) & is_max)
        if len(hist):
            order = np.argsort(x[hist])
            out.append((hist[order], x[hist][order], math.inf))
        prof = (exp == e) & ~is_max
        for s in np.unique(snap[prof]):
            rows = np.flatnonzero(prof & (snap == s))
            order = np.argsort(x[rows])
            xs = x[rows][order]
            gap = 2.5 * float(np.median(np.diff(xs))) if len(xs) > 1 else math.inf
            out.append((rows[order], xs, gap))
    return out


def neighbour_differences(series_list, values):
    """`line_residuals` of every series of `values`. Returns (normalised differences, row
    index of each middle point)."""
    y = np.asarray(values, float)
    es, mids = [np.zeros(0)], [np.zeros(0, int)]
    for rows, x, gap in series_list:
        e, mid = line_residuals(x, y[rows], gap)
        es.append(e)
        mids.append(rows[mid])
    return np.concatenate(es), np.concatenate(mids)


def neighbour_pairs(series_list):
    """Index pairs (i, j) of neighbouring rows of one series."""
    pairs = [np.zeros((0, 2), int)]
    for rows, x, gap in series_list:
        dx = np.diff(x)
        ok = (dx > 0) & (dx <= gap)
        pairs.append(np.stack([rows[:-1][ok], rows[1:][ok]], axis=1))
    return np.concatenate(pairs)


def noise_level(e) -> tuple[float, float]:
    """σ from normalised neighbour differences `e` (module docstring), and its degrees of
    freedom; (nan, 0) without differences."""
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    if len(e) == 0:
        return math.nan, 0.0
    s0 = 1.4826 * float(np.median(np.abs(e)))
    keep = np.abs(e) <= _CUT * s0 if s0 > 0 else np.ones(len(e), bool)
    if keep.sum() < 2:
        keep = np.ones(len(e), bool)
    sigma = math.sqrt(float(np.mean(e[keep] ** 2)) / _TRUNCATED_VARIANCE)
    return sigma, float(keep.sum()) / _D2_DOF_FACTOR


@dataclass(frozen=True)
class Noise:
    """The noise level a fit uses: `sigma_um` (None: re-estimated from the residuals),
    its degrees of freedom `dof`, and `source` ("given", "data" or "residuals")."""

    sigma_um: float | None
    dof: float
    source: str
    data_sigma_um: float = math.nan  # the data's own estimate (reported in any case)
    data_dof: float = 0.0

    def describe(self) -> str:
        if self.source == "given":
            return "given"
        if self.source == "data":
            return "estimated from neighbouring points of the data"
        return "estimated from the residuals"


def stated_noise(data, given: float | None = None) -> Noise:
    """The rule of the module docstring for the rows of `data` (a `_residual.Data`)."""
    s = series(np.asarray(data.exp), np.asarray(data.snap), np.asarray(data.is_max),
               np.asarray(data.x))
    sd, nu = noise_level(neighbour_differences(s, np.asarray(data.depth_um))[0])
    if given is not None:
        return Noise(float(given), math.inf, "given", sd, nu)
    if nu >= MIN_DOF and sd > 0:
        return Noise(sd, nu, "data", sd, nu)
    return Noise(None, 0.0, "residuals", sd, nu)


def profile_noise(angle_deg, depth, revolutions) -> float:
    """σ of raw profile rows (the estimator of the module docstring, scans by revolution
    count; `depth` in any unit, σ in the same); NaN with fewer than 5 differences. For the
    reader's plausibility warnings."""
    revs = np.where(np.isnan(revolutions), -1.0, np.asarray(revolutions, float))
    x = np.asarray(angle_deg, float)
    snap = np.unique(revs, return_inverse=True)[1]
    s = series(np.zeros(len(x), int), snap, np.zeros(len(x), bool), x)
    e = neighbour_differences(s, depth)[0]
    return noise_level(e)[0] if len(e) >= 5 else math.nan
