"""The shape of the missing wear: a smooth correction of the local wear along the state
variables, learned from the misfit through the wear loop (design.md §7, `--shape`).

Two forms (`effects.shape`): a **factor** exp(g(z)) of the local Archard rate, and a
**deposit** e(z) ≥ 0 per step where the pin presses (extra wear not tied to sliding), each
g_v or e_v on `SIZE` cubic B-splines along one state variable z. All coefficients zero is
the fit's model exactly, so one forward-mode Jacobian of the model with every variable's
coefficients in both forms switched on (one compiled function, one evaluation) linearises
them all. On the host, in the whitened system the fits see:

1. **What is not physics.** The fit's own free parameters (K_d, clearances, the effect's
   strengths) and the model's own numerical error are nuisance columns projected off the
   misfit (Frisch-Waugh): the numerical error is the difference of the rows at twice the
   nodes and steps (and half the fixed update, or a quarter of the tolerance) at the fit's
   answer, one forward run, so a discretisation misfit at any numerics a user sets is not
   read as missing wear. Noise correlated along a scan (a profilometer's stylus, surface
   roughness) is prewhitened (AR(1), its coefficient read from the lag-1 correlation of
   the data's second differences, where smooth misfit cancels).
2. **Alone.** Per variable and form, a penalised fit (roughness λ Σ (second difference)²,
   λ by generalised cross-validation); T = ΔRSS/σ² with its null simulated (`DRAWS`
   draws, λ re-chosen in each, σ̂ with its ν dof); significant when p < α / (variables ×
   forms). Its share of the misfit, net of the noise it would take up, is not clipped.
3. **Together.** Per form, one additive fit over all its variables (one GCV λ): the share
   each variable adds to the others' fit (unique) says which carry the misfit together;
   a variable significant alone whose unique share is not is a stand-in for the carrier
   its fitted correction resembles most (speed and load turn rate both follow crank speed
   on the paper's rig).
4. **The answer.** `best` is the significant variable that explains most (design.md §7; ties
   within ln 20 of AIC are named as alternatives), `form` its form. The correction of that
   form over the variables that carry the misfit is refitted through the wear loop with
   its true Jacobian by the least-squares core (penalty and, for a factor, zero sum as
   prior rows; a deposit ≥ 0 by bounds); its RMSE is the real model's.
5. **When and where** (`shape.map`): that correction's extra wear over the cycle and over
   the bore, with bands, the load's reversals and peak marked, and a sentence.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.stats import chi2

from jaxwear._analyses.diagnose._fit import Fit, _log
from jaxwear._analyses.diagnose._model import Model
from jaxwear._analyses.diagnose._stats import ALPHA, neighbour_differences
from jaxwear._analyses.diagnose.shape import linear as lin
from jaxwear._analyses.diagnose.shape.choice import rank_alternatives
from jaxwear._analyses.diagnose.shape.design import (
    JACOBIAN_TOLERANCE,
    JOINT_DRAWS,
    LEVEL,
    SIZE,
    Design,
    numerical_error_rows,
    pair_tensor,
    prepare_design,
    tensor_columns,
)
from jaxwear._analyses.diagnose.shape.interaction import (
    interaction_test,
    leading_pair,
    tensor_system,
)
from jaxwear._analyses.diagnose.shape.linear import DRAWS
from jaxwear._analyses.diagnose.shape.map import when_where
from jaxwear._analyses.diagnose.shape.refit import (
    REFIT_TOLERANCE,
    Ahead,
    _carriers,
    _correction,
    _map_u,
    _refit,
    refit_basis,
    refit_model,
    refit_width,
)
from jaxwear._analyses.diagnose.shape.result import ShapeResult, VariableShape
from jaxwear._analyses.diagnose.shape.text import describe, next_test, next_test_sentence
from jaxwear._core.background import Background
from jaxwear._physics.effects.shape import FORMS

# The refit's Jacobian program is made this much wider where that computes the surface's
# columns in one run instead of two (each run costs its primal and every tangent of the
# width, padding included): on the generator's fatigue study 25 columns against the
# refit's 23 tangents, where a second run cost ~0.8 s and 2 tangents more in each of
# the refits' ~11 evaluations ~0.3 s.
SURFACE_WIDTH = 1.25

# -- the range of each variable met in the data ---------------------------------------------


def _band_of_peak(z, g_hat, G, periodic, level):
    peak = float(z[int(np.argmax(g_hat))])
    draws = z[np.argmax(G, axis=-1)]
    q = ((1 - level) / 2, (1 + level) / 2)
    if periodic:
        d = np.mod(draws - peak + 180.0, 360.0) - 180.0
        lo, hi = np.quantile(d, q)
        return peak, float(np.mod(peak + lo, 360.0)), float(np.mod(peak + hi, 360.0))
    lo, hi = np.quantile(draws, q)
    return peak, float(lo), float(hi)


# -- the model's own numerical error ----------------------------------------------------------


# -- the analysis ---------------------------------------------------------------------------

def shape_analysis(model: Model, fit: Fit, noise_um: float, nu: float, *, after: str = "base",
                   seed: int = 0, draws: int = DRAWS, size: int = SIZE,
                   verbose: bool = False, numerical: bool = True,
                   numerical_um: np.ndarray | None = None,
                   design: Design | None = None, defer: bool = False,
                   refit_groups=None, refit_ahead: bool = False,
                   numerical_ahead=None) -> ShapeResult:
    """The shape of the misfit left by `fit` (of `model`) along every state variable, in
    both forms (module docstring). `noise_um` σ [µm] with `nu` degrees of freedom
    (diagnose's noise level). `numerical`: count the model's numerical error: the rows of
    a finer level minus the fit's rows at its answer, `numerical_um` (rows,) [µm] where the
    caller has them (calibrate's resolution check ran that forward run at this answer),
    else one forward run at twice the nodes and steps (`numerical_ahead`: that run made in
    the background, `design.NumericalAhead`, taken where it was made for this fit).

    `design` (`prepare_design`, or an earlier analysis's `ShapeResult.design`): the basis,
    the states met in the data and the correction's columns, computed at `fit`'s answer
    (e.g. in the background) or at another fit's on the same model (the base fit's, for
    the analysis on top of an effect found): then this analysis runs no model of its own
    until its refit. Its columns are linearised at that other answer: an effect found
    moves them by its rate factor, which costs the test power only, never its level (the
    misfit tested and the fit's own columns projected off are this fit's); the numerical
    error's rows, also from there, enter one column per experiment, each with its own
    scale, as the effect rescales each experiment's wear.

    `defer`: where a variable is significant, return before the refit through the loop
    (status "pending"; `ShapeResult.finished()` runs it), so that the caller can do other
    work meanwhile (draw the figures the refit does not change).

    `refit_groups`: the candidate groups of the refit's model (default: the fit's own);
    those the fit does not have are held at off, where the model is the fit's exactly
    (nesting). Why: diagnose's two analyses (after the base fit and after the effect
    found) then refit through one compiled program where they refit the same carriers:
    the model with the correction and its when/where map compiled once, not twice (on the
    fatigue study 2 x (15-21 s + 18-34 s) of compilation for the same answer).

    `refit_ahead`: once the carriers and the surface are decided, build the refit's model
    and make its first evaluation in the background (`shape.refit.Ahead`), while the
    caller goes on. Off for an analysis whose refit shares another's program (two
    compilations of one program at once would not be one)."""

    # this thread's evaluations, and those of the jobs it waits on (`_counted`): the
    # process-wide count would take in whatever runs beside it (the refit's first
    # evaluation made ahead, `shape.refit.Ahead`)
    evals0 = Model.own_evaluations()
    waited = []  # evaluations of the background jobs this analysis waited on
    own_groups = [g for g in model.candidates if g in fit.groups]
    held = set(refit_groups or ()) | set(own_groups)
    refit_with = [g for g in model.candidates if g in held]
    spent = 0  # evaluations of a design computed before this call, not yet counted
    if design is None:
        design = prepare_design(model, fit, groups=own_groups, size=size, verbose=verbose)
    else:
        spent = design.evaluations
    if design.study is not model.study or not set(own_groups) <= set(design.groups):
        raise ValueError("a shape design is reused on another model")
    # linearised at this fit's answer, or at another one (an earlier fit's)
    reused = not np.array_equal(design.u, _map_u(model, fit.ev.u, design.smodel))
    if spent and not reused:
        # (in the background while the verdict ran under `--shape`; without it, by
        # `diagnose` once the verdict asked for the shape: "before" is true of both)
        _log(verbose, f"  shape of the missing wear after {after}: its columns computed "
                      f"before it (the design's one Jacobian)")
    load, exp_name, deepest = design.load, design.exp_name, design.deepest
    smodel, jmodel, ev_j = design.smodel, design.jmodel, design.ev_j
    basis = smodel.ext.cfg.shape
    if reused:
        _log(verbose, f"  shape of the missing wear after {after}: {len(basis.variables)} "
                      f"variable-forms x {size} B-splines (the columns of the analysis "
                      f"before, no model run)")
    u = _map_u(model, fit.ev.u, smodel)
    ev = fit.ev
    sigma = max(float(noise_um), 1e-12)
    free_base = [smodel.index[model.names[i]] for i in np.flatnonzero(fit.mask)]
    n = smodel.n
    # whitened system: data rows /σ, prior rows in SD units; the fit's own columns from
    # the fit, the correction's from the Jacobian model
    J = np.zeros((n, len(smodel.names)))
    Jp = np.zeros((len(ev.r_prior), len(smodel.names)))
    for i, name in enumerate(model.names):
        if name in smodel.index:
            J[:, smodel.index[name]] = ev.J[:, i]
            Jp[:, smodel.index[name]] = ev.J_prior[:, i]
    for name in basis.keys():
        J[:, smodel.index[name]] = ev_j.J[:, jmodel.index[name]]
    Jw = np.vstack([J / sigma, Jp])
    rho_full = -np.concatenate([ev.r / sigma, ev.r_prior])
    d = None
    elsewhere = False  # d taken at another answer (the design's): a column per experiment
    if numerical:
        if reused and design.numerical_um is not None:
            d, elsewhere = design.numerical_um, True
        elif numerical_um is not None:
            d = np.asarray(numerical_um, np.float64)
            _log(verbose, "    the model's numerical error: the rows of the resolution "
                          "check at this answer (no run of its own)")
        else:
            made = (numerical_ahead.take(model, fit, own_groups)
                    if numerical_ahead is not None else None)
            if made is not None:
                (d, nodes_steps), evals = made
                waited.append(evals)
                _log(verbose, f"    the model's numerical error: one run at {nodes_steps}, "
                              f"made beside the design")
            else:
                d = numerical_error_rows(model, fit, verbose, candidates=own_groups)
        if d is not None and not np.all(np.isfinite(d)):
            d = None
    # correlated noise along the scans: prewhiten (AR(1) read from second differences of
    # the residuals of the finer level, data - (prediction + numerical error)). Not of the
    # data: a worn profile's kinks (the contact's edges) do not cancel in second
    # differences and read as correlated noise (φ 0.95 on white noise of a load-history
    # study; the prewhitened misfit then was the discretisation's kinks, and a factor of
    # the worn depth "explained" them at p 5e-5)
    left = ev.r if d is None else ev.r + d
    e, mids = neighbour_differences(model, left)
    phi, z_phi = lin.ar1_coefficient(e, mids)
    Jw = lin.prewhiten(Jw, model.series, phi, n)
    rho_full = lin.prewhiten(rho_full[:, None], model.series, phi, n)[:, 0]
    nuisance = [Jw[:, free_base]]
    num_info = {"counted": False, "ar1_coefficient": phi, "ar1_z": z_phi}
    if d is not None:
        exps = np.asarray(model.row_exp)
        parts = ([np.where(exps == k, d, 0.0) for k in np.unique(exps)] if elsewhere
                 else [d])
        for part in parts:
            if np.any(part):
                nuisance.append(lin.prewhiten(np.concatenate(
                    [part / sigma, np.zeros(len(ev.r_prior))])[:, None],
                    model.series, phi, n))
        num_info.update(counted=True, rms_um=float(np.sqrt(np.mean(d ** 2))),
                        max_um=float(np.max(np.abs(d))),
                        columns=len(nuisance) - 1)
    Xb = np.hstack(nuisance)
    Qb = np.linalg.qr(Xb)[0] if Xb.shape[1] else np.zeros((len(rho_full), 0))
    proj = lambda X: X - Qb @ (Qb.T @ X)  # noqa: E731
    rho = proj(rho_full[:, None])[:, 0]
    n_res = n - Qb.shape[1]
    rss0 = float(rho @ rho)
    excess = rss0 - n_res  # the misfit beyond the noise, in σ² units
    rng = np.random.default_rng(seed)
    Zs = lin.sum_zero(size)
    blocks = {}
    results = []
    for var in basis.variables:
        cols = [smodel.index[k] for k in var.keys()]
        Z = Zs if var.form == "factor" else np.eye(size)
        A = proj(Jw[:, cols] @ Z)
        S = Z.T @ var.roughness() @ Z
        blocks[var.label] = (A, S, Z, cols, var)
        pf = lin.penalised_fit(A, S, rho, n_res, nu, rng, draws)
        c = Z @ pf.a
        if var.form == "deposit":
            c = lin.nonnegative_fit(A, S, rho, pf.lam)
        jcols = [jmodel.index[k] for k in var.keys()]
        results.append(_variable_result(var, pf, c, Z, excess, rss0, rng, ev_j, deepest,
                                        jcols))
        v = results[-1]
        _log(verbose, f"    {v.label}: explains {v.explained_fraction:.0%} of the misfit, dof "
                      f"{v.dof:.1f}, p {v.p_value:.1e}, peak at {v.peak_at:.4g} {v.unit}")
    alpha_each = ALPHA / len(results)
    results = [replace(v, significant=v.p_value < alpha_each) for v in results]
    # the leading pair's surface (`shape.interaction`) is of the form of the variable that
    # explains most alone; its columns (one Jacobian) are computed in the background once
    # the refit's carriers are chosen (the pair is the form's joint fit's)
    sig0 = [v for v in results if v.significant]
    lead_form = max(sig0, key=lambda v: v.explained_fraction).form if sig0 else None
    forms = {}
    for form in FORMS:
        results, forms[form] = _joint(form, results, blocks, rho, rss0, excess, n_res, nu, rng,
                                      alpha_each, verbose)
    rmse_before = float(np.sqrt(np.mean(ev.r ** 2)))
    sig = [v for v in results if v.significant]
    best = form = inter = None
    alternatives, carriers, confounded = [], (), []
    ahead = None  # the refit's model and first evaluation, made in the background
    basis_r = width = None  # the refit model's basis and Jacobian width
    if sig:
        top, alternatives = choose_best(results)
        # among variables the data explain alike: unique shares, then left-out experiments
        alt_v = [next(v for v in results if v.label == a) for a in alternatives]
        top, alt_v, confounded, loo = rank_alternatives(
            top, alt_v, blocks, rho, model.row_exp, n, alpha_each)
        alternatives = [v.label for v in alt_v]
        if len(loo) > 1:
            _log(verbose, "    left-out experiments' error (σ² units): " + ", ".join(
                f"{k} {x:.1f}" for k, x in sorted(loo.items(), key=lambda kv: kv[1]))
                + (f"; confounded: {', '.join(confounded)}" if confounded else ""))
        best, form = top.name, top.form
        carriers = _carriers(results, top)
        # the leading pair's surface (`shape.interaction`), where the refit's form is the
        # form of the variable that explains most alone; on top of an effect found only
        # the base analysis's pair (its columns reused): a pair of its own would compile
        # another Jacobian
        pair = leading_pair(results, form) if form == lead_form else None
        tensor = pair_tensor(design, *pair, form) if pair is not None else None
        if tensor is not None and reused and tensor.label not in design.tensors:
            tensor = None
        # one model, one compiled Jacobian program, for the surface's columns and the
        # refit whatever the surface's test decides (`refit.refit_basis`): on the
        # generator's fatigue study (48 x 72, 2 cores) the two programs were ~6 s of CPU
        # each, one after the other on the diagnosis's critical path
        key = (tuple(carriers), form)
        if tensor is None and key in design.refit_bases:
            # an earlier analysis's refit of these carriers (its surface off here)
            basis_r, width = design.refit_bases[key]
        else:
            basis_r = refit_basis(blocks, carriers, form, tensor)
            cm_r = refit_model(smodel, refit_with, basis_r)
            width = refit_width(cm_r, basis_r, carriers, form)
            if tensor is not None and tensor.size <= SURFACE_WIDTH * width:
                # the surface's columns in one run where that costs the refit's runs little
                width = max(width, tensor.size)
            design.refit_bases.setdefault(key, (basis_r, width))
        if tensor is not None:
            # at the design's tolerance (a traced value: the same program)
            tm = cm_r.with_wear_tolerance(JACOBIAN_TOLERANCE / REFIT_TOLERANCE
                                          ).with_jacobian_columns(
                [cm_r.index[k] for k in tensor.keys()], width)
            surface = (tensor, Background(_counted, tensor_columns, design, tensor,
                                          own_groups, verbose, tm))
            inter = _interaction(surface, sigma, ev, model, phi, n, proj, blocks, carriers,
                                 form, rho, n_res, nu, rng, draws, excess, rss0, alpha_each,
                                 verbose, waited)
            if inter.carried:
                carriers = tuple(carriers) + tuple(x for x in inter.variables
                                                   if x not in carriers)
    design_out = replace(design, evaluations=0,
                         numerical_um=design.numerical_um if elsewhere else d)

    def result(results, rmse_after, status, correction, ww, evaluations):
        command = next_test(model.study.path, best, form, results, alternatives,
                            confounded)
        sentence = (describe(best, form, results, load, after, alternatives, carriers, ww,
                             confounded=confounded, interaction=inter)
                    + next_test_sentence(command))
        return ShapeResult(after, best, form, tuple(results), ALPHA, sigma, rmse_before,
                           rmse_after, evaluations, status, sentence, load,
                           np.arange(jmodel.ext.cfg.nodes) * 360.0 / jmodel.ext.cfg.nodes,
                           exp_name, tuple(alternatives), forms, tuple(carriers), correction,
                           ww, num_info, design=design_out, next_test=command,
                           linear={"blocks": blocks, "rho": rho, "Qb": Qb, "phi": phi,
                                   "sigma": sigma, "n_res": n_res, "nu": nu,
                                   "excess": excess, "rss0": rss0, "n": n,
                                   "n_prior": len(ev.r_prior), "groups": own_groups,
                                   "peaks": {v.label: v.peak_at for v in results}},
                           interaction=inter, confounded=tuple(confounded))

    def finish(warm=None) -> ShapeResult:
        """The refit through the loop and the when/where map (the costly part); `warm`:
        an earlier refit's (model, u) whose correction it starts from
        (`shape.refit._warm_start`)."""
        # this thread's (the refit runs in it): another analysis may run beside it
        e0 = Model.own_evaluations()
        surf = inter.block if inter is not None and inter.carried else None
        rmse_after, status, corr_model, u_fit, cov, snaps, resid, message = _refit(
            smodel, refit_with, ev, u, free_base, blocks, carriers, form, rho, n_res, sigma,
            Jw, rho_full, verbose, deepest, surface=surf, ahead=ahead, warm=warm,
            basis=basis_r, width=width)
        # the first evaluation made ahead, in another thread, where the refit took it
        e0 -= ahead.evaluations if ahead is not None and ahead.used else 0
        if not math.isfinite(rmse_after):
            # no start of the refit could be evaluated: no RMSE, no correction, and why
            # (the law search then says its check against the shape was not made)
            _log(verbose, f"    the shape's refit gave no RMSE: {message}")
            return replace(result(results, None, status, {}, None,
                                  linear.evaluations + Model.own_evaluations() - e0),
                           refit_message=message,
                           refit_tolerance_um=corr_model.wear_tolerance_um)
        correction = _correction(corr_model, u_fit, carriers, form, carried=surf is not None)
        done = [replace(v, refit_rmse_um=rmse_after) if v.name in carriers
                and v.form == form else v for v in results]
        ww = when_where(corr_model, u_fit, cov, exp_name, deepest, LEVEL, snaps=snaps)
        return replace(result(done, rmse_after, status, correction, ww,
                              linear.evaluations + Model.own_evaluations() - e0),
                       residual_um=resid, refit_message=message,
                       refit_at=(corr_model, np.asarray(u_fit, np.float64)),
                       refit_tolerance_um=corr_model.wear_tolerance_um)

    if sig and refit_ahead:
        ahead = Ahead(smodel, refit_with, u, free_base, blocks, carriers, form, rho, n_res,
                      Jw, rho_full, surface=inter.block if inter is not None
                      and inter.carried else None, basis=basis_r, width=width)
    linear = result(results, None, "none", {}, None,
                    Model.own_evaluations() - evals0 + sum(waited) + spent)
    if not sig:
        return linear
    linear = replace(linear, status="pending", pending=finish)
    return linear if defer else linear.finished()


def choose_best(results):
    """(the best variable-form, the labels of its alternatives): the significant one that
    explains most of the misfit (design.md §7), equal shares broken by the lower AIC; the
    others whose AIC is within ln 20 of it (or lower) are alternatives the data cannot tell
    from it. A ranking by the data, never by the order the variables come in."""
    sig = [v for v in results if v.significant]
    top = max(sig, key=lambda v: (v.explained_fraction, -v.aic))
    alternatives = [f"{v.name}" if v.form == "factor" else f"deposit:{v.name}"
                    for v in sorted(sig, key=lambda v: v.aic)
                    if v is not top and v.aic - top.aic < 2.0 * math.log(20.0)]
    return top, alternatives


def _interaction(surface, sigma, ev, model, phi, n, proj, blocks, carriers, form, rho, n_res,
                 nu, rng, draws, excess, rss0, alpha, verbose, waited):
    """The leading pair's surface tested on top of the additive fit of the pair and the
    form's carriers (`shape.interaction`); its columns' evaluations added to `waited`."""
    tensor, job = surface
    cols, evals = job.result()
    waited.append(evals)
    A, S, Z, X = tensor_system(tensor, cols, sigma, len(ev.r_prior), model.series, phi, n,
                               proj)
    names = list(dict.fromkeys(list(carriers) + [tensor.a.name, tensor.b.name]))
    additive = [blocks[nm if form == "factor" else f"deposit:{nm}"][0] for nm in names]
    inter = interaction_test(tensor, A, S, Z, X, additive, rho, n_res, nu, rng, draws, excess,
                             rss0, alpha, phi)
    _log(verbose, f"    {form}, the surface over {tensor.a.name} x {tensor.b.name} on top of "
                  f"the additive fit: explains {inter.explained_fraction:.0%} more, dof "
                  f"{inter.dof:.1f}, p {inter.p_value:.1e}"
                  + (" (significant: the refit carries it)" if inter.carried else
                     f" (significant, but it would lower the refit's RMSE by "
                     f"{inter.rmse_gain_linearised:.1%}, linearised: the refit does not "
                     f"carry it)"
                     if inter.significant else ""))
    return inter


def _counted(fn, *args):
    """(fn(*args), the model evaluations it made in this thread): a background job's
    count, taken where the analysis waits on it."""
    e0 = Model.own_evaluations()
    out = fn(*args)
    return out, Model.own_evaluations() - e0


def _variable_result(var, pf, c, Z, excess, rss0, rng, ev, deepest, cols) -> VariableShape:
    zg = (np.linspace(0.0, 360.0, 181)[:-1] if var.periodic else
          var.at_coordinate(np.linspace(0.0, 1.0, 181)))
    Bg = var.basis(zg, xp=np)  # on the host (as the law screen's): no eager program
    g = Bg @ c
    w, V = np.linalg.eigh(0.5 * (pf.cov + pf.cov.T))
    L = V * np.sqrt(np.clip(w, 0.0, None))
    C = (pf.a + rng.standard_normal((4000, len(pf.a))) @ L.T) @ Z.T
    G = C @ Bg.T
    q = ((1 - LEVEL) / 2, (1 + LEVEL) / 2)
    g_lo, g_hi = np.quantile(G, q, axis=0)
    peak, lo, hi = _band_of_peak(zg, g, G, var.periodic, LEVEL)
    J_snap = None if ev.J_snaps is None else ev.J_snaps[deepest, -1][:, cols]
    extra = (J_snap @ c) if J_snap is not None else np.zeros(0)
    return VariableShape(
        var.name, var.unit, var.form, lin.explained(pf.drop, pf.dof, excess, rss0), math.nan,
        pf.dof, pf.p, False, peak, lo, hi, pf.lam, pf.drop, rss0 - pf.drop + 2.0 * pf.dof,
        zg, g, g_lo, g_hi, c, extra, (float(zg[0]), float(zg[-1])))


def _joint(form, results, blocks, rho, rss0, excess, n_res, nu, rng, alpha_each, verbose):
    """The form's joint fit: its share, p-value, and each variable's unique share; who
    carries the misfit and who stands in for whom."""

    mine = [v for v in results if v.form == form]
    fit, unique = lin.joint_fit([blocks[v.label][:2] for v in mine], rho, n_res, nu, rng,
                                JOINT_DRAWS)
    fitted = {}
    for v in mine:
        A = blocks[v.label][0]
        Z = blocks[v.label][2]
        fitted[v.name] = A @ np.linalg.lstsq(Z, v.coef, rcond=None)[0]
    out = {}
    for v, d in zip(mine, unique):
        p_u = float(chi2.sf(max(d, 0.0), max(v.dof, 1.0)))
        out[v.name] = replace(v, unique_fraction=lin.explained(d, 0.0, excess, rss0),
                              carries=bool(v.significant and p_u < alpha_each),
                              unique_p_value=p_u)
    carriers = [k for k, v in out.items() if v.carries]
    if not carriers:
        # none adds significantly to the others: the significant ones stand in for each
        # other (the experiments vary them together); the one explaining most leads
        sig = [v for v in out.values() if v.significant]
        if sig:
            lead = max(sig, key=lambda v: v.explained_fraction)
            carriers = [lead.name]
            out[lead.name] = replace(lead, carries=True)
    for k, v in out.items():
        if v.significant and not v.carries and k not in carriers:
            f = fitted[k]
            cos = {w: abs(float(f @ fitted[w])) / max(
                float(np.linalg.norm(f) * np.linalg.norm(fitted[w])), 1e-300)
                for w in carriers}
            out[k] = replace(v, stand_in_for=max(cos, key=cos.get))
    summary = {"explained_fraction": lin.explained(fit.drop, fit.dof, excess, rss0),
               "dof": fit.dof, "p_value": fit.p, "carriers": carriers,
               "stand_ins": {k: v.stand_in_for for k, v in out.items() if v.stand_in_for}}
    _log(verbose, f"    {form}, all variables together: explains "
                  f"{summary['explained_fraction']:.0%}, p {fit.p:.1e}; carried by "
                  f"{', '.join(carriers) or 'none'}")
    return [out.get(v.name, v) if v.form == form else v for v in results], summary


