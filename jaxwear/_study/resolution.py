"""Spatial resolution chosen by the error, the way the wear integrator chooses its steps
(design.md §6).

A study whose `[numerics]` gives neither `nodes` nor `steps_per_rev` runs at the coarsest
level of `LEVELS` whose discretisation error is small enough, checked against the next
finer level:
- forward runs (`simulate`): every experiment's peak depth within `PEAK_RTOL` (0.1 %) of the
  finer level's; the reported error estimate is the largest peak difference [µm];
- fits: one Gauss-Newton step with the finer level's rows (a forward run) and the fit's
  own Jacobian moves no fitted parameter by more than `FIT_SE_TOL` (0.1) of its standard
  error, checked **at the answer**; a fit that fails it is corrected to the finer level by
  defect correction (its residual difference held fixed while the coarse Jacobian steps,
  `_calibrate.correct_to_finer`), so a fit compiles one Jacobian, at the coarsest level.

Why these levels: measured on the rig (276 r/min, 10 000 rev) and the boom (25 h), the peak
depth at 90 × 72 is 0.02 µm and 0.35 µm from 360 × 360, ten times below the data's noise,
at a twentieth of the node-steps (issue 19's table). Given values are used as given.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from jaxwear._physics.adaptive import stable_amplification
from jaxwear._study.budget import estimate_work, max_work
from jaxwear._study.study import Study

LEVELS = ((90, 72), (180, 144), (360, 360))  # (nodes, steps_per_rev), coarse to fine
PEAK_RTOL = 1e-3
FIT_SE_TOL = 0.1


def at_level(study: Study, level: tuple[int, int]) -> Study:
    """`study` at (nodes, steps_per_rev); it keeps its `auto_resolution` mark."""
    return replace(study, config=study.config.replace(nodes=level[0], steps_per_rev=level[1]))


def given(study: Study) -> dict:
    """The report of a study whose numerics are used as given."""
    return {"auto": False, "nodes": study.config.nodes,
            "steps_per_rev": study.config.steps_per_rev}


def report(level, finer, *, kind: str, value, ok: bool) -> dict:
    """The `resolution` block of every output: the level used, the level it was checked
    against and the check's figure (peak difference [µm] or Gauss-Newton step [SE])."""
    out = {"auto": True, "nodes": level[0], "steps_per_rev": level[1],
           "checked_against": None if finer is None else {"nodes": finer[0],
                                                          "steps_per_rev": finer[1]},
           "within_tolerance": bool(ok)}
    if kind == "peak":
        out["error_estimate_um"] = None if value is None else float(value)
        out["tolerance"] = f"{PEAK_RTOL:g} of the peak depth"
    else:
        out["refinement_step_standard_errors"] = None if value is None else float(value)
        out["tolerance"] = f"{FIT_SE_TOL:g} standard errors"
    return out


def correction_report(jacobian, corrected_to, corrections: int, step) -> dict:
    """The defect correction's part of a fit's `resolution` block: the level the Jacobian
    was at, the level whose residuals the answer is corrected to (None: none needed),
    how many corrected refits it took and the last correction's step [SE]."""
    return {"jacobian": {"nodes": jacobian[0], "steps_per_rev": jacobian[1]},
            "corrected_to": None if corrected_to is None else {
                "nodes": corrected_to[0], "steps_per_rev": corrected_to[1]},
            "defect_corrections": int(corrections),
            "correction_step_standard_errors": None if step is None else float(step)}


