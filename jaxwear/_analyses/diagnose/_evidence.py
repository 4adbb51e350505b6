"""Evidence against the base model, leave-one-experiment-out errors, residual summaries."""

from __future__ import annotations

import math

import numpy as np

from jaxwear._analyses.diagnose._fit import Fit, whitened_system
from jaxwear._analyses.diagnose._model import Model, objective
from jaxwear._inference import lsq
from jaxwear._physics.config import timed

EXPLAINED_FOR_SECOND_STAGE = 0.5  # a first effect must remove this much misfit to look on
AMBIGUOUS_LOG_BF = math.log(20.0)  # evidence gap below which two candidates are a tie
STRONG_LOG_BF = math.log(150.0)  # "very strong" evidence (Kass & Raftery 1995)


def evidence_from(n: int, q_base: float, q_fit: float, dk: int) -> float:
    """ln Bayes factor of a fit against the base model, BIC approximation with the noise
    level unknown: ½ [n ln(Q_base/Q_fit) - Δk ln n], Q the weighted least-squares
    objective. It needs no noise estimate, so it also works for a handful of points
    (a depth-vs-time history), where a noise level from the data alone is uncertain."""
    if not (q_fit > 0 and q_base > 0):
        return -math.inf if q_fit > 0 else math.inf
    return 0.5 * (n * math.log(q_base / q_fit) - dk * math.log(n))


def evidence(model: Model, fit: Fit, base: Fit, noise_um: float) -> float:
    """ln Bayes factor of `fit` against `base` (see `evidence_from`); `noise_um` weighs the
    prior rows into the objective (`objective`)."""
    return evidence_from(model.n, objective(base.ev, noise_um), objective(fit.ev, noise_um),
                         fit.k - base.k)


def loo(model: Model, fit: Fit, noise_um: float) -> dict:
    """Leave-one-experiment-out prediction RMSE [µm] per experiment: the fit without the
    experiment's rows (one Gauss-Newton step from the full fit, on the whitened system as
    the core sees it: the experiment's own clearance then returns to its prior, the
    nominal value), predicting those rows."""
    rw, Jw = whitened_system(fit.ev, fit.mask, noise_um)
    out = {}
    for name, rows, _, step in _left_out_steps(model, rw, Jw):
        pred = noise_um * (rw[rows] + Jw[rows] @ step)
        out[name] = float(np.sqrt(np.mean(pred ** 2)))
    return out if len(out) > 1 else {}  # one experiment: nothing to leave out


def _left_out_steps(model: Model, rw, Jw):
    """(experiment, its rows, the mask of the rows kept, the Gauss-Newton step of the
    whitened system `rw`, `Jw` without its rows) for each experiment that has rows."""
    for ei, name in enumerate(model.exp_names):
        rows = np.flatnonzero(model.row_exp == ei)
        if len(rows) == 0:
            continue
        keep = np.ones(len(rw), bool)
        keep[rows] = False
        yield name, rows, keep, lsq.gauss_newton(rw[keep], Jw[keep])[0]


LOO_HALVINGS = 3  # a left-out step that raises the left-in misfit is halved this often


# times a left-out check's forward run may double its attempt count (`loo_refined`)
LOO_DOUBLINGS = 1
# a left-out step whose estimated attempt count is over this many times the fit's is not
# run (halved): the doublings above bound a run's growth, not its start
LOO_STIFF = 16.0


