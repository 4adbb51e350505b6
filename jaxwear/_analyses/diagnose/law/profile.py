"""Honest uncertainty of the law's constants where the linearised standard errors do not
describe the misfit (issue 48): a check of the quadratic approximation, and where it fails
a profile of the misfit.

Why: a law's standard errors are the Gauss-Newton covariance's (`lsq.covariance`): the
misfit χ² taken as quadratic in the fit's coordinates u. A hinge's threshold and exponent
lie along a flat, curved valley where it is not (docs/shape_validation.md, "Numerical
error of the law's constants"): on the rich design's hinge in the sliding speed, seed 3,
the answer v0 = 0.0481 ± 0.0017 m/s, a1 = 1.30 ± 0.16 was 2.8 and 2.5 combined
uncertainties from the generator's 0.04 and 2, yet χ² differs by ~0.5 between the two.

1. **The check** (`CHECK_K`, one forward run a side): each fitted constant of the law (its
   study key's column j of u) moved by ± k standard errors along its covariance direction
   (the other columns following by their linear regression on it: δu = ± k C[:, j]/√C_jj,
   where the Gauss-Newton model predicts Δχ² = k² ± 2k gᵀd, g the gradient the fit's
   stop left), the model run forward there and the true Δχ² compared with the model's: it
   passes where they differ by at most ((1 + `CHECK_RTOL`)² − 1) k² on both sides (the
   standard error the misfit implies there within that fraction of the linearised one).
2. **The profile** (the constants that fail the check only): column j held at trial
   values û_j + t and the others refitted through the one least-squares core
   (`_fit.fit_masked`, the law fit's own compiled model, `PROFILE_EVALUATIONS` at most
   each, started from the last refit's answer moved by the regression); on each side the
   t where the profile's Δχ² is 1 is found by a secant on the signed root √Δχ² (linear
   in t where χ² is quadratic: `side_end`), `PROFILE_POINTS` refits a side at most, the
   constants that fail worst first, `PROFILE_BUDGET` evaluations for all of them. The
   interval [low, high] where the profile is within Δχ² = 1 of its lowest point (all the
   points together, `interval_from_points`) is reported, and the constant's `stderr` becomes
   the larger of its two sides (at least the linearised one: a refit of few evaluations
   stops above the conditional minimum, so its Δχ² is an upper bound of the profile's
   and an interval narrower than the linear one is not trusted), so that `uncertainty`
   = √(SE² + numerical²) carries it; the linearised one is kept beside it.

The misfit checked and profiled is the corrected constants' (`law.numerical`): the fit's
rows moved by δ, the finer level's less the fit's at the answer (a rows' correction the
compiled model holds as data, `Model.with_defect`), centred on the corrected answer: the
finer level's misfit to first order. Why: on the hinge the study's 48 x 72 bias the
constants by more than their errors and the valley runs differently there; the profile of
the study's own misfit, shifted by the correction, left the truth 2.1 of its uncertainty
from v0 (measured, the run of this module's first version), where at 96 x 144 the truth
is within Δχ² 0.5 of the answer. Where no correction was made, the fit's own misfit.

χ² is scaled as the standard errors are (`lsq.error_scale`: the data rows by σ, or by
the residual misfit where it exceeds σ, with the prior rows in their standard
deviations): Δχ² = 1 is one linearised standard error where the misfit is quadratic.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from jaxwear._analyses.diagnose._fit import _log, fit_masked
from jaxwear._analyses.diagnose._model import Model
from jaxwear._core.background import in_context
from jaxwear._core.log import held
from jaxwear._inference import lsq
from jaxwear._physics.effects.law import LAW_EFFECT, SYMBOLS, constants

CHECK_K = 2.0  # the check at ± 2 standard errors: the recovery's bar (Δχ² = 4)
# the check passes where the true Δχ² is within ((1 + this)² − 1) k² of the Gauss-Newton
# model's on both sides: the standard error the misfit implies at ± k SE within about
# 20 % of the linearised one (a z of 2 read as 2.4)
CHECK_RTOL = 0.2
PROFILE_POINTS = 3  # refits a side at most (a secant on 2-3 points)
PROFILE_EVALUATIONS = 4  # model evaluations of one refit at most (its start included)
ROOT_TOL = 0.1  # a side's end found where |√Δχ² − 1| is below this (Δχ² in 0.81-1.21)
# a secant step at most this many times the last trial's distance (and this many where
# Δχ² did not rise: a flat side). Why not 4: on the hinge a side whose first refit came
# out below the answer stepped to 4 SE and met Δχ² 8-57, three refits of 4 evaluations
GROW = 2.5
# model evaluations the profiles of one answer may spend (a profile is started only where
# the mean cost of those made, at least `PROFILE_COST`, still fits);
# the constants that fail the check worst are profiled first, those left keep their
# linearised errors and are named (`Profile.over_budget`). Why 40: a profile takes
# 14-20 evaluations (measured, rich design's hinge seed 3: three in 52, 75-81 s of CPU
# under load; the paper design's step(p)·power(v) seed 1, a 5-experiment study of the
# 2-minute bar: three in 52, 50 s): two constants at most, the worst failing
PROFILE_BUDGET = 40
PROFILE_COST = 16  # evaluations a profile is expected to take before one is made
# a profile's two sides run at once, one in a second thread, where the machine has two
# cores: each side is a chain of up to `PROFILE_POINTS` single-threaded refits from the
# centre, independent of the other's. Measured on the generator's step(p)·power(v) (the
# 2-minute bar's study, 2 cores, 2026-11-29): two profiles of 40 evaluations took 20.7 s of
# `diagnose --shape`'s wall, one side after the other
SIDES_APART = True


def constant_keys(law) -> dict:
    """{NAME of `constants(law)`: the study key it is fitted as} for the law's fitted
    constants (a hinge's threshold `law_x0_k`, an exponential's scale `law_b_k`, ...);
    {} for a law with memory (its own constants)."""
    if getattr(law, "memory", False) or not hasattr(law, "terms"):
        return {}
    out = {("A" if law.form == "factor" else "D"): law.strength_key}
    for k, t in enumerate(law.terms, 1):
        sym = SYMBOLS[t.variable]
        if t.kind in ("power", "hinge"):
            out[f"a{k}"] = f"law_a_{k}"
        if t.kind in ("hinge", "step"):
            out[f"{sym}0"] = f"law_x0_{k}"
        if t.kind == "step":
            out[f"{sym}_width"] = f"law_w_{k}"
        if t.kind == "exp":
            out[f"{sym}_e"] = f"law_b_{k}"
    return out


def side_end(delta_chi2: Callable[[float], float], t1: float, *, points: int = PROFILE_POINTS,
             tol: float = ROOT_TOL, bound: float = math.inf) -> tuple[float, list, bool]:
    """Where a profile's Δχ²(t) reaches 1 on the side of `t1` (t1 ≠ 0, its sign the
    side's; Δχ²(0) = 0 at the answer): a secant on the signed root ρ(t) = √max(Δχ², 0)
    (linear in t where χ² is quadratic), from (0, 0) and t1, at most `points` evaluations
    of `delta_chi2`, stopped where |ρ − 1| < `tol`; a step at most `GROW` times the last
    trial's distance and never beyond `bound` (≥ 0, the distance to the coordinate's
    bound). Returns (t at Δχ² = 1: the secant's estimate from the last two points (one
    step more, not evaluated), at most `GROW` times the last trial's distance and
    `bound`; the (t, Δχ²) evaluated; whether the last trial was within `tol`). A trial
    whose Δχ² is not finite (the model did not run) ends the side at the last finite
    one's estimate."""
    sign = 1.0 if t1 > 0 else -1.0
    pts = [(0.0, 0.0)]
    done: list = []
    t = sign * min(abs(t1), bound)
    for _ in range(points):
        d = float(delta_chi2(t))
        if not math.isfinite(d):
            done.append((t, d))
            break
        done.append((t, d))
        rho = math.sqrt(max(d, 0.0))
        pts.append((abs(t), rho))
        nxt = _secant(pts, bound)
        if abs(rho - 1.0) < tol:
            # the secant's last step, not evaluated: where ρ is not linear in t (a
            # profile whose Δχ² grows linearly, a banana's) it brings the end closer
            return sign * (nxt if nxt is not None else abs(t)), done, True
        if nxt is None or math.isclose(nxt, abs(t), rel_tol=1e-9):
            break
        t = sign * nxt
    if len(pts) < 2:  # the first trial did not run: its distance, not reached
        return sign * min(abs(t1), bound), done, False
    est = _secant(pts, bound)
    return sign * (est if est is not None else pts[-1][0]), done, False


