"""Laws the data do not tell apart (issue 48, recovery): the fitted laws of another structure
whose left-out-experiment RMSE is within one standard error of the answer's, and where
their predictions part.

Why: the search answers with the simplest law within one standard error of the best
left-out RMSE (`law.search.rank`). Where a law of another structure predicts the left-out
experiments as well (on the generator's exponential of the worn depth a power h^1.94 and a
hinge both at 0.3139 µm; its hinge of the speed a power v^4.99 at the noise), the answer
is one of several the data allow, and the report must say so and which: the
`equivalents`, each with its constants and errors, and the state where its rate and the
answer's differ most (`separation`), which a next experiment must reach to tell them
apart.

Pure functions of fitted laws (`LawFit`) and the states met at the fit (no model run).
"""

from __future__ import annotations

import math

import numpy as np

from jaxwear._physics.effects.law import DERIVED, SYMBOLS, law_phi_numpy, variable_unit
from jaxwear._physics.effects.shape import DEPOSIT_VARIABLES, VARIABLES

# the least band of "within one standard error" (a fraction of the answer's left-out RMSE):
# `law.search.LOO_TIE`, repeated here so that this module imports nothing of the search
TIE = 0.01
# how far beyond the states met a separating state is looked for: to `REACH` times the
# upper end and 1/`REACH` times the lower (`law.search.unbounded` asks the same of an
# exponential: bounded to twice the upper end)
REACH = 2.0
GRID = 201  # points of a variable's extended range


def loo_band(f) -> float:
    """One standard error [µm] of `f`'s left-out RMSE from its experiments' spread (the
    mean of their squared errors, by the delta method), at least `TIE` of it."""
    m = np.square(np.asarray(list((f.loo_per_experiment or {}).values()), float))
    lo = f.loo_rmse_um
    se = 0.0
    if len(m) >= 2 and lo is not None and lo > 0:
        se = float(np.std(m, ddof=1) / math.sqrt(len(m)) / (2.0 * lo))
    return max(se, TIE * (lo or 0.0))


def _terms(law) -> tuple:
    return tuple((t.kind, t.variable) for t in getattr(law, "terms", ()))


def nests(law, inner) -> bool:
    """`law` holds every term of `inner` (kind and variable) and more, in one form: it is
    `inner` times a term the data may not need (on the generator's power of the pressure,
    (p/p_ref)^a1 · exp((ω − ω_ref)/ω_e) with ω_e = −16500 ± 19100 deg/s, the same left-out
    error to 4 digits): not another law, and not reported as one."""
    a, b = _terms(law), _terms(inner)
    return (law.form == inner.form and bool(b) and len(a) > len(b)
            and all(a.count(t) >= b.count(t) for t in b))


def equivalents(ranked) -> list:
    """The laws of `ranked` (best first, `law.search.rank`) of another structure than the
    answer (`ranked[0]`; structure: form, kinds and variables, `LawSpec.label`), neither
    nesting it nor nested in it (`nests`), whose left-out RMSE is within one standard error
    (`loo_band` of the answer) of the answer's, best left-out first. [] where the answer
    has no left-out RMSE."""
    if not ranked:
        return []
    best = ranked[0]
    lo = best.loo_rmse_um
    if lo is None or not math.isfinite(lo):
        return []
    band = loo_band(best)
    out = [f for f in ranked[1:] if f.law.label != best.law.label and not f.refused
           and not nests(f.law, best.law) and not nests(best.law, f.law)
           and f.loo_rmse_um is not None and math.isfinite(f.loo_rmse_um)
           and abs(f.loo_rmse_um - lo) <= band]
    # one per structure (its best left-out), best left-out first
    seen, uniq = set(), []
    for f in sorted(out, key=lambda f: f.loo_rmse_um):
        if f.law.label not in seen:
            seen.add(f.law.label)
            uniq.append(f)
    return uniq


def _base(law) -> list:
    """The shape's variables `law`'s terms are made of (p·v: p and v), in order."""
    out = []
    for t in getattr(law, "terms", ()):
        for v in (DERIVED[t.variable][1] if t.variable in DERIVED else (t.variable,)):
            if v not in out:
                out.append(v)
    return out


def _rate(law, z: dict) -> np.ndarray:
    """The law's share of the rate at the states `z`: 1 + A Φ (a factor; K_d's level
    aside) or D Φ (a deposit)."""
    phi = np.asarray(law_phi_numpy(law, z), float)
    return 1.0 + law.strength * phi if law.form == "factor" else law.strength * phi


