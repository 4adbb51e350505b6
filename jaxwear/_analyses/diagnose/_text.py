"""The verdict in words."""

from __future__ import annotations

import math

import numpy as np

from jaxwear._analyses.diagnose._evidence import derived, where_it_fails
from jaxwear._analyses.diagnose._fit import Fit
from jaxwear._analyses.diagnose._result import Diagnosis, _mean_sq
from jaxwear._analyses.diagnose._stats import ALPHA
from jaxwear._inference.calibrate import unit_of
from jaxwear._physics.effects import STRUCTURAL_CANDIDATES, get_effect


def _fmt_value(v, se, unit=""):
    """`v ± se unit`, rounded to the standard error's second significant digit."""
    if se is None or not math.isfinite(se) or se <= 0:
        return f"{v:.3g}{unit}"
    if se >= abs(v) or abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.3g} ± {se:.2g}{unit}"
    digits = max(0, 1 - int(math.floor(math.log10(se))))
    return f"{v:.{digits}f} ± {se:.{digits}f}{unit}"


def _strength_text(diag: Diagnosis, fit: Fit, effect: str) -> str:

    if effect == "unsymmetric":
        return "no extra parameter"
    m = diag.model
    parts = []
    for i in np.flatnonzero(fit.mask):
        c = m.columns[i]
        if c.group == effect:
            u = unit_of(m.names[i])
            parts.append(f"{m.names[i]} = " + _fmt_value(
                float(fit.values[i]), float(fit.stderr[i]), "" if u == "-" else f" {u}"))
    if effect == "running_in":
        for k, (v, se) in derived(m, fit).items():
            parts.append(f"identifiable product a·S_r = {_fmt_value(v, se, ' m')}")
    return ", ".join(parts)


def _signature_text(diag: Diagnosis) -> str:
    """Where the base residuals (model - measured) were largest, in words."""
    w = where_it_fails(diag.model, diag.base.ev.r)
    unit = "rev" if w["time_unit"] == "revolutions" else "h"
    bits = []
    if len(w["per_time"]) > 1:
        t = max(w["per_time"], key=lambda d: abs(d["mean_um"]))
        side = "shallower" if t["mean_um"] < 0 else "deeper"
        bits.append(f"at {t['at']:g} {unit} the base model predicts {side} wear than measured "
                    f"by {abs(t['mean_um']):.2f} µm on average")
    if len(w["per_experiment"]) > 1:
        e = max(w["per_experiment"], key=lambda d: d["rmse_um"])
        bits.append(f"the worst experiment is {e['experiment']} ({e['speed_rpm']:.0f} r/min, "
                    f"{e['clearance_mm']:.3g} mm; RMSE {e['rmse_um']:.2f} µm)")
    if w["per_angle"]:
        a = max(w["per_angle"], key=lambda d: abs(d["mean_um"]))
        bits.append(f"over angle the largest mean residual is {a['mean_um']:+.2f} µm at "
                    f"{a['from_deg']}-{a['to_deg']}°")
    return "; ".join(bits)


def _describe(effect: str) -> str:
    if effect in STRUCTURAL_CANDIDATES:
        return STRUCTURAL_CANDIDATES[effect].signature
    return get_effect(effect).signature


def summarize_verdict(diag: Diagnosis) -> str:
    """The verdict paragraph: first what the diagnosis changed in the numerics (its
    `flags`), ending with the fits that did not converge (a refit out of its budget or
    stalled still counts with what it reached: its evidence is a lower bound) and those
    not usable at all (not compared)."""
    text = " ".join([f"{f}." for f in diag.flags] + [_verdict_text(diag)])
    # (where no refit came to an answer, the verdict's own words list the refits)
    fits = [("the base fit", diag.base)] + ([] if _undetermined(diag) else [
        (f"the refit with {c.effect}", c.fit) for c in diag.candidates if c.fit is not None])
    late = [f"{name} ({f.status}, {f.evaluations} evaluations)" for name, f in fits
            if not f.converged and f.usable]
    if late:
        text += (f" Not converged: {'; '.join(late)}; each is used with the misfit it "
                 f"reached, so its evidence is a lower bound.")
    if diag.failed and not _undetermined(diag):
        text += f" {_failed_text(diag)}; not compared, so the verdict is not certain."
    return text


