"""The shape of the missing wear in words (`shape.analysis`): one plain sentence a machine designer
can act on."""

from __future__ import annotations

import math

import numpy as np

from jaxwear._analyses.diagnose._stats import ALPHA
from jaxwear._analyses.diagnose.shape.interaction import SURFACE_MATERIAL
from jaxwear._analyses.diagnose.shape.linear import DRAWS, trend

# cycle phase: the crank angle, the swing's phase, or the phase within a load file's period
LABELS = {"cycle_phase_deg": "cycle phases", "pressure_MPa": "contact pressures",
          "sliding_speed_m_per_s": "sliding speeds", "sliding_distance_m": "sliding distances",
          "load_turn_rate_deg_per_s": "load turn rates",
          "load_turn_deg_per_deg": "load turns per degree of the cycle",
          "load_N": "joint loads", "bore_angle_deg": "bore angles",
          "worn_depth_um": "depths already worn"}
LABEL = {"pressure_MPa": "contact pressure", "sliding_speed_m_per_s": "sliding speed",
         "sliding_distance_m": "sliding distance", "load_turn_rate_deg_per_s": "load turn rate",
         "load_turn_deg_per_deg": "load turn per degree of the cycle", "load_N": "joint load",
         "worn_depth_um": "depth already worn"}
FORM_WORDS = {"factor": "more of the wear Archard already makes there (a factor of the "
                        "local rate)",
              "deposit": "extra wear not tied to sliding, made where the pin presses (as "
                         "impacts, fretting or cold flow make it)"}


def _levels(v) -> tuple[float, float]:
    """(low, high) of the correction where the data determine it: over the grid points
    whose band is no wider than twice its median width (where little wears, it is free to
    wander)."""
    width = v.g_upper - v.g_lower
    ok = width <= 2.0 * np.median(width)
    g = v.g[ok] if ok.any() else v.g
    return float(g.min()), float(g.max())


def _region(v) -> tuple[float, float]:
    """Where the correction is above half-way between its low and high levels, around the
    peak: for a step, from the step on."""
    g = v.g
    low, high = _levels(v)
    half = low + 0.5 * (high - low)
    k = int(np.argmax(g))
    n = len(g)
    lo = hi = k
    step = (lambda i: i % n) if v.name in ("cycle_phase_deg", "bore_angle_deg") else (
        lambda i: min(max(i, 0), n - 1))
    for _ in range(n):
        nxt = step(lo - 1)
        if g[nxt] < half or nxt == lo:
            break
        lo = nxt
    for _ in range(n):
        nxt = step(hi + 1)
        if g[nxt] < half or nxt == hi:
            break
        hi = nxt
    return float(v.z[lo]), float(v.z[hi])


def threshold(v, rising: bool = True) -> float:
    """Where the correction steps up (`rising`; else down): the best two-level step fitted to
    it over the plotting grid (uniform in the wear-weighted quantile), each point weighted
    by 1/(its band width)², so that where the data leave it free it counts little. Returns
    z at the first point past the step (for a rate that jumps at a threshold, the
    threshold)."""
    g = v.g if rising else -v.g
    w = 1.0 / np.maximum(v.g_upper - v.g_lower, 1e-12) ** 2
    best, k_best = math.inf, 1
    for k in range(1, len(g)):
        sse = 0.0
        for part, wp in ((g[:k], w[:k]), (g[k:], w[k:])):
            m = float(np.sum(wp * part) / np.sum(wp))
            sse += float(np.sum(wp * (part - m) ** 2))
        if sse < best:
            best, k_best = sse, k
    return float(v.z[k_best])


def p_text(p: float) -> str:
    """"p 3.1e-03", or "p ≤ 5.0e-05" where no simulated draw reached the statistic (the
    p-value (1 + 0)/(1 + draws) is then a bound)."""

    return f"p ≤ {p:.1e}" if p <= 1.5 / (1.0 + DRAWS) else f"p {p:.1e}"


def where_along(v) -> str:
    """Where along its variable a correction concentrates, in words."""

    lo, hi = _region(v)
    rising = trend(v) > 0
    unit = v.unit
    if v.name in ("cycle_phase_deg", "bore_angle_deg"):
        return f"at {LABELS[v.name]} {lo:.0f}-{hi:.0f}°"
    if rising and hi >= v.z[int(0.85 * (len(v.z) - 1))]:
        return f"above {LABEL[v.name]} {threshold(v):.3g} {unit}, rising with it"
    if not rising and lo <= v.z[int(0.15 * (len(v.z) - 1))]:
        return (f"below {LABEL[v.name]} {threshold(v, rising=False):.3g} {unit}, "
                f"falling with it")
    return f"at {LABELS[v.name]} {lo:.3g}-{hi:.3g} {unit}"