def separation(a, b, samples: dict, ranges: dict, study_path=None) -> dict | None:
    """Where the rates of the fitted laws `a` and `b` (`LawFit`s of one form, memoryless)
    differ most: each law's rate (`_rate`) over the states met `samples` ({form:
    {variable: (n,)}}, equal weights: `law.search.states_met`) normalised to its mean there
    (the fit's K_d absorbs the level), one variable of either law swept over its range met
    (`ranges`: {form: {variable: (lo, hi)}}) extended `REACH`-fold, the others at their
    medians met. Returns {variable, unit, at, ratio (b's rate over a's, normalised, at
    `at`), ratio_in_range (the largest |ratio − 1| within the range met), range_met,
    beyond_range (bool), command (a `jaxwear design --goal separate` between the two
    variables where the two laws are of distinct single shape variables, else None)}, or
    None where it cannot be computed (a law with memory, no states)."""
    if getattr(a.law, "memory", False) or getattr(b.law, "memory", False):
        return None
    form = a.law.form
    Z = samples.get(form) or {}
    rng = ranges.get(form) or {}
    names = [v for v in dict.fromkeys(_base(a.law) + _base(b.law)) if v in Z and v in rng]
    if not names or b.law.form != form:
        return None
    base = {k: np.asarray(v, float) for k, v in Z.items() if k not in DERIVED}
    ra, rb = _rate(a.law, base), _rate(b.law, base)
    ma, mb = float(np.mean(ra)), float(np.mean(rb))
    if not (ma > 0 and mb > 0 and math.isfinite(ma) and math.isfinite(mb)):
        return None
    med = {k: float(np.median(v)) for k, v in base.items()}
    best = None
    for name in names:
        lo, hi = rng[name]
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            continue
        z_lo = lo / REACH if lo > 0 else lo
        grid = np.linspace(z_lo, hi * REACH if hi > 0 else hi, GRID)
        grid = np.unique(np.concatenate([grid, np.linspace(lo, hi, GRID)]))
        z = {k: np.full(len(grid), v) for k, v in med.items()}
        z[name] = grid
        ga, gb = _rate(a.law, z) / ma, _rate(b.law, z) / mb
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(ga > 0, gb / ga, np.nan)
        dev = np.abs(np.log(np.where(ratio > 0, ratio, np.nan)))
        if not np.any(np.isfinite(dev)):
            continue
        k = int(np.nanargmax(dev))
        inside = (grid >= lo) & (grid <= hi)
        dev_in = np.where(inside, dev, np.nan)
        k_in = int(np.nanargmax(dev_in)) if np.any(np.isfinite(dev_in)) else k
        row = {"variable": name, "unit": variable_unit(name), "at": float(grid[k]),
               "ratio": float(ratio[k]), "ratio_in_range": float(ratio[k_in]),
               "range_met": [float(lo), float(hi)],
               "beyond_range": bool(not inside[k])}
        if best is None or dev[k] > best[0]:
            best = (float(dev[k]), row)
    if best is None:
        return None
    row = best[1]
    row["command"] = _command(a.law, b.law, study_path)
    return row


def _command(a, b, study_path) -> str | None:
    """`jaxwear design STUDY --goal separate --between shape:X,shape:Y` where `a` and `b`
    are laws of one shape variable each, distinct (the shape's correction along each is the
    rival the design ranks experiments for, `design.shape_rival`), else None."""
    va, vb = _base(a), _base(b)
    if study_path is None or len(va) != 1 or len(vb) != 1 or va == vb:
        return None
    if any(getattr(t, "variable", None) in DERIVED for t in (*a.terms, *b.terms)):
        return None
    allowed = VARIABLES if a.form == "factor" else DEPOSIT_VARIABLES
    if va[0] not in allowed or vb[0] not in allowed:
        return None
    pre = "shape:" if a.form == "factor" else "shape:deposit:"
    return f"jaxwear design {study_path} --goal separate --between {pre}{va[0]},{pre}{vb[0]}"


def equivalents_sentence(best, equivalents_: list, separations: list) -> str:
    """"The data do not tell X from Y (left-out a against b µm, within one standard error
    s µm); their rates differ most at z = ... (x % ...): a test that reaches it would
    separate them." for each equivalent, or ""."""
    if best is None or not equivalents_:
        return ""
    band = loo_band(best)
    out = []
    for f, sep in zip(equivalents_, separations):
        s = (f"The data do not tell {best.law.label} from {f.law.label} (left-out "
             f"experiments {best.loo_rmse_um:.4f} against {f.loo_rmse_um:.4f} µm, within one "
             f"standard error, {band:.4f} µm)"
             + (f"; its {', '.join(f.undetermined)} not determined" if f.undetermined
                else ""))
        if sep:
            sym = SYMBOLS.get(sep["variable"], sep["variable"])
            lo, hi = sep["range_met"]
            where = ("beyond the states met" if sep["beyond_range"] else "within the states met")
            s += (f"; their rates part most at {sym} = {sep['at']:.4g} {sep['unit']} "
                  f"({sep['ratio'] - 1:+.0%}, {where}, {lo:.4g}-{hi:.4g} {sep['unit']}; "
                  f"at most {sep['ratio_in_range'] - 1:+.0%} within them): an experiment "
                  f"that reaches {sym} = {sep['at']:.4g} {sep['unit']} would separate them")
            if sep.get("command"):
                s += f" (`{sep['command']}` ranks the next experiments that would)"
        out.append(s + ".")
    return " ".join(out)
