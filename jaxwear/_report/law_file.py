"""`law.py`: the law found from the shape (`law.search`) as an effect file (DESIGN §7 `shape.law`).

Self-contained like `missing_wear.py`: the formula in its docstring, each fitted constant
a parameter of the effect (its key names its unit, its default the fitted value, its
standard error in the docstring), the references z_s (and an exponential's cap z_c, beyond
which it is held flat: `law.search.bounded`) as named module constants, and a
local rate of a few lines of jax.numpy that computes the formula as written (no held
selectors: `effects.law.LAW_SEARCH` is the search's device, not the user's file). Text
only: the CLI writes it.
"""

from __future__ import annotations

import math
import textwrap

from jaxwear._physics.effects.law import SYMBOLS, LawSpec, formula, term_formula
from jaxwear._report.law_memory_file import memory_file_source

EFFECT_NAME = "found_law"
_UNIT_KEY = {"-": "", "MPa": "_MPa", "m/s": "_m_per_s", "m": "_m", "deg/s": "_deg_per_s",
             "deg/deg": "_deg_per_deg", "N": "_N", "µm": "_um",
             "nm·rad per step": "_nm_rad_per_step", "MPa·m/s": "_MPa_m_per_s",
             "1/cycle": "_per_cycle"}


def parameter_key(name: str, unit: str) -> str:
    """The study key of a constant: `found_law_<NAME>` and its unit (DESIGN §6: the key
    names its unit)."""
    return f"{EFFECT_NAME}_{name}{_UNIT_KEY.get(unit, '')}"


def _term_code(law: LawSpec, k: int, keys: dict) -> str:
    """φ_k as jax.numpy over `z` and the parameters `e` (the formula of `term_formula`)."""
    t = law.terms[k - 1]
    z = f'z["{t.variable}"]'
    sym = SYMBOLS[t.variable]
    ref = f"{sym.upper()}_REF"

    def e(name):
        return f'e["{keys[name]}"]'

    if t.kind == "power":
        return f"safe_power(jnp.maximum({z} / {ref}, {POWER_FLOOR}), {e(f'a{k}')})"
    if t.kind == "hinge":
        return (f"safe_power(jnp.maximum(({z} - {e(sym + '0')}) / {ref}, 0.0), "
                f"jnp.maximum({e(f'a{k}')}, {HINGE_MIN}))")
    if t.kind == "step":
        return f"jax.nn.sigmoid(({z} - {e(sym + '0')}) / {e(sym + '_width')})"
    if t.kind == "exp":
        # a bounded exponential: held flat beyond its cap (`term_formula`'s min(z, z_cap))
        zc = f"jnp.minimum({z}, {sym.upper()}_CAP)" if math.isfinite(t.cap) else z
        return f"jnp.exp(jnp.clip(({zc} - {ref}) / {e(sym + '_e')}, -50.0, 50.0))"
    return "1.0"


POWER_FLOOR = 1e-3  # as `effects.law.POWER_FLOOR`
HINGE_MIN = 0.5  # as `effects.law.HINGE_MIN_EXPONENT`


