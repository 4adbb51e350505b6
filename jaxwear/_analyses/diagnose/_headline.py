"""The answer first (issue 49): the verdict as one line (`headline`), at most five short
sentences (`summary`) and the long text (`details`), for the JSON (design.md §7 `verdict`),
the command line's last lines and the report's first screen.

The headline names what is missing, with its constants and their units, then the error from
the base model to the answer against the noise, in-sample and on left-out experiments. The
answer is, in this order: the effect found (`effect_found`); the law of the shape's search
where its status is `found` (design.md §7 `shape.law.status`); nothing where the base model
is `adequate`; otherwise the best lead (a law that is a lead, the shape's variable, the
library candidate that approximates). The summary gives the evidence, where and when on the
joint, what the data cannot tell apart and the command that would, in that order; the
details are the verdict's paragraph with the shape's and the law's sentences.
"""

from __future__ import annotations

import math

import numpy as np

from jaxwear._analyses.diagnose._result import Diagnosis, _mean_sq
from jaxwear._analyses.diagnose._stats import ALPHA
from jaxwear._analyses.diagnose._text import (
    _fmt_value,
    _signature_text,
    _strength_text,
    design_pointer,
    noise_claim,
    p_text,
)
from jaxwear._analyses.diagnose.shape.text import LABEL, where_along

MAX_SENTENCES = 5  # of the summary (design.md §7)


def num(x, digits: int = 3) -> str:
    """`x` for people: `digits` significant digits, trailing zeros kept where they are
    significant (0.580, not 0.58), no float noise (2, not 1.9999999999999996), "—" for
    None or NaN."""
    if x is None or not math.isfinite(float(x)):
        return "—"
    x = float(x)
    if x == 0:
        return "0"
    if abs(x) >= 10 ** digits:
        return f"{x:.0f}"
    if abs(x) < 1e-3:
        return f"{x:.{digits - 1}e}"
    s = f"{x:#.{digits}g}"
    return s.rstrip(".") if "e" not in s else s


def law_status(law) -> str | None:
    """"found" or "lead" of the shape's law (`law.search.LawResult`), None where there is none.
    The search's own status where it gives one (design.md §7 `shape.law.status`); else a
    law is a lead where it is worse than the shape, leaves a constant undetermined or does
    not predict the left-out experiments better than the base model."""
    if law is None or getattr(law, "best", None) is None:
        return None
    status = getattr(law, "status", None)
    if status in ("found", "lead"):
        return status
    b = law.best
    if law.worse_than_shape or b.undetermined:
        return "lead"
    if (b.loo_rmse_um is not None and law.loo_before_um is not None
            and not b.loo_rmse_um < law.loo_before_um):
        return "lead"
    return "found"


def law_text(law) -> str:
    """The law's formula with its constants in their units, in one line."""
    b = law.best
    f = b.formula.replace("   [", " [")
    # ± the standard error and the constants' numerical error together (`law.numerical`)
    ne = getattr(b, "numerical_error", None) or {}

    def pm(k, s):
        n = ne.get(k)
        return math.hypot(s, n) if n is not None and math.isfinite(n) else s

    consts = ", ".join(
        f"{k} = " + (_fmt_value(v, pm(k, s), "" if u == "-" else f" {u}")
                     if s is not None and math.isfinite(s) and s > 0
                     else f"{num(v)}{'' if u == '-' else ' ' + u}")
        for k, (v, s, u) in b.constants.items())
    return f"{f}, with {consts}"


def _shape_of(diag: Diagnosis):
    return diag.shape


def _law_of(diag: Diagnosis):
    shp = diag.shape
    return None if shp is None else getattr(shp, "law", None)


def answer(diag: Diagnosis) -> str:
    """What the headline reports as the answer: "effect", "law", "adequate" or "lead"."""
    if diag.status == "effect_found":
        return "effect"
    if diag.status == "adequate":
        return "adequate"
    if law_status(_law_of(diag)) == "found":
        return "law"
    return "lead"


def lead(diag: Diagnosis) -> str | None:
    """The best lead of a verdict without an answer (`answer` "lead"): "law" where the
    law of the search predicts the left-out experiments better than the base model (a lead
    that does not is no lead), else "shape" where the shape found a variable, else
    "library" where a library candidate approximates; None where there is none."""
    law = _law_of(diag)
    if law is not None and law.best is not None:
        b = law.best
        if b.loo_rmse_um is None or law.loo_before_um is None or (
                b.loo_rmse_um < law.loo_before_um):
            return "law"
    shp = _shape_of(diag)
    if shp is not None and shp.best is not None:
        return "shape"
    if diag.partial and diag.final is not diag.base:
        return "library"
    return None