def for_forward(study: Study, peaks: Callable[[Study], np.ndarray],
                log: Callable[[str], None] | None = None) -> tuple[Study, dict]:
    """The coarsest level whose peak depths `peaks(study)` (experiments,) [µm] agree with the
    next finer level's within `PEAK_RTOL`; (study at that level, report)."""
    if not study.auto_resolution:
        return study, given(study)
    prev = None
    for level in LEVELS:
        st = at_level(study, level)
        p = np.asarray(peaks(st), np.float64)
        if prev is not None:
            err = float(np.max(np.abs(p - prev[1])))
            ok = err <= PEAK_RTOL * max(float(np.max(np.abs(p))), 1e-30)
            if log:
                log(f"resolution {prev[0][0]} x {prev[0][1]}: peak within {err:.3g} µm of "
                    f"{level[0]} x {level[1]}" + ("" if ok else ", refining"))
            if ok:
                return at_level(study, prev[0]), report(prev[0], level, kind="peak",
                                                         value=err, ok=True)
        prev = (level, p)
    # the finest level: its error is at most the last difference seen
    return at_level(study, LEVELS[-1]), report(LEVELS[-1], None, kind="peak", value=err,
                                              ok=False)


def at_stable_update(study: Study, values: dict, *, done: str, at: str = "the fitted K_d"
                     ) -> tuple[Study, str | None]:
    """`study` at a fixed step M its explicit wear update is stable at, and the flag that
    says so; the one rule of every verb that refits a paper-integrator study (`predict`,
    `diagnose`).

    `values`: parameter values by study key (fitted ones; `K_d_per_Pa` is the one the
    estimate depends on: `stable_amplification`, smallest over the experiments); `done`:
    what was done at the new M, and `at`, which K_d that is, for the flag ("fitted and
    forecast", "the fitted K_d"). Where the study's
    `revolutions_per_update` exceeds the estimate there, the depth may look smooth while
    its derivatives blow up at some points (measured on the boom at M = 10, estimate ~5:
    predict's bands, diagnose's refits), so M becomes half the estimate (rounded down, at
    least 1): a margin of 2, as the estimate is linear in K_d and a refit moves K_d.
    Returns (study, None) where nothing changes: the adaptive integrator, M within the
    estimate, or K_d not among `values`; (study, a flag that says so) where the stable M
    would make one run exceed the work limit (`_budget.max_work`, JAXWEAR_MAX_WORK): M is
    then kept, and the caller tells a switch from that by `returned is not study`.
    """
    if study.integrator != "paper" or "K_d_per_Pa" not in values:
        return study, None
    kd = float(values["K_d_per_Pa"])
    limit = min(stable_amplification(study.params(e).with_values({"K_d_per_Pa": kd}),
                                     study.config) for e in study.experiments)
    M = study.revolutions_per_update
    if not M > limit:
        return study, None
    m_new = float(max(1, math.floor(limit / 2)))
    stable = replace(study, revolutions_per_update=m_new)
    est = estimate_work(stable)
    if est is not None and not est.node_steps <= max_work():
        return study, (
            f"[numerics] revolutions_per_update = {M:g} exceeds the stable amplification "
            f"~{limit:.3g} at {at}; kept, as one run at the stable {m_new:g} would exceed "
            f"the work limit ({est.node_steps:.3g} contact node-steps, JAXWEAR_MAX_WORK "
            f"{max_work():.3g}): derivatives there may be unstable")
    return stable, (
        f"[numerics] revolutions_per_update = {M:g} exceeds the stable amplification "
        f"~{limit:.3g} at {at}; {done} with {m_new:g} instead")


def amplification_warnings(study: Study, params=None) -> list[str]:
    """A line for each experiment whose M exceeds the explicit-update stability estimate
    (paper integrator only; `params`: per-experiment `Params` to check, e.g. fitted ones)."""
    out = []
    if study.integrator != "paper":
        return out
    M = study.revolutions_per_update
    for i, exp in enumerate(study.experiments):
        p = study.params(exp) if params is None else params[i]
        limit = stable_amplification(p, study.config)
        if M > limit:
            out.append(f"warning: {exp.name}: revolutions_per_update = {M:g} exceeds the "
                       f"stability estimate {limit:.3g} of the explicit wear update for this "
                       f"joint (stiff layer or large K_d); the profile may oscillate. Use "
                       f"[numerics] revolutions_per_update <= {max(1, int(limit)):d} and "
                       f"compare with a smaller value.")
    return out
