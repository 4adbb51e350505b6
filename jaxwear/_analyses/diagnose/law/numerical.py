"""The numerical error of the law's constants (issue 48: recovery): the law found is
checked against a finer resolution the way `calibrate` checks its base model
(`_inference.calibrate.correct_to_finer`), and its constants are corrected to it.

Why: the law is fitted at the study's numerics (its nodes and steps per cycle); their
discretisation error is in no standard error. Measured (docs/shape_validation.md,
"Numerical error of the law's constants"): on the rich design's hinge in the sliding
speed, jaxwear's model with the true law at the true parameters differs from the
generator's at 96 x 144 by 0.08 µm RMS at the study's 48 x 72, and the fit's Gauss-Newton
step on that difference moves the hinge's threshold by +1.8 and its exponent by −1.9
standard errors (what the diagnoses found: v0 0.049-0.050 m/s and a1 1.07-1.24 for 0.04
and 2); at 96 x 144 the two implementations agree to 0.003 µm and the step is 0.02 SE.
The error is the bore's nodes' (48 -> 96 moves it, 72 -> 144 steps does not).

At the law's answer û: one forward run of the law model at twice the nodes and steps per
cycle (half the update M, a quarter of the study's integration tolerance: `finer_rows`),
δ = rows_fine(û) − rows(û) (the search's runs integrate at `search.LAW_TOLERANCE` times
the study's tolerance: δ holds that error too, and the correction removes it with the
grid's); the answer's shift is one Gauss-Newton step of the law fit's own
Jacobian on the rows moved by δ, less the step on the rows as they are (what the fit's
stop left: `lsq.defect_step`): no new compilation at the study's level, one at the finer.
The step is checked by a forward run of the fit's own model with δ held: it must lower the
misfit to the finer level's rows, else it is halved (at most `HALVINGS` times; a step's
width, fitted in log space, overshot: the rich design's step in the load, seed 2, W_width
16.8 -> 108 N by the full step), and where no fraction lowers it the constants stand at the
study's numerics, `numerical.corrected` false and `why` said.
The constants reported are the corrected ones (the finer level's to first order, as
calibrate reports its corrected answer), and each constant's `numerical_error` is the size
of its full linear correction: the error left at the finer level is at most that where the
discretisation error at least halves when the nodes and steps double (first order:
equal; second order: a third of it). The sentence's ± folds it in with the standard
error (√(SE² + numerical²), JSON `uncertainty`).

Why one step and not a refit with δ held (calibrate's `correct_to_finer`): the cost (a
refit is ~10 Jacobian evaluations of the law model), and a hinge's constants lie along a
flat, curved valley where a refit stops wherever its statistical stop says (measured on
the hinge in the sliding speed at 96 x 144: started from the 48 x 72 answer the fit
stopped at v0 0.0482 m/s, a1 1.29; started from the truth at 0.0412, 1.90; χ² 0.5 apart),
so iterating moves the answer along the valley, not towards the finer level's minimum.
The linear step is the displacement of the fit's quadratic model's minimum by δ.

A deposit's strength D is per step of the cycle (`effects.law`): at twice the steps the
same law lays half of D per step, so the finer run holds D · steps/(2 steps).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from jaxwear._analyses.diagnose._fit import _log
from jaxwear._analyses.diagnose._model import Model
from jaxwear._inference import lsq
from jaxwear._physics.effects.law import constants

PER_STEP = ("law_deposit",)  # study keys of a quantity per step of the cycle
HALVINGS = 2  # times the correction may be halved before it is not made


def finer_model(lm: Model) -> Model:
    """`lm` (a law model of the search) at twice the nodes and steps per cycle, half the
    fixed update M and a quarter of the adaptive tolerance (as the shape's numerical error,
    `shape.design.numerical_error_rows`), its columns and starts the same."""
    st = lm.study
    cfg = st.config
    finer = dataclasses.replace(
        st, config=cfg.replace(nodes=2 * cfg.nodes, steps_per_rev=2 * cfg.steps_per_rev),
        revolutions_per_update=max(st.revolutions_per_update / 2, 1.0),
        wear_tolerance_um=st.wear_tolerance_um / 4)
    return Model(finer, keys=lm.keys, start=lm.start, candidates=[], contact=lm.contact)


def finer_rows(lm: Model, fm: Model, u) -> np.ndarray:
    """The rows [µm] of `fm` (`finer_model(lm)`) at the values `lm` has at u, a quantity
    per step of the cycle (`PER_STEP`) scaled to the finer cycle's steps (the same law)."""
    vals = lm.values(np.asarray(u, np.float64))
    ratio = lm.study.config.steps_per_rev / fm.study.config.steps_per_rev
    fv = np.array([vals[lm.index[n]] * (ratio if n in PER_STEP else 1.0) for n in fm.names])
    return fm.predict(fm.packing.u_of(fv))