def errors(diag: Diagnosis) -> dict:
    """{"before", "after", "loo_before", "loo_after"} [µm] of the answer (`answer`): the
    base model's and the answer's RMSE in-sample and on left-out experiments (None where
    not computed); for a lead, the best of what was fitted (the law, the shape, the
    library candidate)."""
    before, loo_before = diag.base.rmse, _mean_sq(diag.loo_before)
    kind = answer(diag)
    law = _law_of(diag)
    if kind == "adequate":
        return dict(before=before, after=None, loo_before=loo_before, loo_after=None)
    if kind == "effect":
        return dict(before=before, after=diag.final.rmse, loo_before=loo_before,
                    loo_after=_mean_sq(diag.loo_after))
    if kind == "law" or lead(diag) == "law":
        # the base model's left-out error by the law search's own rule (each step checked
        # by a forward run), so that both sides of the arrow are measured alike
        lb = law.loo_before_um
        return dict(before=before, after=law.best.rmse_um,
                    loo_before=lb if lb is not None and math.isfinite(lb) else loo_before,
                    loo_after=law.best.loo_rmse_um, **({} if kind == "law" else
                                                       {"with": "the law"}))
    shp = _shape_of(diag)
    if (diag.final is diag.base and shp is not None and shp.best is not None
            and shp.rmse_after_um is not None):
        return dict(before=before, after=shp.rmse_after_um, loo_before=loo_before,
                    loo_after=getattr(shp, "loo_rmse_um", None), **{"with": "the shape"})
    if diag.final is not diag.base:
        return dict(before=before, after=diag.final.rmse, loo_before=loo_before,
                    loo_after=_mean_sq(diag.loo_after), **{"with": diag.final.label})
    return dict(before=before, after=None, loo_before=loo_before, loo_after=None)


def corrected(diag: Diagnosis):
    """(label, the rows' residuals [µm]) of the model the answer corrects the base model
    to (`answer`): the effect found, else the law (found or a lead), else the shape's
    refitted correction, else the library candidate that approximates; None where the
    answer is the base model (`adequate`, or nothing fitted)."""
    kind = answer(diag)
    if kind == "adequate":
        return None
    if kind == "effect":
        return " + ".join(diag.effects), np.asarray(diag.final.ev.r)
    law = _law_of(diag)
    if ((kind == "law" or lead(diag) == "law") and law.best.residual_um is not None):
        return ("the law" if kind == "law" else "the law (a lead)",
                np.asarray(law.best.residual_um))
    shp = _shape_of(diag)
    if (diag.final is diag.base and shp is not None and shp.best is not None
            and shp.residual_um is not None):
        return "the shape", np.asarray(shp.residual_um)
    if diag.final is not diag.base:
        return diag.final.label, np.asarray(diag.final.ev.r)
    return None


def error_text(diag: Diagnosis) -> str:
    """"RMSE 0.580 → 0.307 µm against noise 0.304 µm; left-out experiments 0.62 → 0.33 µm"."""
    e = errors(diag)
    noise = f"noise {num(diag.noise_um)} µm"
    if e["after"] is None:
        s = f"RMSE {num(e['before'])} µm against {noise}"
        if e["loo_before"] is not None:
            s += f"; left-out experiments {num(e['loo_before'])} µm"
        return s
    by = f" ({e['with']})" if e.get("with") else ""
    s = f"RMSE {num(e['before'])} → {num(e['after'])} µm{by} against {noise}"
    if e["loo_before"] is not None and e["loo_after"] is not None:
        s += f"; left-out experiments {num(e['loo_before'])} → {num(e['loo_after'])} µm"
    return s


_NO_LEAD = "none: see where the residuals are largest"


def _partial_text(diag: Diagnosis) -> str:
    """"the library's X (strength)" of a partly explained verdict's candidate, or ""."""
    c = next((c for c in diag.candidates if c.effect == diag.partial[0]), None)
    if c is None or c.fit is None:
        return ""
    st = _strength_text(diag, c.fit, c.effect) if c.effect in diag.model.candidates else ""
    return f"the library's {c.effect}" + (f" ({st})" if st else "")