def _undetermined(diag: Diagnosis) -> bool:
    """True where no refit came to an answer (the screen's promise unresolved, or every
    refit unusable where the base model's tests reject): the verdict says so and no more."""
    usable = [c for c in diag.candidates if c.fit is not None and c.fit.usable]
    return (diag.status == "unexplained" and not diag.partial
            and (diag.unresolved or (bool(diag.failed) and not usable)))


def _why_unusable(diag: Diagnosis, effect: str) -> str:
    f = next(c.fit for c in diag.candidates if c.effect == effect)
    if f.unstable:
        return f"{effect}: the wear loop's derivatives were unstable at the refit"
    return f"{effect}: the model did not run from the refit's start ({f.message})"


def _failed_text(diag: Diagnosis) -> str:
    """'The refit(s) with ... failed (why)'."""
    s = "s" if len(diag.failed) > 1 else ""
    return (f"The refit{s} with {', '.join(diag.failed)} failed ("
            + "; ".join(_why_unusable(diag, e) for e in diag.failed) + ")")


def _remedy(diag: Diagnosis) -> str:
    st = diag.study
    if st.integrator == "paper":
        return (f"lower numerics.revolutions_per_update ({st.revolutions_per_update:g}) "
                f"and rerun")
    return f"lower numerics.wear_tolerance_um ({st.wear_tolerance_um:g} µm) and rerun"


def p_text(p: float) -> str:
    """A p-value in words that never rounds a small one to "0.00" (2 significant digits)."""
    return f"{p:.2g}" if p >= 0.01 else f"{p:.1e}"


def noise_claim(tests) -> str:
    """What the misfit left by a fit is, in words, by its own combined test (`Tests`): "at
    the noise level" only where that test accepts at α; where it rejects, the opposite.
    The one place a verdict sentence says "noise level" of a fit with an effect (issue 43:
    a sentence said "at the noise level (p = 0.00)")."""

    if not tests.systematic:
        return (f"at the noise level (combined test p = {p_text(tests.p_min)} ≥ α = "
                f"{ALPHA:g})")
    return (f"still above the noise: its combined test rejects (p = {p_text(tests.p_min)} "
            f"< α = {ALPHA:g})")


def _partly_text(diag: Diagnosis) -> str:
    """`partly_explained`: the best library fit lowers the misfit but its test rejects."""
    name = diag.partial[0] if diag.partial else diag.final.label
    c = next((c for c in diag.candidates if c.effect == name), None)
    fit = c.fit if c is not None and c.fit is not None else diag.final
    tests = c.tests if c is not None and c.tests is not None else diag.final_tests
    strength = _strength_text(diag, fit, name) if name in diag.model.candidates else ""
    return (f" The best library candidate, {name}" + (f" ({strength})" if strength else "")
            + f", lowers the RMSE from {diag.base.rmse:.3f} to {fit.rmse:.3f} µm, "
            f"{noise_claim(tests)}, and no pair of candidates passes it: the missing physics "
            f"is only approximated by the library (partly explained), so no effect is named "
            f"as missing. The shape of the missing wear (on top of the base model, and on "
            f"top of {name} where it finds something else) describes what it misses.")