def _secant(pts: list, bound: float) -> float | None:
    """The distance where ρ = 1 on the secant through the last two (distance, ρ) of
    `pts`, kept within `GROW` times the last distance and `bound`; where ρ does not rise
    with the distance between them (a flat or non-monotone profile), `GROW` times the
    last distance."""
    (t0, r0), (t1, r1) = pts[-2], pts[-1]
    slope = (r1 - r0) / (t1 - t0) if t1 != t0 else math.nan
    if slope > 0:
        t = t1 + (1.0 - r1) / slope
    else:
        t = GROW * t1
    t = min(max(t, t1 / GROW), GROW * t1, bound)
    return t if t > 0 else None


def interval_from_points(points, t_low: float = -math.inf, t_high: float = math.inf):
    """The profile's interval from its evaluated points (t, Δχ²) (the answer's (0, 0)
    among them; Δχ² against the answer's χ²): its lowest point (t_m, Δ_m), and on each
    side the t where Δχ² = Δ_m + 1, interpolated on the signed root √(Δχ² − Δ_m) between
    the points that bracket it, else extrapolated by the secant of the side's last two
    points (at most `GROW` times the last one's distance, within [`t_low`, `t_high`]),
    else (no point beyond the lowest on that side) `GROW` times the farthest point's
    distance. Why from the lowest point: where the answer is not the minimum of the
    misfit profiled (a fit stopped along a flat valley, a linear correction), Δχ² = 1
    above the answer is not an interval of the likelihood (on the hinge the corrected
    misfit's profile fell 7.7 below the answer's). Returns (t at the low end, at the
    high end, t_m, Δ_m, (low end bracketed, high end bracketed))."""
    pts = sorted((float(t), float(d)) for t, d in points if math.isfinite(d))
    if not pts:
        return math.nan, math.nan, 0.0, 0.0, (False, False)
    m = min(range(len(pts)), key=lambda i: pts[i][1])
    tm, dm = pts[m]
    far = max((abs(t - tm) for t, _ in pts), default=0.0)

    def end(side: int):
        seq = pts[m::-1] if side < 0 else pts[m:]
        room = (tm - t_low) if side < 0 else (t_high - tm)
        rs = [(abs(t - tm), math.sqrt(max(d - dm, 0.0))) for t, d in seq]
        for k in range(1, len(rs)):
            if rs[k][1] >= 1.0:
                (a, ra), (b, rb) = rs[k - 1], rs[k]
                dist = a + (1.0 - ra) * (b - a) / (rb - ra) if rb > ra else b
                return tm + side * min(dist, room), True
        if len(rs) >= 2:
            dist = _secant(rs, max(room, 0.0))
            dist = rs[-1][0] if dist is None else dist
        else:
            dist = min(GROW * far, room) if far > 0 else 0.0
        return tm + side * dist, False

    (lo_t, lo_ok), (hi_t, hi_ok) = end(-1), end(1)
    return lo_t, hi_t, tm, dm, (lo_ok, hi_ok)


