"""From the shape to a law (issue 43 item 2): a small grammar of physical laws over the
state variables (`effects.law`), pre-screened on the shape's linearised system, the best
few fitted through the wear loop by the one least-squares core, ranked by the error on
left-out experiments and BIC.

1. **Pre-screen** (no model run). For every single-term law of the grammar (each kind
   along each variable, each form, on a grid of its constants) its Φ(z) is projected on
   the shape's B-splines of that variable and form (least squares over the wear-weighted
   range of z, `ShapeVariable.at_coordinate`); the shape's columns (whitened, the fit's own
   parameters and the numerical error projected off: `ShapeResult.linear`) then give its
   linearised change of the rows, and one least-squares amplitude (≥ 0) the χ² it removes.
   For a factor that is first order in A (1 + AΦ ≈ exp(AΦ), the shape's factor) and the
   level of Φ is K_d's (the shape's factor columns sum to zero). Per variable and form the
   best law is kept.
2. **Starts by a forward run** (`screened_starts`, `_law_start`; the shape's answer a
   factor): the pre-screen's best law along the shape's best variable at a few fractions
   of its first-order strength, and, where the shape carries both the pressure and the speed,
   a few laws of the derived p·v (the PV factor: `effects.law.DERIVED`; the shape has no
   columns along it), each run forward once with K_d scaled to the data; the best start
   of each is fitted through the loop (p·v's first where its start fits better), then
   the product of the single law with the shape's other carrier (else the pre-screen's
   best other variable), started from the single law as fitted (`from_fitted`).
   Otherwise (a deposit): the best single law of the pre-screen along the shape's
   variable, its product with the best other variable of its form (`candidates`) and
   the pre-screen's own best where it differs.
3. **Through the loop.** Each candidate fitted with the fit's own parameters (K_d, the
   clearances) by `fit_masked` (the one least-squares core, `jaxwear._inference.lsq`), on
   one compiled model for all of them (the law's structure is held data: `effects.law`).
   Each gets its RMSE, its leave-one-experiment-out RMSE (`loo`), its BIC evidence
   against the base fit, diagnose's combined test of its residuals and the constants its
   data do not determine (`undetermined`); once one passes that test (the misfit left is
   noise), or a law of two variables reaches the shape's refitted RMSE (`as_shape`), the
   rest are not fitted.
   Then, where the history shows or no law of the present states reaches the noise,
   laws with memory: a per-node damage or film the cycle drives (`_law_memory`).
4. **Ranking.** By the left-out-experiment RMSE (a law whose strength is undetermined as
   if `LAW_WORSE` higher); candidates within `LOO_TIE` of the best are ranked by BIC (the
   evidence, which pays for constants). The best, with its constants in their units and
   standard errors (delta method through the packing), is `LawResult.best`.
5. **Against the shape.** Where the best law's RMSE is more than `LAW_WORSE` above the
   shape's refitted correction's, no law of the grammar explains the misfit as well as
   the shape: the sentence, the JSON (`worse_than_shape`) and `law.py` say so, and it is
   not called the law found.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from jaxwear._analyses.diagnose._evidence import evidence, loo
from jaxwear._analyses.diagnose._fit import Fit, _log, fit_masked
from jaxwear._analyses.diagnose._law_memory import after, memory_candidates
from jaxwear._analyses.diagnose._law_result import (  # noqa: F401 (the search's types)
    LAW_WORSE,
    LawFit,
    LawResult,
    _fmt,
    law_sentence,
)
from jaxwear._analyses.diagnose._law_start import (
    derived_variables,
    forward_rmse,
    joint_states,
    pv_laws,
)
from jaxwear._analyses.diagnose._model import Model
from jaxwear._analyses.diagnose._refit import _tests_for
from jaxwear._analyses.diagnose._stats import neighbour_pairs
from jaxwear._physics.effects.law import (
    DEPOSIT_LAW_VARIABLES,
    DERIVED,
    LAW_EFFECT,
    LAW_VARIABLES,
    SYMBOLS,
    LawSpec,
    Term,
    constants,
    law_phi_numpy,
    searching,
)

# candidates fitted through the wear loop: the best single law and the product of two
# (measured on the generator's pv_tanh law: a third, the best single law of another
# variable, cost a third of the search's 247 s and ranked last, left-out RMSE 28.7 µm)
THROUGH_LOOP = 2
LAW_EVALUATIONS = 10  # budget of each through-loop fit (model evaluations)
LOO_TIE = 0.01  # left-out RMSEs within 1 % are a tie, broken by BIC
# a candidate's fit stops once 3 evaluations together lower the data's ½χ² by less than
# this (`lsq.solve`'s `settled`): it is ranked by its misfit, and a Δχ² of 2 moves no
# BIC comparison (ln 20 ≈ 3). Measured on the running_pressure study: both laws ran to
# their budget of 12 at 0.3334 -> 0.3333 µm, 12 and 24 s.
SETTLED_CHI2 = 1.0
GRID = 121  # points of z over its range for projecting Φ on the splines
# the continuous constants of `LAW_SEARCH`: columns of the one compiled law model (held
# where a candidate does not use them), so that every candidate shares its program
LAW_KEYS = ("law_gain", "law_deposit", "law_a_1", "law_x0_1", "law_w_1", "law_b_1",
            "law_a_2", "law_x0_2", "law_w_2", "law_b_2")
THRESHOLD_QUANTILES = (0.1, 0.25, 0.4, 0.5, 0.6, 0.75, 0.9)
# the constants that make a term 1 everywhere (a product's second term at its start)
NEUTRAL = {"power": {"a": 0.0}, "exp": {"b": 0.0}}


# -- 1. the pre-screen on the shape's linearised system ---------------------------------------

def reference(var) -> float:
    """z_s > 0 of a variable: its wear-weighted median over the range met, else its upper
    end (a state that is 0 over most of the wear, e.g. the worn depth early on)."""
    med = float(var.at_coordinate(0.5))
    hi = float(max(abs(var.lo), abs(var.hi)))
    return med if med > 1e-6 * max(hi, 1e-300) else max(hi, 1e-12)


def single_laws(var, form: str, peak: float | None = None) -> list[LawSpec]:
    """The grammar's one-term laws along `var` (a `ShapeVariable`) on a grid of their
    constants spanning the range met in the data. `peak`: where the shape's own
    correction of this variable and form is largest (`VariableShape.peak_at`): a
    deposit's reference (below)."""
    ref = reference(var)
    hi = float(max(abs(var.lo), abs(var.hi)))
    if (form == "deposit" and peak is not None and math.isfinite(peak)
            and peak > 1e-6 * max(hi, 1e-300)):
        # a deposit is made where its events are (the reversals' turn rates, thousands of
        # deg/s), not where the Archard wear is (the wear-weighted median, 63 deg/s on the
        # impact study): referred to the latter, D and a power's exponent were one
        # direction (D ~ 2.5e-12 ± 4.6e-12 for (ω/63)^4) and its fit crawled through its
        # whole budget at 0.81 standard errors a step
        ref = float(peak)
    lo, hi = var.lo / ref, var.hi / ref
    span = max(hi - lo, 1e-12)
    x0s = [float(var.at_coordinate(q)) / ref for q in THRESHOLD_QUANTILES]
    out = []
    for a in (-1.0, -0.5, 0.5, 1.0, 2.0, 4.0):
        out.append(Term("power", var.name, ref, a=a))
    for x0 in x0s:
        for a in (1.0, 2.0):
            out.append(Term("hinge", var.name, ref, a=a, x0=x0))
        for w in (0.02, 0.1):
            out.append(Term("step", var.name, ref, x0=x0, w=w * span))
    for bs in (-4.0, -1.0, 1.0, 4.0):
        out.append(Term("exp", var.name, ref, b=bs / span))
    return [LawSpec(form, (t,)) for t in out]