def law_file_source(law: LawSpec, consts: dict, *, study_path: str, rmse_um: float,
                    loo_rmse_um: float | None, noise_um: float, caveat: str = "",
                    status: str = "found", ranges: dict | None = None) -> str:
    """The text of `law.py` for a fitted `law` and its `consts` ({NAME: (value, stderr,
    unit)}, `effects.law.constants`); `caveat`: what the search found wanting in it (worse
    than the shape, constants undetermined), written at the top of its docstring;
    `status`: "found" or "lead" (`law.search.LawResult.status`), said in the first line;
    `ranges`: {variable: (lo, hi)} the states it was fitted on, carried by the effect
    (`state_range`) so that calibrate and predict flag its use beyond them."""
    # the references and caps are chosen, not fitted: module constants, not parameters
    fixed = ("_ref", "_cap")
    fitted = {n: c for n, c in consts.items() if not n.endswith(fixed)}
    refs = {n: c for n, c in consts.items() if n.endswith(fixed)}
    keys = {n: parameter_key(n, u) for n, (_, _, u) in fitted.items()}
    lines_c = []
    for n, (v, s, u) in consts.items():
        err = f" ± {s:.3g}" if s is not None and math.isfinite(s) and s > 0 else ""
        what = ("cap, fixed: held flat beyond it" if n.endswith("_cap") else
                "reference, fixed" if n in refs else f"key {keys[n]}")
        lines_c.append(f"    {n} = {v:.6g}{err} {'' if u == '-' else u}  ({what})")
    memory = getattr(law, "memory", False)  # a law with memory: `law_memory_file`
    params = []
    strength = "D" if law.form == "deposit" else "A"
    for n, (v, s, u) in ({} if memory else fitted).items():
        sd = s if s is not None and math.isfinite(s) and s > 0 else max(0.1 * abs(v), 1e-3)
        if n == strength:
            lo, hi, off = 0.0, max(100.0 * abs(v), 1.0), 0.0
        elif n.startswith("a"):
            lo, hi, off = (HINGE_MIN if "hinge" in _kind_of(law, n) else -3.0), 6.0, v
        else:
            span = max(50.0 * abs(v), 50.0 * sd, 1e-9)
            lo, hi, off = v - span, v + span, v
            if n.endswith("_width") or n.endswith("_e"):
                lo, hi = (min(v / 1e3, v * 1e3), max(v / 1e3, v * 1e3)) if v != 0 else (
                    -span, span)
        lo, hi = min(lo, v), max(hi, v)
        doc = f"{n}: {'strength' if n == strength else 'constant'} of the law [{u}]"
        params.append(f'        "{keys[n]}": jw.EffectParameter(\n'
                      f'            1.0, {v!r}, {off!r}, {lo!r}, {hi!r},\n'
                      f'            "{doc}", scale={sd!r}),')
    ref_lines = [f"{SYMBOLS[t.variable].upper()}_REF = {t.ref!r}  # z_s of "
                 f"{t.variable} [{t.unit}]" for t in law.terms if t.kind in
                 ("power", "hinge", "exp") and not memory]
    ref_lines += [f"{SYMBOLS[t.variable].upper()}_CAP = {t.cap * t.ref!r}  # z_c of "
                  f"{t.variable} [{t.unit}]: the exponential held flat beyond it"
                  for t in law.terms if not memory and t.kind == "exp"
                  and math.isfinite(t.cap)]
    phi = "" if memory else " * ".join(_term_code(law, k, keys)
                                       for k in range(1, len(law.terms) + 1))
    if law.form != "deposit":
        ret = f'return rate * (1.0 + e["{keys["A"]}"] * phi)'
    else:
        ret = (f'kernel = (swept_kernel(ctx.load_angle, ctx.pressure.shape[1]) if ctx.swept '
               f'is None\n                  else ctx.swept)\n'
               f'        return rate + e["{keys["D"]}"] * DEPOSIT_UNIT_M * phi * kernel')
    loo = f"{loo_rmse_um:.4f}" if loo_rmse_um is not None else "-"
    terms = "the state s per node, 0 on a new surface" if memory else "; ".join(
        f"φ{k} = {term_formula(t, k)}" for k, t in enumerate(law.terms, 1))
    warn = f"\n{caveat}\n" if caveat else ""
    first = ("the wear law that `jaxwear diagnose --shape` found (issue 43)." if status ==
             "found" else "a LEAD, not a law found: the best law of the grammar that "
             "`jaxwear diagnose --shape` tried does not predict the left-out experiments as "
             "a found law must (DESIGN §7).")
    rng = {k: (float(lo), float(hi)) for k, (lo, hi) in (ranges or {}).items()}
    met = ", ".join(f"{k} {lo:.4g} to {hi:.4g}" for k, (lo, hi) in rng.items()) or "-"
    # a law with memory reads the cycle's own variables (time out of contact, contact
    # work), not the state variables calibrate and predict check a range of
    range_note = "" if memory else (f"Fitted on the states (the range met, STATE_RANGE): "
                                    f"{met}.\ncalibrate and predict flag this law used "
                                    f"beyond them.\n\n")
    header = f'''"""{EFFECT_NAME}: {first}
{warn}
Study: {study_path}

    {formula(law)}
    ({terms})

Constants (fitted through the wear loop with K_d and the clearances; value ± standard error):
{chr(10).join(lines_c)}

Fitted: RMSE {rmse_um:.4f} µm, on left-out experiments {loo} µm; noise {noise_um:.4f} µm.

Load it in a study:

    [model]
    effect_files = ["law.py"]    # path relative to the study file
    effects = ["{EFFECT_NAME}"]

{range_note}Its strength {strength} (key {keys[strength]}) is 0 off and the fitted value by default;
the other constants are parameters too (defaults: the fitted values), which calibrate can
refit (--fit K_d,clearance,{keys[strength]},...). In Python: `jw.register_effect(FoundLaw())`.
"""'''
    if memory:
        return memory_file_source(law, consts, keys=keys, header=header)
    return header + f'''

import jax
import jax.numpy as jnp

import jaxwear as jw
from jaxwear.effects import safe_power, state_variables, swept_kernel

DEPOSIT_UNIT_M = 1e-9  # D = 1 is 1 nm·rad of depth per step (volume D R_b B)
# the states the law was fitted on: variable -> (lo, hi) in its unit
STATE_RANGE = {rng!r}
{chr(10).join(ref_lines)}


class FoundLaw(jw.Effect):
    name = "{EFFECT_NAME}"
    parameters = {{
{chr(10).join(params)}
    }}
    signature = {("the law found by diagnose --shape: " + law.label)!r}
    uses_swept_kernel = {law.form == "deposit"!r}  # the kernel once per run: ctx.swept
    state_range = STATE_RANGE  # read by calibrate and predict (a flag beyond it)

    def local_rate(self, p, rate, ctx):
        e = p.effect_params
        z = state_variables(ctx.pressure, ctx.slide, ctx.dt, ctx.sliding_distance,
                            ctx.load_angle, ctx.load, ctx.worn_depth)
        z = {{k: jnp.broadcast_to(v, ctx.pressure.shape) for k, v in z.items()}}
        # p·v: the frictional power density's PV factor [MPa·m/s]
        z["pv_MPa_m_per_s"] = z["pressure_MPa"] * z["sliding_speed_m_per_s"]
        phi = {phi}
        {ret}
'''


def _kind_of(law: LawSpec, name: str) -> str:
    """The kind of the term an exponent `a<k>` belongs to."""
    try:
        return law.terms[int(name[1:]) - 1].kind
    except (ValueError, IndexError):
        return ""


def law_caveat(res) -> str:
    """The warning `law.py` opens with (`law.search.LawResult` `res`): worse than the shape's
    refitted correction, and the constants the data do not determine; "" where none."""
    b = res.best
    out = []
    if res.worse_than_shape:
        out.append(f"WARNING: no law of the grammar explains the misfit as well as the shape. "
                   f"This law reaches an RMSE of {b.rmse_um:.4f} µm where the shape's "
                   f"correction (missing_wear.py) reaches {res.shape_rmse_um:.4f} µm "
                   f"({b.rmse_um / res.shape_rmse_um - 1:+.0%}): a lead, not the law found.")
    if b is not None and b.undetermined:
        out.append(f"Constants not determined by the data (standard errors above their "
                   f"values): {', '.join(b.undetermined)}.")
    if b is not None and res.status == "lead":
        out.append("A lead, not a law found: " + "; ".join(res.lead_reasons) + ".")
    return "\n".join(textwrap.fill(x, 88) for x in out)