@dataclasses.dataclass(frozen=True)
class Profile:
    """The check of the answer's linearised standard errors and the profiles made
    (module docstring): per constant checked, the Δχ² at ∓/± `k` standard errors
    (`check`: NAME -> (Δχ² below, Δχ² above)); per constant profiled (`intervals`: NAME
    -> {low, high, stderr_linear, minimum (the value at the profile's lowest point),
    delta_chi2_minimum (its Δχ² against the answer), points: [[value, Δχ²], ...],
    reached (each end bracketed by points, not extrapolated)}); the χ² scale
    [µm] (`lsq.error_scale`), the forward runs and model evaluations added and their CPU
    seconds; why nothing was checked where nothing was."""

    k: float = CHECK_K
    check: dict = dataclasses.field(default_factory=dict)
    # NAME -> (Δχ² below, above) the Gauss-Newton model predicts (k² and the gradient's)
    predicted: dict = dataclasses.field(default_factory=dict)
    intervals: dict = dataclasses.field(default_factory=dict)
    scale_um: float = math.nan
    forward_runs: int = 0
    model_evaluations: int = 0
    # of them, those of the profiles' second thread (`SIDES_APART`), which the caller's
    # own count (`Model.own_evaluations`) does not hold
    evaluations_beside: int = 0
    cpu_s: float = 0.0
    why: str = ""
    # the lowest Δχ² a profile's refit met below the answer (< 0: the answer was not the
    # minimum; clipped to 0 in the secant, which widens that side)
    lowest_delta_chi2: float = 0.0
    # the misfit checked and profiled is the corrected constants' (the rows moved by the
    # finer level's δ, `law.numerical`), else the fit's own
    corrected_rows: bool = False
    # constants that failed the check but were not profiled (`PROFILE_BUDGET` spent)
    over_budget: tuple = ()
    # constants that failed the check, not profiled: the fit stopped short of its minimum
    # (`LawFit.status` not "converged", e.g. its budget)
    unconverged: tuple = ()

    def passes(self, name: str) -> bool:
        """Δχ² at ∓/± k SE within `CHECK_RTOL` of the Gauss-Newton model's on both sides,
        in the units of k² (the misfit's implied standard error within that fraction)."""
        d, m = self.check.get(name), self.predicted.get(name)
        tol = ((1.0 + CHECK_RTOL) ** 2 - 1.0) * self.k ** 2
        return (d is not None and m is not None
                and all(math.isfinite(x) and abs(x - y) <= tol for x, y in zip(d, m)))

    def to_json(self) -> dict:
        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {"k": self.k, "rtol": CHECK_RTOL,
                "checked": sorted(self.check), "profiled": sorted(self.intervals),
                "chi2_scale_um": num(self.scale_um), "forward_runs": self.forward_runs,
                "model_evaluations": self.model_evaluations, "cpu_s": self.cpu_s,
                "lowest_delta_chi2": num(self.lowest_delta_chi2),
                "on_corrected_rows": self.corrected_rows,
                "not_profiled_budget": list(self.over_budget),
                "not_profiled_unconverged": list(self.unconverged),
                "budget_evaluations": PROFILE_BUDGET,
                "why": self.why or None}

    def constant_json(self, name: str) -> dict:
        """The keys one constant of `shape.law.constants` gains: `quadratic_check`, and
        `profile` where it was profiled."""
        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        out = {}
        if name in self.check:
            out["quadratic_check"] = {"k": self.k,
                                      "delta_chi2": [num(x) for x in self.check[name]],
                                      "predicted": [num(x) for x in
                                                    self.predicted.get(name, ())],
                                      "passes": self.passes(name)}
        if name in self.intervals:
            iv = self.intervals[name]
            out["profile"] = {"low": num(iv["low"]), "high": num(iv["high"]),
                              "stderr_linear": num(iv["stderr_linear"]),
                              "reached": list(iv["reached"]),
                              "minimum": num(iv.get("minimum")),
                              "delta_chi2_minimum": num(iv.get("delta_chi2_minimum")),
                              "points": [[num(v), num(d)] for v, d in iv["points"]]}
        return out