def _verdict_text(diag: Diagnosis) -> str:
    t = diag.base_tests
    noise = diag.noise_um
    head = (f"The base model (as the study states it, {diag.base.k} fitted parameters) fits "
            f"{diag.model.n} measured points with RMSE {diag.base.rmse:.3f} µm against a noise "
            f"level of {noise:.3f} µm estimated from neighbouring points "
            f"(chi-square ratio {t.ratio:.2f}, p = {t.p_chi2:.1e}; lag-1 residual "
            f"autocorrelation {t.rho:.2f}, p = {t.p_autocorr:.1e}")
    if t.score_effect:
        head += f"; best single-candidate score test {t.score_effect}, p = {t.p_score:.1e}"
    head += ")."
    if diag.status == "adequate":
        return head + (" The misfit is consistent with measurement noise: no missing effect "
                       "is needed to explain these data.")
    sig = _signature_text(diag)
    if diag.status == "effect_found":
        f = diag.final
        eff = diag.effects
        names = " and ".join(eff)
        strength = "; ".join(f"{e}: {_strength_text(diag, f, e)}" for e in eff)
        lb, la = _mean_sq(diag.loo_before), _mean_sq(diag.loo_after)
        verb = "effects are" if len(eff) > 1 else "effect is"
        if not t.systematic:
            lead = next(c for c in diag.candidates if c.fit is f)
            head += (f" With so few points these tests are inconclusive, but the evidence for "
                     f"{names} over the base model is very strong (ln Bayes factor "
                     f"{lead.evidence:.1f} > ln 150, BIC with the noise level unknown).")
        text = (f"{head} The misfit is systematic, and the missing {verb} {names} "
                f"({strength}). With it the RMSE falls to {f.rmse:.3f} µm, "
                f"{noise_claim(diag.final_tests)}"
                + (f", and the left-out-experiment prediction error from {lb:.3f} to "
                   f"{la:.3f} µm" if lb is not None and la is not None else "")
                + f". What pointed to it: {sig}"
                f" — the signature of {eff[0]} ({_describe(eff[0])}).")
        if diag.alternatives:
            text += (f" The data cannot tell it apart from {', '.join(diag.alternatives)}, "
                     f"which fits nearly as well (evidence gap < ln 20): treat the name as "
                     f"one of these, not as certain.")
            text += design_pointer(diag, eff[0])
        return text
    usable = [c for c in diag.candidates if c.fit is not None and c.fit.usable]
    if _undetermined(diag):
        # no refit came to an answer: the verdict cannot say more than that
        lead = next((c for c in diag.candidates if c.screen is not None
                     and (c.fit is None or c.effect in diag.failed)), None)
        why = ("the misfit is systematic" if t.systematic else
               "these tests do not reject noise on so few points, but the candidates' "
               "linearised evidence is very strong")
        if lead is not None and not t.systematic:
            why += (f" (linearised, {lead.effect} would remove "
                    f"{100 * lead.screen.explained:.0f} % of the misfit)")
        short = [c for c in usable if c.fit.status == "budget"]
        done = []
        if diag.failed:
            done.append(_failed_text(diag))
        done += [f"the refit with {c.effect} ran out of its budget ({c.fit.evaluations} "
                 f"evaluations) at RMSE {c.rmse_um:.3f} µm, short of very strong evidence "
                 f"(ln Bayes factor {c.evidence:.1f}, a lower bound)" for c in short]
        if not done:
            done.append("no candidate was refitted")
        text = "; ".join(done)
        return (f"{head} The base model is not shown to be adequate: {why} ({sig}). "
                f"{text[0].upper()}{text[1:]}, so no candidate was refitted to an answer and "
                f"the missing effect, if any, is not determined"
                + (f": {_remedy(diag)}." if diag.failed else "."))
    text = f"{head} The misfit is systematic ({sig})."
    if diag.status == "partly_explained":
        return text + _partly_text(diag)
    if diag.partial:
        c = next(c for c in diag.candidates if c.effect == diag.partial[0])
        text += (f" The best candidate, {c.effect} ({_strength_text(diag, c.fit, c.effect)}),"
                 f" lowers the RMSE to {c.rmse_um:.3f} µm but leaves a systematic remainder "
                 f"(p = {c.tests.p_min:.1e}); no candidate or pair of candidates brings the "
                 f"misfit to noise level.")
    else:
        text += " No candidate explains it."
    return text + (" The missing physics is not among the library's candidates: look at the "
                   "residual figures for where the model fails.")


def design_pointer(diag: Diagnosis, winner: str) -> str:
    """The sentence that names the command telling tied explanations apart (issue 44):
    `jaxwear design --between` takes effects, not structural candidates."""
    rivals = [a for a in diag.alternatives if a not in STRUCTURAL_CANDIDATES]
    if winner in STRUCTURAL_CANDIDATES or not rivals:
        return ""
    return (f" To tell them apart, `jaxwear design {diag.study.path} --between "
            f"{winner},{rivals[0]}` ranks the next experiments by how well they would "
            f"separate the two and writes the best as an [[experiment]] stanza.")