def _lead_text(diag: Diagnosis, library: bool = True) -> str:
    """The best lead of a verdict without an answer, in words ("" where there is none);
    `library`: the candidate that approximates counts as one."""
    law = _law_of(diag)
    which = lead(diag)
    if which == "law":
        return f"the law {law_text(law)} (a lead: {_why_lead(law)})"
    shp = _shape_of(diag)
    if which == "shape":
        v = shp.variable(shp.best, shp.form)
        what = "more wear" if shp.form == "factor" else "extra wear not tied to sliding"
        return f"{what} following {shp.best} (explains {v.explained_fraction:.0%} of the misfit)"
    if library and diag.partial:
        return _partial_text(diag)
    return ""


def _why_lead(law) -> str:
    """Why the law is a lead, not found, in a few words."""
    b = law.best
    if law.worse_than_shape:
        return (f"{b.rmse_um / law.shape_rmse_um - 1:+.0%} above the shape's refitted "
                f"correction")
    if b.undetermined:
        return f"{', '.join(b.undetermined)} not determined by these data"
    if law.shape_unchecked is not None:
        return "not compared with the shape's refitted correction, which has no RMSE"
    if (b.loo_rmse_um is not None and law.loo_before_um is not None
            and not b.loo_rmse_um < law.loo_before_um):
        return "it predicts left-out experiments no better than the base model"
    return "short of the bar for a law found"


def headline(diag: Diagnosis) -> str:
    """The answer in one line (design.md §7 `verdict.headline`; module docstring)."""
    kind = answer(diag)
    err = error_text(diag)
    if kind == "adequate":
        return f"Adequate: the base model fits to the noise ({err})."
    if kind == "effect":
        strength = "; ".join(
            f"{e}: {s}" if len(diag.effects) > 1 else s
            for e in diag.effects if (s := _strength_text(diag, diag.final, e)))
        name = " + ".join(diag.effects)
        return (f"Missing effect: {name}" + (f" ({strength})" if strength else "")
                + f". {err}.")
    if kind == "law":
        return f"Law found: {law_text(_law_of(diag))}. {err}."
    if diag.status == "partly_explained" and diag.partial:
        approx = _partial_text(diag)
        lead = _lead_text(diag, library=False)
        return (f"Partly explained: {approx} only approximates it"
                + (f"; the best lead is {lead}" if lead else "") + f". {err}.")
    return f"Not explained; the best lead is {_lead_text(diag) or _NO_LEAD}. {err}."


# -- the summary: evidence, where and when, what is confounded and the command ----------

def _evidence(diag: Diagnosis) -> str:
    t = diag.base_tests
    kind = answer(diag)
    if kind == "adequate":
        return (f"The misfit is consistent with measurement noise: chi-square ratio "
                f"{t.ratio:.2f} (p = {p_text(t.p_chi2)}), lag-1 residual autocorrelation "
                f"{t.rho:.2f} (p = {p_text(t.p_autocorr)}).")
    if kind == "effect":
        lead = next((c for c in diag.candidates if c.fit is diag.final), None)
        ev = "" if lead is None else (f"ln Bayes factor {lead.evidence:.1f} over the base "
                                      f"model (very strong above ln 150 = 5.0); ")
        return f"Evidence: {ev}with it the misfit is {noise_claim(diag.final_tests)}."
    law = _law_of(diag)
    if kind == "law":
        b = law.best
        shape = (f"fits as well as the free shape ({num(law.shape_rmse_um)} µm)"
                 if law.shape_rmse_um is not None and math.isfinite(law.shape_rmse_um)
                 else "fits")
        loo = (f" and predicts the left-out experiments ({num(law.loo_before_um)} → "
               f"{num(b.loo_rmse_um)} µm)" if b.loo_rmse_um is not None
               and law.loo_before_um is not None else "")
        left = (f"the misfit left is at the noise level (combined test p = "
                f"{p_text(b.p_combined)} ≥ α = {ALPHA:g})" if b.at_noise else
                f"its combined test still rejects (p = {p_text(b.p_combined)} < α = "
                f"{ALPHA:g}), {b.rmse_um / diag.noise_um - 1:.0%} above the noise")
        return f"Evidence: the law {shape}{loo}; {left}."
    base = (f"The base model's misfit is systematic (combined test p = "
            f"{p_text(t.p_min)} < α = {ALPHA:g})")
    if diag.partial:
        c = next((c for c in diag.candidates if c.effect == diag.partial[0]), None)
        if c is not None and c.fit is not None:
            return (f"{base}; the library's {c.effect} lowers it to {num(c.fit.rmse)} µm but "
                    f"its own test still rejects, so it only approximates the missing "
                    f"physics.")
    return f"{base} and no library candidate lowers it materially."


