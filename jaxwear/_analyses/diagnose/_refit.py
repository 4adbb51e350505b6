"""Refits of the leading candidates (single and pairs), the noise level, and the check
that the wear loop's derivatives are stable."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from jaxwear._analyses.diagnose._evidence import STRONG_LOG_BF, evidence
from jaxwear._analyses.diagnose._fit import Fit, _log, fit_masked
from jaxwear._analyses.diagnose._model import Model, objective
from jaxwear._analyses.diagnose._result import Candidate
from jaxwear._analyses.diagnose._screen import Screen, screen
from jaxwear._analyses.diagnose._stats import Tests, neighbour_differences, run_tests
from jaxwear._core.errors import InputError
from jaxwear._core.noise import stated_noise
from jaxwear._inference.evaluation import Evaluation
from jaxwear._study.data_checks import check_noise_measurable, check_wear_measured

# A refit's budget of evaluations (each a full run of every experiment with its Jacobian:
# seconds at the default numerics); it stops earlier when done (`jaxwear._inference.lsq.solve`), and
# one that runs out is reported as not converged.
REFIT_MAX_EVALUATIONS = 20


def _tests_for(model, fit, noise, nu, pairs, scores=None) -> Tests:
    t = run_tests(model, fit.ev.r, fit.k, noise, nu, pairs)
    if scores:
        best = min(scores, key=lambda s: s.p)
        t = replace(t, p_score=min(1.0, best.p * len(scores)), score_effect=best.effect)
    return t


def _start_for(model: Model, fit: Fit, scr: Screen | None) -> np.ndarray:
    u = fit.ev.u.copy()
    if scr is not None:
        for k, v in scr.start.items():
            u[model.index[k]] = model.u_of(k, v, u)
    return u


def _rescaled_to_data(mdl: Model, u0, kd: int | None):
    """The model at u0 and, where K_d is fitted (its column `kd`), at u0 with K_d scaled by
    the least-squares factor that brings the rows to the data (wear is linear in K_d to
    first order: one evaluation instead of the core's first steps). Returns (u, its
    evaluation)."""
    ev0 = mdl.evaluate(u0)
    if kd is not None and ev0.usable:
        d = ev0.pred
        a = float(d @ mdl.measured) / max(float(d @ d), 1e-300)
        if a > 0 and math.isfinite(a) and abs(math.log(a)) > 0.02:
            u0 = np.array(u0, np.float64)
            u0[kd] += math.log(a)
            ev0 = mdl.evaluate(u0)
    return u0, ev0


def _refit(by_contact, from_fit: Fit, groups, scr, noise, verbose, nu=math.inf) -> Fit:
    contact = "unsymmetric" if "unsymmetric" in groups else None
    mdl = by_contact(contact)
    mask = mdl.group_mask([g for g in groups if g != "unsymmetric"])
    label = "+".join(groups)
    _log(verbose, f"  refit with {label}")
    # Start at the screen's (capped) step with K_d rescaled to the data; where that is
    # worse than the fit we come from, start from that fit instead (strength off): a
    # refit can then only improve on it.
    u0 = _start_for(mdl, from_fit, scr)
    kd = mdl.index.get("K_d_per_Pa")
    u0, ev0 = _rescaled_to_data(mdl, u0, kd if kd is not None and mask[kd] else None)
    same = contact == from_fit.contact
    back = np.asarray(from_fit.ev.u, np.float64)
    if not ev0.usable or (same and objective(ev0, noise) > objective(from_fit.ev, noise)):
        if not ev0.usable and not np.array_equal(u0, back):  # a failed start is a value
            _log(verbose, f"    {label}: the screen's start is not usable ({ev0.why}); "
                          f"starting from the {from_fit.label} fit")
        if same:
            u0, ev0 = back.copy(), from_fit.ev
        elif not np.array_equal(u0, back):  # (the same point is not run twice)
            u0 = back.copy()
            ev0 = mdl.evaluate(u0)
    if not ev0.usable and not same:
        # The fit we come from can sit where the other contact cannot run: a symmetric
        # contact fitted to a worn bore drives clearances towards zero (measured: 1.9e-6 mm
        # against 0.05 nominal), where the unsymmetric contact's history did not finish in
        # minutes. Start from the study's values (u = 0: nominal clearances, strengths
        # off) with that fit's K_d, rescaled to the data.
        _log(verbose, f"    {label}: not usable at the {from_fit.label} fit's values "
                      f"({ev0.why}); starting from the study's values")
        u0 = np.zeros_like(back)
        if kd is not None:
            u0[kd] = back[kd]
        u0, ev0 = _rescaled_to_data(mdl, u0, kd if kd is not None and mask[kd] else None)
    f = fit_masked(mdl, mask, u0, noise_um=noise, noise_dof=nu, label=label,
                   groups=tuple(groups), ev0=ev0, max_evaluations=REFIT_MAX_EVALUATIONS,
                   verbose=verbose)
    f = replace(f, contact=contact)
    if not _derivatives_ok(mdl, f.ev):
        f = replace(f, status="unstable", message=f.message + (
            "; the wear loop's derivatives are unstable here (lower "
            + ("revolutions_per_update" if mdl.study.integrator == "paper"
               else "wear_tolerance_um") + "): this fit is not reliable"))
        _log(verbose, f"    {label}: unstable derivatives, not used")
    return f


# A candidate is refitted (beyond the leader) where its score is at least this fraction of
# the leader's: a refit costs ~10 model evaluations.
NEGLIGIBLE_SCORE = 0.1


def refit_leaders(live, max_refits: int, refit, alpha: float, comparable: float,
                  verbose=False) -> dict:
    """Refit the leading candidates by score; returns {effect: Fit} of those refitted.

    `live`: the feasible screens with a positive score, best first (`Screen`); `refit`:
    (effect, screen) -> (Fit, gain), gain the χ² [in σ²] the refit removed where it fits
    to noise level with very strong evidence, else None. The leader is always refitted;
    another where its own score test is significant (p < `alpha`) and its score not
    negligible next to the leader's (`NEGLIGIBLE_SCORE`), at most `max_refits` of them.
    While no refit is usable (`Fit.usable`: unstable derivatives, a model that does not
    run), the next candidates by score stand in for it, significant or not, but never
    negligible (a leader that could not be refitted says nothing about its rivals). A
    candidate is not refitted where one already fits to noise level and its score is
    below `comparable` times what that one removed: its refit could not tie (issue 10).
    """
    done, settled, tried = {}, None, 0
    for i, scr in enumerate(live):
        if tried >= max_refits:
            break
        wanted = i == 0 or (scr.p < alpha
                            and scr.score >= NEGLIGIBLE_SCORE * live[0].score)
        stand_in = (not wanted and scr.score >= NEGLIGIBLE_SCORE * live[0].score
                    and done and not any(f.usable for f in done.values()))
        if not (wanted or stand_in):
            continue
        tried += 1
        if settled is not None and scr.score < comparable * settled:
            _log(verbose, f"  {scr.effect}: not refitted (score {scr.score:.1f} < "
                          f"{comparable:g} x {settled:.1f} of a fit at noise level)")
            continue
        if stand_in:
            _log(verbose, f"  {scr.effect}: refitted in place of "
                          f"{', '.join(done)} (not usable)")
        f, gain = refit(scr.effect, scr)
        done[scr.effect] = f
        if gain is not None:
            settled = gain if settled is None else max(settled, gain)
    return done


def _derivative_ratio(model: Model, ev: Evaluation) -> float:
    """(d·∂d/∂ln K_d)/(d·d): about 1, since depth is nearly proportional to K_d."""
    k = model.index.get("K_d_per_Pa")
    if k is None or model.columns[k].group != "" or not model.columns[k].log:
        return 1.0
    d, j = ev.pred, ev.J[:, k]
    if not np.all(np.isfinite(j)):
        return math.nan
    return float(d @ j) / max(float(d @ d), 1e-300)


def _derivatives_ok(model: Model, ev: Evaluation) -> bool:
    return 0.2 < _derivative_ratio(model, ev) < 5.0


def _check_derivatives(model: Model, fit: Fit):
    """A Jacobian far from d depth/d ln K_d ≈ depth means the forward-mode derivative of the
    wear loop is unstable (too many revolutions per update for a fast-wearing joint): the
    fits would be meaningless, so stop and say what to change."""
    ratio = _derivative_ratio(model, fit.ev)
    if not 0.2 < ratio < 5.0:
        if model.study.integrator != "paper":
            raise InputError(
                f"{model.study.path}: the derivative of depth with respect to K_d is "
                f"{ratio:.3g} times the depth (expected about 1): lower "
                f"numerics.wear_tolerance_um ({model.study.wear_tolerance_um:g} µm)")
        raise InputError(
            f"{model.study.path}: numerics.revolutions_per_update = "
            f"{model.study.revolutions_per_update:g} is too large for this joint: the "
            f"derivative of depth with respect to K_d is {ratio:.3g} times the depth "
            f"(expected about 1), so the amplified wear updates are unstable for "
            f"derivatives; halve revolutions_per_update")


def _noise(model: Model, known: float | None = None):
    """Noise level [µm] and its degrees of freedom by the one rule (`_noise.stated_noise`):
    given, else the data's own neighbouring points. Where those are too few for the rule's
    `MIN_DOF` (a depth history of a handful of points), the diagnosis still needs one
    level to compare its candidates at: the data's estimate with its few degrees of
    freedom (the F tests pay for them), refused only when there is none."""

    if known is not None and not known > 0:
        raise InputError(f"noise_um must be > 0, got {known}")
    nz = stated_noise(model.ext.data, known)
    if nz.sigma_um is not None:
        return float(nz.sigma_um), float(nz.dof)
    e, _ = neighbour_differences(model, model.measured)
    if len(e) < MIN_TRIPLES:
        raise InputError(too_few_triples(model.study, len(e), model.n))
    if not nz.data_sigma_um > 0:  # equal depths: weights of 1/0 ended in LinAlgError
        check_wear_measured(model.study)
        check_noise_measurable(model.study)
    return float(nz.data_sigma_um), float(nz.data_dof)


MIN_TRIPLES = 2  # neighbour triples for a noise level (each one degree of freedom)


def too_few_triples(study, triples: int, rows: int) -> str:
    """The message when the data cannot give their own noise level."""
    return (f"{study.path}: {rows} data row(s) give {triples} neighbour triple(s) (a point "
            f"and its two neighbours in one profile scan or history, spaced within 2.5x the "
            f"median); estimating the noise level needs {MIN_TRIPLES}: 4 or more evenly "
            f"spaced points in one profile or history, or give the noise as [fit] noise_um")


def _second_stage(model, by_contact, best: Candidate, rest, noise, nu, pairs, max_refits,
                  verbose):
    """With the first effect in, look for a second one that brings the misfit to noise."""
    tries = [(s_.effect, s_) for s_ in rest if s_.feasible and s_.score > 0]
    tries = tries[:max(1, max_refits - 1)]
    if "unsymmetric" in model.candidates and best.effect != "unsymmetric":
        tries.append(("unsymmetric", None))
    results = []
    for name, scr in tries:
        f = _refit(by_contact, best.fit, [best.effect, name], scr, noise, verbose, nu)
        mdl = by_contact(f.contact)
        t = _tests_for(mdl, f, noise, nu, pairs, screen(mdl, f, noise, nu))
        results.append((evidence(model, f, best.fit, noise), f, t))
    results = [x for x in results if x[1].usable]
    results.sort(key=lambda x: -x[0])
    if results and results[0][0] > STRONG_LOG_BF and not results[0][2].systematic:
        return results[0][1], results[0][2]
    return None