def loo_refined(model: Model, fit: Fit, noise_um: float, predict=None) -> tuple[dict, int]:
    """({experiment: left-out prediction RMSE [µm]}, forward runs made): `loo`'s
    Gauss-Newton step without the experiment's rows, checked by one forward run of the
    model there (`predict`: u of `model` -> rows [µm], default `model.predict`), which
    gives the left-out rows exactly and the left-in misfit; a step that raises the left-in
    misfit (the linearisation fails: a sharp step's threshold) is halved, at most
    `LOO_HALVINGS` times. Why: `loo`'s linearised prediction of the left-out rows from an
    undamped step blew up to 819 µm for a smooth step in the worn depth whose in-sample
    RMSE was at the noise (issue 48), and ranked a good law last. An experiment whose step
    no fraction makes lower the left-in misfit is given the worse of the last forward run
    and the linearised prediction: a step cut to an eighth predicts nearly as the fit to
    every experiment does, whose error on the rows it has seen understates theirs."""
    if predict is None:
        # a left-out step whose integration needs more than twice the attempts the fit's
        # own runs took is stiff there: halved like a step that raises the misfit, not
        # integrated at up to 8x the attempts. Measured (issue 48, the generator's speed
        # bump, 2026-11-28): the checks of a law power(W)·exp(ω) ran one forward run for
        # over 6 minutes of wall; the law search took 1795 s of CPU in 188 model runs
        def predict(u):
            return model.predict(u, doublings=LOO_DOUBLINGS, stiff=LOO_STIFF)
    rw, Jw = whitened_system(fit.ev, fit.mask, noise_um)
    n = len(model.measured)
    free = np.flatnonzero(fit.mask)
    lo, hi = model.bounds_u()
    u0 = np.asarray(fit.ev.u, np.float64)
    measured = np.asarray(model.measured, np.float64)
    out, runs = {}, 0
    for name, rows, keep, step in _left_out_steps(model, rw, Jw):
        data_in = np.flatnonzero(keep[:n])
        q0 = float(rw[keep] @ rw[keep])
        # the undamped step's linearised prediction of the rows left out (`loo`'s)
        linear = float(np.sqrt(np.mean((noise_um * (rw[rows] + Jw[rows] @ step)) ** 2)))
        best, accepted = None, False
        for _ in range(LOO_HALVINGS + 1):
            u = u0.copy()
            u[free] = np.clip(u0[free] + step, lo[free], hi[free])
            d = np.asarray(predict(u), np.float64)
            runs += 1
            if np.all(np.isfinite(d)):
                r = (d - measured) / noise_um
                prior = rw[n:] + Jw[n:] @ (u[free] - u0[free])
                q = float(r[data_in] @ r[data_in] + prior @ prior)
                best = float(np.sqrt(np.mean((d[rows] - measured[rows]) ** 2)))
                if q <= q0 * (1 + 1e-9):
                    accepted = True
                    break
            step = 0.5 * step
        if best is not None and not accepted and math.isfinite(linear):
            # no fraction of the step lowered the left-in misfit: the last one tried (an
            # eighth) is nearly the fit to every experiment, which has seen the rows left
            # out, so its error understates theirs. The worse of it and the linearised
            # prediction stands. Measured (issue 48, the generator's power of the
            # pressure, rich design, seed 3): a lead exp(ω)·hinge(p) with two constants
            # undetermined checked to 0.3145 µm left out (0.3143 in-sample; linearised
            # 0.3214) and outranked the hidden power(p) alone (0.3213, every constant
            # determined, the same in-sample RMSE)
            best = max(best, linear)
        if best is not None:
            out[name] = best
    return (out if len(out) > 1 else {}), runs


def rmse_per_experiment(model: Model, r) -> dict:
    return {name: float(np.sqrt(np.mean(r[model.row_exp == i] ** 2)))
            for i, name in enumerate(model.exp_names) if np.any(model.row_exp == i)}


def where_it_fails(model: Model, r) -> dict:
    """Residual summaries (model - measured, µm): per experiment (with speed and clearance),
    per measurement time, and per 30° sector of the bushing."""
    st = model.study
    per_exp = []
    for i, e in enumerate(st.experiments):
        m = model.row_exp == i
        if not m.any():
            continue
        p = st.params(e)
        per_exp.append({"experiment": e.name, "speed_rpm": float(p.speed) * 60 / (2 * math.pi),
                        "clearance_mm": float(p.clearance) * 1e3, "rows": int(m.sum()),
                        "mean_um": float(np.mean(r[m])),
                        "rmse_um": float(np.sqrt(np.mean(r[m] ** 2)))})
    per_time = []
    for t in sorted(set(model.row_time.tolist())):
        m = model.row_time == t
        per_time.append({"at": t, "rows": int(m.sum()), "mean_um": float(np.mean(r[m])),
                         "rmse_um": float(np.sqrt(np.mean(r[m] ** 2)))})
    per_angle = []
    if not model.is_max.all():
        prof = ~model.is_max
        for a in range(0, 360, 30):
            m = prof & (model.row_x >= a) & (model.row_x < a + 30)
            if m.any():
                per_angle.append({"from_deg": a, "to_deg": a + 30, "rows": int(m.sum()),
                                  "mean_um": float(np.mean(r[m])),
                                  "rmse_um": float(np.sqrt(np.mean(r[m] ** 2)))})
    unit = "hours" if timed(st.config) else "revolutions"
    return {"per_experiment": per_exp, "per_time": per_time, "time_unit": unit,
            "per_angle": per_angle}


def derived(model: Model, fit: Fit) -> dict:
    """Identifiable combinations of poorly separated parameters, with delta-method errors:
    `running_in_excess_m` = a·S_r, the running-in's extra wear in metres of steady sliding
    (what depth data fix when they end long after S_r)."""
    out = {}
    ia, isr = model.index.get("running_in_amplitude"), model.index.get("running_in_distance_m")
    if (ia is None or isr is None or not fit.mask[ia] or not fit.mask[isr]
            or fit.values is None or fit.cov_u is None):
        return out
    a, sr = float(fit.values[ia]), float(fit.values[isr])
    free = np.flatnonzero(fit.mask)
    G = model.value_jacobian(fit.ev.u)[np.ix_(free, free)]
    fa, fs = list(free).index(ia), list(free).index(isr)
    g = sr * G[fa] + a * G[fs]  # d(a·S_r)/du over the free columns
    out["running_in_excess_m"] = (a * sr, float(np.sqrt(max(g @ fit.cov_u @ g, 0.0))))
    return out
