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
    for ei, name in enumerate(model.exp_names):
        rows = np.flatnonzero(model.row_exp == ei)
        if len(rows) == 0:
            continue
        keep = np.ones(len(rw), bool)
        keep[rows] = False
        step = lsq.gauss_newton(rw[keep], Jw[keep])[0]
        pred = noise_um * (rw[rows] + Jw[rows] @ step)
        out[name] = float(np.sqrt(np.mean(pred ** 2)))
    return out if len(out) > 1 else {}  # one experiment: nothing to leave out


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