def _where(diag: Diagnosis) -> str:
    """Where and when on the joint, from the shape where it found a variable, else from
    the base model's residuals."""
    shp = _shape_of(diag)
    if answer(diag) != "adequate" and shp is not None and shp.best is not None:
        v = shp.variable(shp.best, shp.form)
        s = f"It concentrates {where_along(v)}"
        ww = shp.when_where
        if ww is not None and ww.made:
            a, b, _ = ww.made[0]
            c, d, _ = ww.lands[0] if ww.lands else (math.nan, math.nan, 0)
            s += (f"; it is made at cycle phases {a:.0f}-{b:.0f}°"
                  + (f" and lands on the bore at {c:.0f}-{d:.0f}°" if ww.lands else "")
                  + f" ({ww.experiment})")
        return s + "."
    if answer(diag) == "adequate":
        return ""
    sig = _signature_text(diag)
    return f"Where the base model fails: {sig}." if sig else ""


def _confounded(diag: Diagnosis) -> str:
    """What the data cannot tell apart, and the command that would."""
    if answer(diag) == "effect" and diag.alternatives:
        return (f"The data cannot tell {diag.effects[0]} from "
                f"{', '.join(diag.alternatives)}." + design_pointer(diag, diag.effects[0]))
    shp = _shape_of(diag)
    if answer(diag) in ("law", "lead") and shp is not None and shp.next_test:
        rival = shp.next_test.rsplit("shape:", 1)[-1]
        best = shp.best if shp.form == "factor" else f"deposit:{shp.best}"
        return (f"These experiments cannot tell {best} from {rival}: `{shp.next_test}` "
                f"ranks the next experiments that would.")
    return ""


def summary(diag: Diagnosis) -> str:
    """At most `MAX_SENTENCES` short sentences (design.md §7 `verdict.summary`): what the
    diagnosis changed in the numerics first (`Diagnosis.flags`), then the evidence, where
    and when, what is confounded and the command that separates it; for a law that is a
    lead, why."""
    parts = [f"{f}." if not f.endswith(".") else f for f in diag.flags]
    parts += [s for s in (_evidence(diag), _where(diag), _confounded(diag)) if s]
    law = _law_of(diag)
    if answer(diag) == "lead" and law is not None and law.best is not None:
        parts.append("law.py holds the best law tried as a lead only" + (
            "" if lead(diag) == "law" else
            f" (it predicts the left-out experiments no better than the base model: "
            f"{num(law.best.loo_rmse_um)} against {num(law.loo_before_um)} µm)")
            + "; missing_wear.py holds the shape.")
    if not diag.confident and diag.failed:
        parts.append(f"Refits that failed, not compared: {', '.join(diag.failed)}.")
    return " ".join(parts[:MAX_SENTENCES])


def shape_adds(first, after) -> bool:
    """Whether the shape on top of the effect (`after`) says something the shape on top
    of the base model (`first`) does not: it finds a variable and that variable or form
    is another (the same variable again repeats the first; none left is the verdict's own
    test's answer)."""
    if after is None or after.best is None:
        return False
    if first is None or first.best is None:
        return True
    return (after.best, after.form) != (first.best, first.form)


def details(diag: Diagnosis, verdict_text: str) -> str:
    """The long text (design.md §7 `verdict.details`): the verdict's paragraph
    (`_text.summarize_verdict`), the shape's sentence, the shape on top of the effect
    where it adds something (`shape_adds`), the law's sentence and its weighing against the
    library's names (`Diagnosis.law_contest`)."""
    shp, after = diag.shape, diag.shape_after_effect
    parts = [verdict_text]
    if shp is not None:
        parts.append(shp.sentence)
    if after is not None:
        parts.append(after.sentence if shape_adds(shp, after) else
                     f"On top of {after.after} the shape finds nothing the first does not"
                     + (" (no variable beyond the noise)." if after.best is None else
                        f" (the same {LABEL.get(after.best, after.best)} again)."))
    law = _law_of(diag)
    if law is not None:
        parts.append(law.sentence)
    contest = getattr(diag, "law_contest", None)
    if contest:  # a law weighed against library names (issue 48 item 3)
        parts.append(contest.get("sentence", ""))
    return " ".join(p for p in parts if p)


def compose(diag: Diagnosis, verdict_text: str) -> tuple[str, str, str]:
    """(headline, summary, details) of a diagnosis (module docstring); `verdict_text`: the
    verdict's paragraph (`_text.summarize_verdict`)."""
    return headline(diag), summary(diag), details(diag, verdict_text)