def _response(law: LawSpec, block):
    """The linearised change of the whitened, projected rows per unit strength of `law`
    (a one-term law along the block's variable), or None where Φ is flat."""
    A, _, Z, _, var = block
    t = np.linspace(0.0, 1.0, GRID)
    z = var.at_coordinate(t)
    B = np.asarray(var.basis(np.asarray(z)))
    phi = law_phi_numpy(law, {var.name: z})
    if not np.all(np.isfinite(phi)) or np.ptp(phi) <= 1e-12 * max(np.abs(phi).max(), 1e-300):
        return None
    c = np.linalg.lstsq(B, phi, rcond=None)[0]
    # the shape's columns of this block: Z spans the sum-zero coefficients for a factor
    # (a level is K_d's), all of them for a deposit
    return A @ np.linalg.lstsq(Z, c, rcond=None)[0]


def prescreen(linear: dict, forms=("factor", "deposit")) -> list[tuple[float, LawSpec]]:
    """(χ² removed [σ²], the law at its least-squares strength ≥ 0) of every one-term law
    of the grammar, best first (module docstring, step 1)."""
    blocks, rho = linear["blocks"], linear["rho"]
    peaks = linear.get("peaks", {})
    out = []
    for form in forms:
        names = LAW_VARIABLES if form == "factor" else DEPOSIT_LAW_VARIABLES
        for name in names:
            label = name if form == "factor" else f"deposit:{name}"
            if label not in blocks:
                continue
            for law in single_laws(blocks[label][4], form, peaks.get(label)):
                resp = _response(law, blocks[label])
                if resp is None:
                    continue
                rr = float(resp @ resp)
                amp = float(resp @ rho) / max(rr, 1e-300)
                if not amp > 0:
                    continue
                out.append((amp * float(resp @ rho), dataclasses.replace(law, strength=amp)))
    out.sort(key=lambda x: -x[0])
    return out