def profile_law(lf, noise_um: float, nu: float, *, verbose: bool = False):
    """`lf` (the answer's `LawFit`, after `law.numerical.correct_law`) with its constants'
    linearised standard errors checked and, where the check fails, replaced by the
    profile's (module docstring); `profile` set. Call inside `effects.law.searching()`."""
    c0, e0 = time.process_time(), Model.own_evaluations()
    apart = [0]  # model evaluations in the profiles' second thread (`SIDES_APART`)
    f, lm = lf.fit, lf.model

    def out(prof, **kw):
        prof = dataclasses.replace(prof, cpu_s=time.process_time() - c0,
                                   model_evaluations=Model.own_evaluations() - e0
                                   + apart[0], evaluations_beside=apart[0])
        return dataclasses.replace(lf, profile=prof, **kw)

    keys = constant_keys(lf.law)
    if f is None or lm is None or f.values is None or f.cov is None or not f.ev.usable:
        return out(Profile(why="the law's fit has no usable answer to check"))
    if not keys:
        return out(Profile(why="a law with memory: its constants are not checked"))
    free = np.asarray(f.mask, bool)
    idx = np.flatnonzero(free)
    pos = {int(i): p for p, i in enumerate(idx)}
    C = np.asarray(f.cov.cov, np.float64)
    und = np.asarray(f.cov.undetermined, bool)
    todo = {nm: lm.index[k] for nm, k in keys.items()
            if k in lm.index and lm.index[k] in pos and not und[pos[lm.index[k]]]
            and nm in lf.constants}
    if not todo:
        return out(Profile(why="no determined constant to check"))
    ev0 = f.ev
    u_fit = np.asarray(ev0.u, np.float64)
    n = len(lm.measured)
    rss = float(np.sum((ev0.pred - lm.measured) ** 2))
    # the scale of the standard errors as the core chose it (`lsq.solve`'s outcome: k_eff
    # of the covariance at σ)
    k_eff = lsq.covariance(lsq.whitened(ev0.point(), float(noise_um), free)[1], n).k_eff
    scale, _ = lsq.error_scale(rss, n, k_eff, float(noise_um), nu, False)
    lo, hi = lm.bounds_u()
    num = lf.numerical
    corrected = (num is not None and getattr(num, "corrected", False)
                 and getattr(num, "delta", None) is not None and num.u is not None)
    if corrected:
        # the misfit of the corrected constants: the fit's rows moved by δ, the finer
        # level's less the fit's at the answer (`law.numerical`; the finer level's misfit
        # to first order), its minimum the corrected answer. The same compiled programs
        # (the rows' correction is a traced array)
        lm = lm.with_defect(lm.ext.defect + num.delta)
        u0 = np.asarray(num.u, np.float64)
    else:
        u0 = u_fit
    runs = 0

    def chi2(pred, r_prior) -> float:
        r = (np.asarray(pred) - lm.measured) / scale
        return float(r @ r + r_prior @ r_prior)

    def prior_at(u):  # the prior rows at u (Gaussian in u: linear rows)
        return ev0.r_prior + ev0.J_prior @ (u - u_fit)

    # χ² at the centre (one forward run where the constants were corrected)
    if corrected:
        pred0 = lm.predict(u0)
        runs += 1
        if not np.all(np.isfinite(pred0)):
            return out(Profile(why="the model did not run at the corrected answer",
                               forward_runs=runs))
    else:
        pred0 = ev0.pred
    base = chi2(pred0, prior_at(u0))
    # the Gauss-Newton model of χ² at the centre, at the standard errors' scale (the fit's
    # Jacobian): Δχ²(δ) = 2 gᵀδ + |Jw δ|², g = Jwᵀ rw (the fit's stop leaves a gradient
    # along a flat valley, and the correction a step of the linear model only: they move
    # the two sides apart linearly)
    Jw = lsq.whitened(ev0.point(), scale, free)[1]
    rw = np.concatenate([(pred0 - lm.measured) / scale, prior_at(u0)])
    grad = Jw.T @ rw

    def forward(u) -> float:
        nonlocal runs
        pred = lm.predict(u)
        runs += 1
        if not np.all(np.isfinite(pred)):
            return math.nan
        return chi2(pred, prior_at(u)) - base

    def value_at(u, name) -> float:
        law = lf.law.with_values(dict(zip(lm.names, map(float, lm.values(u)))))
        return float(constants(law)[name][0])

    _log(verbose, f"  law {lf.law.label}: its standard errors checked at ± {CHECK_K:g} SE "
                  f"(forward runs along each constant's covariance direction)")
    check, predicted = {}, {}
    for nm, j in todo.items():
        p = pos[j]
        d = C[:, p] / math.sqrt(C[p, p])
        sides, model = [], []
        for sgn in (-1.0, 1.0):
            step = sgn * CHECK_K * d
            model.append(float(2.0 * grad @ step + np.sum((Jw @ step) ** 2)))
            u = u0.copy()
            u[idx] += step
            if np.any(u < lo) or np.any(u > hi):
                sides.append(math.nan)  # a bound within k SE: the quadratic does not hold
                continue
            sides.append(forward(u))
        check[nm], predicted[nm] = tuple(sides), tuple(model)
    prof = Profile(check=check, predicted=predicted, scale_um=scale, forward_runs=runs,
                   corrected_rows=corrected)
    bad = [nm for nm in todo if not prof.passes(nm)]
    _log(verbose, f"    Δχ² at ∓/± {CHECK_K:g} SE, true (quadratic model's): " + "; ".join(
        f"{nm} {a:.3g}/{b:.3g} ({predicted[nm][0]:.3g}/{predicted[nm][1]:.3g})"
        for nm, (a, b) in check.items())
        + (f"; profiled: {', '.join(bad)}" if bad else "; the linearised errors stand"))
    if not bad:
        return out(prof)
    if lf.status != "converged":
        # a fit that stopped short of its minimum (its budget, its steps still several
        # standard errors) has no likelihood's shape around it to profile: the profile
        # would only go on with the fit. Measured on the speed study's power(v) (budget,
        # its last step 2.6 SE): A's profile came out lowest 4.7 below the answer at three
        # times its value, and its 40 evaluations took `diagnose --shape` from ~90 s to
        # 129.9 s (quiet, 2 cores). Its ± stays the linearised one, said to be so
        _log(verbose, f"    not profiled (the fit ended {lf.status}, short of its minimum): "
                      f"{', '.join(bad)}: their linearised errors stand")
        return out(dataclasses.replace(prof, unconverged=tuple(bad)))

    # the profiles' centre: the answer (corrected). A law candidate's fit stops once ½χ²
    # settles (`SETTLED_CHI2`), and the correction is one linear step: along a flat
    # valley a refit may come out below the centre (the hinge: Δχ² −0.57 a standard
    # error away on the fit's rows, −7.7 on the corrected rows; three more evaluations
    # of the whole fit lowered it by 0.025 only, so no polish is made). The secant's
    # search clips such a Δχ² to 0 (it steps on), and the interval is taken around the
    # profile's lowest point (`interval_from_points`), the lowest reported
    # (`lowest_delta_chi2`, and each profile's `minimum`).
    Cc, ref, uc = C, base, u0
    lowest = 0.0
    cs = dict(lf.constants)
    intervals = {}

    def severity(nm):  # how far the check's worse side is from the model's (NaN: worst)
        gaps = [abs(a - b) for a, b in zip(check[nm], predicted[nm])]
        return max((x if math.isfinite(x) else math.inf) for x in gaps)

    spent, over, done = 0, [], 0  # model evaluations of the profiles, in every thread
    sides_apart = SIDES_APART and (os.cpu_count() or 1) > 1
    for nm in sorted(bad, key=severity, reverse=True):
        # a profile is started where the budget holds it: what it will take estimated by
        # the mean of those made (at least `PROFILE_COST`)
        if spent + max(PROFILE_COST, spent / max(done, 1)) > PROFILE_BUDGET:
            over.append(nm)
            continue
        done += 1
        j = todo[nm]
        p = pos[j]
        reg = Cc[:, p] / Cc[p, p]  # the others' regression on column j (per unit of u_j)
        se_u = math.sqrt(Cc[p, p])
        mask = free.copy()
        mask[j] = False

        def side(sgn, nm=nm, j=j, reg=reg, se_u=se_u, mask=mask):
            """(its points (t, value, Δχ²), its progress lines, its model evaluations):
            one side of the profile, from the centre out (`side_end`), on its own copy of
            the model: the attempt counts its runs raise (`Model.evaluate`) reach neither
            the other side's nor depend on which ran first, so that the sides at once and
            one after the other give the same points."""
            e0, mine, last = Model.own_evaluations(), [], {"t": 0.0, "u": uc.copy()}
            sm = copy.copy(lm)

            def delta(t):
                u = last["u"].copy()
                u[idx] += (t - last["t"]) * reg
                u[j] = uc[j] + t
                u = np.clip(u, lo, hi)
                try:
                    g = fit_masked(sm, mask, u, noise_um=noise_um, noise_dof=nu,
                                   label=f"profile {nm}", groups=(LAW_EFFECT,),
                                   max_evaluations=PROFILE_EVALUATIONS - 1)
                except lsq.FitError:
                    return math.nan
                if g.values is None or not g.ev.usable:
                    return math.nan
                last.update(t=t, u=np.asarray(g.ev.u, np.float64))
                dc = chi2(g.ev.pred, g.ev.r_prior) - ref
                mine.append((float(g.ev.u[j] - uc[j]), value_at(g.ev.u, nm), dc))
                _log(verbose, f"      {nm} {value_at(g.ev.u, nm):.5g}: Δχ² {dc:.3g} "
                              f"({g.evaluations} evaluations, {g.status})")
                return dc

            # the first trial at the linearised standard error (the end where χ² is
            # quadratic); not where the check's line says Δχ² = 1: the line leaves a
            # curved valley the refit follows (the hinge's: Δχ² 40-75 at 2 SE on the
            # line, the profile's Δχ² = 1 beyond 1 SE)
            room = (uc[j] - lo[j]) if sgn < 0 else (hi[j] - uc[j])
            with held() as lines:
                side_end(delta, sgn * se_u, bound=max(room, 0.0))
            return mine, lines, Model.own_evaluations() - e0

        # the two sides at once where the machine has a second core (each a chain of
        # refits from the centre: independent), their lines printed low side first
        if sides_apart:
            with ThreadPoolExecutor(max_workers=1, thread_name_prefix="jaxwear-profile") as ex:
                low_side = ex.submit(in_context(side), -1.0)
                high = side(1.0)
                low = low_side.result()
            apart[0] += low[2]
        else:
            low, high = side(-1.0), side(1.0)
        pts = []
        for mine, lines, evals in (low, high):
            pts += mine
            spent += evals
            for line in lines:
                _log(verbose, line)
        lowest = min([lowest] + [dc for _, _, dc in pts])
        # the interval from every point of the profile (both sides and the answer),
        # around its lowest (`interval_from_points`)
        t_lo, t_hi, t_m, d_m, reached = interval_from_points(
            [(0.0, 0.0)] + [(t, d) for t, _, d in pts], lo[j] - uc[j], hi[j] - uc[j])

        def value_t(t, nm=nm, j=j):
            u = uc.copy()
            u[j] = uc[j] + t
            return value_at(u, nm)

        v, s_lin, unit = cs[nm]
        # the reported value less the centre's (0 but for rounding: the centre is the
        # corrected answer, or the fit's where no correction was made)
        shift = v - value_at(u0, nm)
        ends = [value_t(t_lo), value_t(t_hi)]
        low, high = min(ends) + shift, max(ends) + shift
        wide = max(high - v, v - low)
        se_new = max(s_lin, wide) if math.isfinite(wide) else s_lin
        cs[nm] = (v, se_new, unit)
        intervals[nm] = {"low": low, "high": high, "stderr_linear": s_lin,
                         "reached": tuple(reached), "minimum": value_t(t_m) + shift,
                         "delta_chi2_minimum": d_m,
                         "points": sorted((pv + shift, d) for _, pv, d in pts)}
        more = "" if all(reached) else ", an end extrapolated"
        _log(verbose, f"    {nm}: profile [{low:.4g}, {high:.4g}] (Δχ² = 1 above its lowest, "
                      f"{d_m:.3g} at {value_t(t_m) + shift:.4g}{more}), standard error "
                      f"{s_lin:.3g} -> {se_new:.3g}")
    if over:
        _log(verbose, f"    not profiled ({PROFILE_BUDGET} evaluations spent): "
                      f"{', '.join(over)}: their linearised errors stand")
    prof = dataclasses.replace(prof, intervals=intervals, forward_runs=runs,
                               lowest_delta_chi2=lowest, over_budget=tuple(over))
    return out(prof, constants=cs)