@dataclasses.dataclass(frozen=True)
class Numerical:
    """The check of a law's constants against a finer resolution: the levels (nodes,
    steps per cycle), the linear correction's largest move in standard errors (of the
    fit's determined columns, u), the forward runs and their CPU seconds, the rows' change
    δ (RMS, µm), whether the constants were corrected, why not where they were not, and
    the fraction of the linear step applied."""

    level: tuple
    finer: tuple
    step_se: float = math.nan
    # the adaptive wear tolerances [µm] of the fit's runs (the search's, `LAW_TOLERANCE`
    # times the study's) and of the finer run (a quarter of the study's); None under the
    # paper's fixed-step integrator
    tolerance_um: float | None = None
    finer_tolerance_um: float | None = None
    forward_runs: int = 0
    cpu_s: float = 0.0
    rows_rms_um: float = math.nan
    corrected: bool = False
    why: str = ""
    fraction: float = 1.0  # of the linear step applied (halved where it overshot)
    # δ (rows,) [µm]: the finer level's rows less the fit's at the answer, and the
    # corrected answer's u (None where not corrected): the misfit the corrected constants
    # minimise to first order, for their profile (`law.profile`); not reported
    delta: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    u: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)

    def to_json(self) -> dict:
        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {"nodes": self.level[0], "steps_per_rev": self.level[1],
                "wear_tolerance_um": num(self.tolerance_um),
                "checked_against": {"nodes": self.finer[0], "steps_per_rev": self.finer[1],
                                    "wear_tolerance_um": num(self.finer_tolerance_um)},
                "step_se": num(self.step_se),
                "rows_rms_um": num(self.rows_rms_um), "corrected": self.corrected,
                "step_fraction": self.fraction,
                "forward_runs": self.forward_runs, "cpu_s": self.cpu_s,
                "why": self.why or None}