def describe(best, form, results, load, after, alternatives=(), carriers=(), ww=None,
             confounded=(), interaction=None) -> str:
    on_top = "" if after == "base" else f" on top of {after}"
    if best is None:
        return (f"No state variable explains the misfit{on_top} beyond noise and the model's "
                f"own numerical error (family-wise α = {ALPHA:g} over {len(results)} "
                f"variable-forms).")
    v = next(r for r in results if r.name == best and r.form == form)
    s = (f"The missing wear{on_top} is {FORM_WORDS[form]}, following {best} (explains "
         f"{v.explained_fraction:.0%} of the misfit, {p_text(v.p_value)}): it concentrates "
         f"{where_along(v)}")
    others = [c for c in carriers if c != best]
    if others:
        s += f"; together with {', '.join(others)}, which carry part of it too"
    if interaction is not None and interaction.significant:
        a, b = interaction.variables
        s += (f", and as a product of {a} and {b} (their surface adds "
              f"{interaction.explained_fraction:.0%} to the sum of one-variable corrections, "
              f"{p_text(interaction.p_value)}"
              + ("" if interaction.carried else
                 f"; not refitted: linearised, it would lower the refitted RMSE by "
                 f"{interaction.rmse_gain_linearised:.1%}, under the "
                 f"{SURFACE_MATERIAL:.0%} a comparison resolves")
              + ")")
    s += "."
    if ww is not None and ww.made:
        s += (f" It is made at cycle phases {_arcs(ww.made)} and lands on the bore at "
              f"{_arcs(ww.lands)} ({ww.experiment})")
        if ww.reversals_deg and ww.share_at_reversals >= 0.5:
            s += (f", {ww.share_at_reversals:.0%} of it within {20:.0f}° of the load's "
                  f"reversals ({', '.join(f'{r:.0f}°' for r in ww.reversals_deg)}): look at "
                  f"what happens when the joint load swings round (impacts across the "
                  f"clearance)")
        elif math.isfinite(ww.peak_load_deg) and any(
                abs(np.mod(0.5 * (a + b) - ww.peak_load_deg + 180.0, 360.0) - 180.0) <= 30.0
                for a, b, _ in ww.made[:1]):
            s += f", around the load's peak ({ww.peak_load_deg:.0f}°)"
        s += "."
    s += stand_ins(results, form)
    if len(confounded) >= 2:
        s += (f" The data cannot tell {', '.join(confounded)} apart (none adds significantly "
              f"to the others, and each predicts left-out experiments as well): a test that "
              f"varies them apart would.")
    elif alternatives:
        s += (f" Preferred to {', '.join(alternatives)} (each within ln 20 of its AIC) by "
              f"the unique shares of the joint fit and the error on left-out experiments.")
    return s


def stand_ins(results, form) -> str:
    """" Stand-ins on this experiment matrix (they vary with it): for worn_depth_um,
    bore_angle_deg, cycle_phase_deg, load_N and 5 more.": one clause per leading variable,
    at most three stand-ins named (issue 49: eight pairs "a for b" read as noise), "" where
    there are none. The shape's table names every one."""
    by_lead = {}
    for r in results:
        if r.form == form and r.stand_in_for:
            by_lead.setdefault(r.stand_in_for, []).append(r.name)
    if not by_lead:
        return ""
    clauses = []
    for lead, names in sorted(by_lead.items()):
        names = sorted(names)
        few = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        clauses.append(f"for {lead}, {few}")
    return (" Stand-ins on this experiment matrix (they vary with it): "
            + "; ".join(clauses) + ".")


# a stand-in counts as a rival to tell apart when it explains at least this share of what
# the best explains (alone fits): on the paper's matrix pressure, sliding speed and the load
# each explained 102-104 % of a pressure law's misfit (issue 44)
RIVAL_SHARE = 0.9


def rival_of(best, form, results, alternatives=(), confounded=()) -> str | None:
    """The label of the variable the data tell least from the best: the first other of
    the variables the joint fit and the left-out experiments cannot tell apart
    (`confounded`, `shape.choice`), else the stand-in (same form) that explains most,
    where that is at least `RIVAL_SHARE` of the best's share; None where there is none.
    `alternatives` (AIC within ln 20) that the unique shares or the left-out error told
    from the best ("preferred to") are not rivals: the data already decided."""
    if best is None:
        return None
    label = best if form == "factor" else f"deposit:{best}"
    others = [c for c in confounded if c != label]
    if len(confounded) >= 2 and others:
        return others[0]
    top = next(r for r in results if r.name == best and r.form == form)
    near = [r for r in results if r.form == form and r.significant and r.name != best
            and r.stand_in_for is not None
            and r.explained_fraction >= RIVAL_SHARE * top.explained_fraction]
    if not near:
        return None
    return max(near, key=lambda r: r.explained_fraction).label


def next_test(study_path, best, form, results, alternatives=(), confounded=()
              ) -> str | None:
    """The command that ranks the next experiments by how well they would tell the best
    variable from its rival (`rival_of`; `jaxwear design`, issue 44), or None."""
    rival = rival_of(best, form, results, alternatives, confounded)
    if rival is None:
        return None
    label = best if form == "factor" else f"deposit:{best}"
    return (f"jaxwear design {study_path} --goal separate --between "
            f"shape:{label},shape:{rival}")


def next_test_sentence(command: str | None) -> str:
    """The sentence that names `command` (`next_test`), or ""."""
    if command is None:
        return ""
    return (f" To tell them apart, `{command}` ranks the next experiments by how well they "
            f"would separate the two and writes the best as an [[experiment]] stanza.")


def _arcs(arcs) -> str:
    """"50-70° (55 %) and 290-310° (43 %)"."""
    return " and ".join(f"{a:.0f}-{b:.0f}° ({w:.0%})" for a, b, w in arcs)