def candidates(screened, n: int = THROUGH_LOOP, prefer=None) -> list[tuple[float, LawSpec]]:
    """The laws fitted through the loop, in this order: the best single law along the
    shape's best variable and form (`prefer` = (form, variable): the shape's choice, made
    with its correction refitted through the loop) or, without one, the pre-screen's best;
    the product of that law with the best law of another variable of its form (the first's
    strength as its start: it starts near the first law's size); and, where the
    pre-screen's best single law is along another variable than the first, that law too. A
    law of two variables at once is the next thing to try when the best single one leaves
    a misfit (issue 43: the shape's additive fit cannot see it). Why the shape's variable
    first: the pre-screen is first order in the law's strength (1 + AΦ ≈ exp(AΦ)); on the
    generator's PV step (a doubling of the rate) its best was a hinge in the load that
    reached 0.384 µm through the loop where the shape along the sliding speed reached
    0.317."""
    best_per = {}
    for drop, law in screened:
        key = (law.form, law.terms[0].variable)
        if key not in best_per:
            best_per[key] = (drop, law)
    ranked = sorted(best_per.values(), key=lambda x: -x[0])
    if not ranked:
        return []
    first = best_per.get(tuple(prefer)) if prefer is not None else None
    first = first or ranked[0]
    out = [first]
    form, var = first[1].form, first[1].terms[0].variable
    others = [x for x in ranked if x[1].form == form and x[1].terms[0].variable != var]
    if others:
        l1, l2 = first[1], others[0][1]
        out.append((math.nan, LawSpec(form, (l1.terms[0], l2.terms[0]), l1.strength)))
    if ranked[0] is not first:
        out.append(ranked[0])
        n += 1  # the pre-screen's own choice besides the shape's
    return out[:n]


# -- 3. through the loop -----------------------------------------------------------------------