def correct_law(lf, noise_um: float, *, verbose: bool = False):
    """`lf` (a `LawFit` with its fit and law model) with its constants corrected to twice
    its nodes and steps per cycle and each constant's `numerical_error` (module docstring);
    `lf` as it is, with `numerical.why` said, where the check cannot be made. Call inside
    `effects.law.searching()`."""
    f, lm = lf.fit, lf.model
    c0 = time.process_time()
    cfg = lm.study.config if lm is not None else None
    level = (cfg.nodes, cfg.steps_per_rev) if cfg is not None else (0, 0)
    finer = (2 * level[0], 2 * level[1])
    tols = {"tolerance_um": None if lm is None else lm.wear_tolerance_um,
            "finer_tolerance_um": None}

    def out(**kw):
        info = Numerical(level, finer, cpu_s=time.process_time() - c0, **tols, **kw)
        return dataclasses.replace(lf, numerical=info)

    if f is None or lm is None or f.values is None or not f.ev.usable:
        return out(why="the law's fit has no usable answer to check")
    _log(verbose, f"  law {lf.law.label}: its constants checked against {finer[0]} x "
                  f"{finer[1]} (one forward run there, defect correction)")
    try:
        fm = finer_model(lm)
        tols["finer_tolerance_um"] = fm.wear_tolerance_um
        rows = finer_rows(lm, fm, f.ev.u)
    except Exception as e:  # noqa: BLE001 (the answer stands; the report says why)
        return out(why=f"the finer model could not be run ({type(e).__name__}: {e})")
    runs = 1
    if not np.all(np.isfinite(rows)):
        return out(forward_runs=runs, why="the finer model is not finite at the answer "
                                          "(worn through)")
    ev0 = f.ev
    lo, hi = lm.bounds_u()
    free = np.asarray(f.mask, bool)
    delta = rows - ev0.pred  # δ: the finer level's rows less the fit's, at the answer
    # the fit's own Jacobian: the step on the rows moved by δ, less the step its stop left
    step, cov, _ = lsq.defect_step(ev0.shifted(delta).point(), noise_um, lo, hi, free,
                                   relative_to=ev0.point())
    first = lsq.step_ratio(step, cov)
    se = {n: float(s) for n, s in zip(lm.names, f.stderr)}

    def at(t):
        u = np.array(ev0.u, np.float64)
        u[free] += t * step
        return u, constants(lf.law.with_values(dict(zip(lm.names, map(float,
                                                                    lm.values(u))))), se)

    # the numerical error: the constants' change by the full linear step
    u1, full = at(1.0)
    err = {k: abs(full[k][0] - v) for k, (v, _, _) in lf.constants.items() if k in full}
    if not all(math.isfinite(x) for x in err.values()):
        return out(forward_runs=runs, step_se=first,
                   why="the corrected constants are not finite (the answer stands)")

    # the step checked by forward runs of the fit's own (compiled) model with δ held: it
    # must lower the misfit to the finer level's rows, else it is halved (the linear step
    # of a strongly curved law, e.g. a step's width fitted in log space, overshoots)
    def misfit(u, pred):
        r = (pred + delta - lm.measured) / noise_um
        rp = ev0.r_prior + ev0.J_prior @ (u - ev0.u)
        return float(r @ r + rp @ rp)

    before = misfit(ev0.u, ev0.pred)
    t, law, new, why = 1.0, None, None, ""
    for _ in range(HALVINGS + 1):
        u, cs = (u1, full) if t == 1.0 else at(t)
        pred = lm.predict(u)
        runs += 1
        if np.all(np.isfinite(pred)) and misfit(u, pred) <= before:
            law = lf.law.with_values(dict(zip(lm.names, map(float, lm.values(u)))))
            new = cs
            break
        t *= 0.5
    else:
        why = (f"the correction did not lower the misfit to the finer level's rows (halved "
               f"{HALVINGS} times): the constants stand at the study's numerics, their "
               f"numerical error the linear step's")
    info = Numerical(level, finer, first, **tols, forward_runs=runs,
                     cpu_s=time.process_time() - c0,
                     rows_rms_um=float(np.sqrt(np.mean(delta ** 2))),
                     corrected=law is not None, why=why,
                     fraction=1.0 if law is None else t, delta=delta,
                     u=None if law is None else np.asarray(u, np.float64))
    _log(verbose, f"    δ {info.rows_rms_um:.3g} µm RMS; the answer moves by "
                  f"{first:.2g} standard errors"
                  + (f" (× {t:g})" if law is not None and t < 1 else "") + "; "
                  + (", ".join(f"{k} {lf.constants[k][0]:.4g} -> {new[k][0]:.4g}"
                               for k in err if err[k] > 0) if law is not None else why)
                  + f" ({runs} forward runs, {info.cpu_s:.1f} s CPU)")
    if law is None:
        return dataclasses.replace(lf, numerical_error=err, numerical=info)
    return dataclasses.replace(lf, law=law, constants=new, numerical_error=err,
                               numerical=info)