def law_model(model: Model, fit: Fit, law: LawSpec) -> Model:
    """The model of `fit` (its study, numerics and rows' correction) with `law` switched
    on: the law's structure (kinds, variables, references, form) as held study
    parameters, its constants as columns (`LAW_KEYS`), started at `law`'s values and the
    fit's own parameters at its answer. Every law gives the same program (one
    compilation for the search). Call inside `effects.law.searching()`."""
    st = model.study
    vals = law.values()
    # a law with memory is its own effect and columns (`_law_memory`)
    effects, cols = getattr(law, "model_effects", (LAW_EFFECT,)), getattr(law, "columns",
                                                                          LAW_KEYS)
    held = {k: v for k, v in vals.items() if k not in cols}
    study = dataclasses.replace(
        st, config=st.config.replace(effects=tuple(st.config.effects) + tuple(effects)),
        parameters={**st.parameters, **held})
    start = {n: float(v) for n, v, m in zip(model.names, fit.values, model.base_mask) if m}
    start.update({k: vals[k] for k in cols})
    return Model(study, keys=list(model.keys) + list(cols), start=start, candidates=[],
                 defect_um=model.ext.defect)


def fit_law(model: Model, fit: Fit, law: LawSpec, noise_um: float, nu: float, *,
            max_evaluations: int = LAW_EVALUATIONS, verbose: bool = False):
    """`law` fitted through the wear loop with the fit's own parameters (its free columns)
    by the one least-squares core: (the law with its fitted constants, its `Fit`, the law
    model)."""
    lm = law_model(model, fit, law)
    free_base = {model.names[i] for i in np.flatnonzero(fit.mask)}
    keys = set(law.free_keys())
    mask = np.array([n in free_base or n in keys for n in lm.names])
    f = fit_masked(lm, mask, np.zeros(len(lm.names)), noise_um=noise_um, noise_dof=nu,
                   label=f"law {law.label}", groups=(LAW_EFFECT,),
                   max_evaluations=max_evaluations, verbose=verbose, rescales=1,
                   settled=SETTLED_CHI2)
    values = {n: float(v) for n, v in zip(lm.names, f.values)} if f.values is not None else {}
    return law.with_values(values), f, lm


def search(model: Model, fit: Fit, linear: dict, noise_um: float, nu: float, *,
           n: int = THROUGH_LOOP, forms=("factor", "deposit"), prefer=None,
           correction: dict | None = None, shape_rmse_um: float | None = None,
           max_evaluations: int = LAW_EVALUATIONS, verbose: bool = False) -> LawResult:
    """The law search on the misfit left by `fit` (module docstring); `linear`: the shape
    analysis's linearised system (`ShapeResult.linear`) on top of the same fit; `forms`:
    those the search tries; `prefer`: (form, variable) the shape found best (`candidates`);
    `correction` (`ShapeResult.correction`) and `shape_rmse_um`: the shape's correction
    refitted through the loop and its RMSE: the factor laws then start from their fit to
    that correction (`_law_start`), and a best law more than `LAW_WORSE` above that RMSE
    is reported as worse than the shape (`LawResult.worse_than_shape`)."""
    t0, c0 = time.perf_counter(), time.process_time()
    screened = prescreen(linear, forms)
    todo = [(d, law, "prescreen") for d, law in candidates(screened, n, prefer)]
    starts = screened_starts(model, fit, linear, screened, prefer, correction, verbose)
    if starts:
        # the pre-screen's own choice of another variable is not fitted: the shape's
        # correction through the loop already weighed every variable
        todo = starts
    loo_before = loo(model, fit, noise_um)
    lb = _rms(loo_before)
    _log(verbose, f"  law search: {len(screened)} one-term laws pre-screened; through the "
                  f"loop: " + "; ".join(f"{law.label} (from the {src})"
                                        for _, law, src in todo))
    fitted = []
    pairs = neighbour_pairs(model)
    with searching():
        # then the laws with memory, where the history shows or no law of the present
        # states reaches the noise (`_law_memory`)
        for drop, law, src in after(todo, lambda: memory_candidates(
                model, fit, prefer, correction, law_model, fitted, noise_um,
                verbose=verbose, skip=any(f.at_noise for f in fitted),
                as_shape=as_shape(fitted, shape_rmse_um))):
            if fitted and any(f.at_noise for f in fitted):
                # a law already fits to noise by diagnose's own tests: the others can at
                # most tie with it (each fit costs ~10 runs of the wear loop)
                _log(verbose, f"    {law.label}: not fitted (a law already fits to noise)")
                continue
            if fitted and as_shape(fitted, shape_rmse_um) and src != "memory":
                # a law of two variables already fits as well as the shape's correction
                # (refitted through the loop): measured on the PV step, the two laws
                # fitted after the step in p·v (0.316 µm, the shape 0.317) reached 0.400
                # and 0.360, and the search took 56 s of CPU with them, 17.5 s without
                _log(verbose, f"    {law.label}: not fitted (a law of two variables already "
                              f"fits as well as the shape)")
                continue
            if src == "prescreen":  # a product: from the single law as fitted
                law = from_fitted(law, fitted, linear)
            found, f, lm = fit_law(model, fit, law, noise_um, nu,
                                   max_evaluations=max_evaluations, verbose=verbose)
            if f.status == "unusable" or f.values is None:
                _log(verbose, f"    {law.label}: {f.status} ({f.message})")
                continue
            se = {nm: float(s) for nm, s in zip(lm.names, f.stderr)}
            lo_each = loo(lm, f, noise_um)
            lo = _rms(lo_each)
            ev = evidence(model, f, fit, noise_um)
            tests = _tests_for(lm, f, noise_um, nu, pairs)
            fitted.append(LawFit(found, f.rmse, lo, ev, f.status, f.evaluations,
                                 constants(found, se), drop, not tests.systematic,
                                 tests.p_min, undetermined(found, se), src,
                                 residual_um=np.asarray(f.ev.r),
                                 loo_per_experiment_um=lo_each))
            _log(verbose, f"    {found.label}: RMSE {f.rmse:.4f} µm, left-out "
                          f"{_fmt(lo)} µm, evidence {ev:.1f} ({f.status}, "
                          f"{f.evaluations} evaluations)")
    ranked = rank(fitted)
    best = ranked[0] if ranked else None
    # CPU seconds of every thread beside the wall: on a shared machine the wall depends
    # on the others' load, the CPU time much less
    res = LawResult(best, tuple(ranked), len(screened), float(noise_um), fit.rmse, lb,
                    time.perf_counter() - t0, extra={"cpu_s": time.process_time() - c0},
                    shape_rmse_um=shape_rmse_um)
    return dataclasses.replace(res, sentence=law_sentence(res))


def warm(model: Model, fit: Fit, linear: dict, prefer=None) -> None:
    """The law model's program traced and compiled (one for every law of the search) by
    one evaluation of the first candidate's start, ahead of `search`: diagnose runs it in
    the background while the shape's correction is refitted through the loop (tracing
    and compiling the law model took 10-17 s of the search's 21-73 s on the impact
    study). Failures are left to the search, which meets them again and reports them."""
    try:
        todo = candidates(prescreen(linear), THROUGH_LOOP, prefer)
        if todo:
            with searching():
                lm = law_model(model, fit, todo[0][1])
                lm.evaluate(np.zeros(len(lm.names)))
    except Exception:  # noqa: BLE001 (the search reports it where it matters)
        return


SCREEN_STRENGTHS = (1.0, 0.5, 0.25, 0.1)  # of the pre-screen's (first-order) strength


def screened_starts(model: Model, fit: Fit, linear: dict, screened, prefer, correction,
                    verbose=False):
    """The factor laws to fit through the loop, their starts chosen by one forward run
    each (`_law_start`): [(χ² drop, law, source)]: the pre-screen's best law along the
    shape's best variable at the strength (`SCREEN_STRENGTHS` of the pre-screen's) whose
    forward run fits best; then its product with the best law of the shape's other
    carrier (else the pre-screen's best other variable; started from the single law as
    fitted, `from_fitted`); and, where the shape carries both p and v, a law of the
    derived p·v (`_law_start.pv_laws`) first where its forward run beats the single
    law's. [] where
    the shape's answer is not a factor along a variable of the pre-screen."""
    if prefer is None or prefer[0] != "factor":
        return []
    first = prefer[1]
    lead = next(((d, law) for d, law in screened if law.form == "factor"
                 and law.terms[0].variable == first), None)
    if lead is None:
        return []
    drop, law1 = lead
    trials = [dataclasses.replace(law1, strength=law1.strength * f) for f in SCREEN_STRENGTHS]
    carriers = [v["name"] for v in (correction or {}).get("variables", ())
                if v["name"] != first and v.get("form", "factor") == "factor"]
    pv = []
    blocks = linear.get("blocks", {})
    # p·v where the shape's correction carries both p and v (a law of their product is
    # then what its sum of one-variable parts stands in for); measured with either alone:
    # on pv_tanh (p alone) the step in p·v was fitted first and lost (0.333 µm against
    # the power of p's 0.316) at 12 evaluations, and on running_pressure its 10 forward
    # runs chose nothing
    if {"pressure_MPa", "sliding_speed_m_per_s"} <= ({first} | set(carriers)) and \
            {"pressure_MPa", "sliding_speed_m_per_s"} <= set(blocks):
        Z, w = joint_states(model, fit)
        for var in derived_variables(Z, w).values():
            pv += pv_laws(var)
    with searching():
        rm = [(forward_rmse(law_model(model, fit, law), model.measured), law)
              for law in trials + pv]
    r1, start1 = min(rm[:len(trials)], key=lambda x: x[0])
    out = [(drop, start1, "forward")]
    second = next((v for v in carriers if v in LAW_VARIABLES), None)
    others = [(d, law) for d, law in screened if law.form == "factor"
              and law.terms[0].variable not in (first,)]
    other = (next(((d, law) for d, law in others if law.terms[0].variable == second), None)
             or (others[0] if others else None))
    if other is not None:
        out.append((math.nan, LawSpec("factor", (start1.terms[0], other[1].terms[0]),
                                      start1.strength), "prescreen"))
    msg = f"{start1.label} x{start1.strength:.3g} {r1:.4f} µm"
    if pv:
        r2, start2 = min(rm[len(trials):], key=lambda x: x[0])
        msg += f"; {start2.label} x{start2.strength:.3g} {r2:.4f} µm"
        if r2 < r1:
            out.insert(0, (math.nan, start2, "forward"))
    _log(verbose, f"  law search: starts by one forward run each ({len(rm)}), RMSE with K_d "
                  f"scaled: {msg}")
    return out


def as_shape(fitted, shape_rmse_um) -> bool:
    """A law of two variables in `fitted` (a product, or the derived p·v) within
    `LOO_TIE` of the shape's refitted RMSE or below it: the laws still to fit (one
    variable's, and the product of one with another) have nothing the shape shows left to
    add. A law of one variable at the shape's RMSE is not enough: on the generator's
    running-in at high pressure the step in p alone reached the shape's 0.333 µm and the
    product with the sliding distance, fitted after it, 0.316."""
    def two(law):
        names = set()
        for t in law.terms:
            names |= set(DERIVED[t.variable][1]) if t.variable in DERIVED else {t.variable}
        return len(names) >= 2

    return bool(shape_rmse_um is not None and math.isfinite(shape_rmse_um) and any(
        f.rmse_um <= shape_rmse_um * (1 + LOO_TIE) and two(f.law) for f in fitted))


def undetermined(law: LawSpec, se: dict) -> tuple:
    """Names (`constants`) of the constants the data do not determine at the answer: the
    strength with its standard error above its value, an exponent or a threshold not
    known to within 1 (the exponent's unit; the threshold's in units of the reference
    z_s), a width or an exponential's rate with its standard error above its value; a
    standard error that is not finite. Why: a law whose constants trade off against each
    other (the PV step's load hinge: A = 26.64 ± 2.5e+03, W0 = 218 ± 713 N, a1 = 1.98 ±
    80) fits a misfit without measuring anything; the report says so."""
    if getattr(law, "memory", False):
        return law.undetermined(se)
    names = list(constants(law))
    out = []

    def bad(key, limit):
        s = se.get(key, math.nan)
        return not (s is not None and math.isfinite(s) and s <= limit)

    if bad(law.strength_key, abs(law.strength)):
        out.append(names[0])
    for k, t in enumerate(law.terms, 1):
        sym = SYMBOLS[t.variable]
        if t.kind in ("power", "hinge") and bad(f"law_a_{k}", 1.0):
            out.append(f"a{k}")
        if t.kind in ("hinge", "step") and bad(f"law_x0_{k}", 1.0):
            out.append(f"{sym}0")
        if t.kind == "step" and bad(f"law_w_{k}", abs(t.w)):
            out.append(f"{sym}_width")
        if t.kind == "exp" and bad(f"law_b_{k}", abs(t.b)):
            out.append(f"{sym}_e")
    return tuple(out)


def from_fitted(law: LawSpec, fitted, linear: dict) -> LawSpec:
    """A product's start from the single law fitted before it along its first variable:
    that term as fitted, the strength divided by the second term's wear-weighted mean
    over its range (so that the product starts near the single law's answer, which it
    nests, instead of at the pre-screen's linearised constants: on the generator's
    pv_tanh law the product from the pre-screen ran out of its budget at an RMSE above the
    single law's)."""
    if len(law.terms) < 2:
        return law
    first = next((f.law for f in fitted if len(f.law.terms) == 1 and f.law.form == law.form
                  and f.law.terms[0].variable == law.terms[0].variable), None)
    if first is None:
        return law
    t2 = law.terms[1]
    if t2.kind in NEUTRAL:
        # a second term that is 1 at its start (a power of exponent 0, an exponential of
        # rate 0): the product starts exactly at the single law's answer, which it nests.
        # The mean over the range below is not where the first law acts: on the impact
        # study a power of the turn rate (ω/63 deg/s)^4 started the product at 17.9 µm
        # RMS (the single law: 0.308) and it stalled there
        return LawSpec(law.form, (first.terms[0], dataclasses.replace(t2, **NEUTRAL[t2.kind])),
                       first.strength)
    label = t2.variable if law.form == "factor" else f"deposit:{t2.variable}"
    block = linear.get("blocks", {}).get(label)
    mean = 1.0
    if block is not None:
        var = block[4]
        z = var.at_coordinate(np.linspace(0.0, 1.0, GRID))
        phi = law_phi_numpy(LawSpec(law.form, (t2,)), {t2.variable: z})
        mean = float(np.mean(phi)) if np.all(np.isfinite(phi)) else 1.0
    return LawSpec(law.form, (first.terms[0], t2), first.strength / max(mean, 1e-3))


def rank(fitted) -> list:
    """Best first: by the left-out-experiment RMSE, ties within `LOO_TIE` (relative) by
    the BIC evidence (module docstring, step 4). A law whose strength the data do not
    determine (`undetermined`) ranks as if its left-out RMSE were `LAW_WORSE` higher: it
    must beat a determined law by more than that margin to lead."""
    if not fitted:
        return []

    def key(f):
        k = f.loo_rmse_um if f.loo_rmse_um is not None else f.rmse_um
        strength = "D" if f.law.form == "deposit" else "A"
        return k * (1 + LAW_WORSE) if strength in f.undetermined else k

    best = min(key(f) for f in fitted)
    tied = [f for f in fitted if key(f) <= best * (1 + LOO_TIE)]
    rest = sorted([f for f in fitted if key(f) > best * (1 + LOO_TIE)], key=key)
    return sorted(tied, key=lambda f: -f.evidence) + rest


def _rms(d: dict):
    return float(np.sqrt(np.mean(np.square(list(d.values()))))) if d else None


