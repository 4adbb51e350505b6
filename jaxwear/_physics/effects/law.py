"""A small grammar of physical wear laws over the state variables (issue 43 item 2), as one
effect whose structure is data: the law search (`diagnose.law.search`) fits every candidate of
the grammar with one compiled model.

A law is one or two terms φ over state variables z (`effects.shape.state_variables`),
each on the normalised x = z / z_s (z_s > 0, a fixed reference of the variable: the
wear-weighted median of the states met in the data):

| kind | φ(x) | constants |
|---|---|---|
| `power` | x^a | a |
| `hinge` | max(x − x0, 0)^a (a ≥ 0.5) | x0, a |
| `step` | 1 / (1 + exp(−(x − x0)/w)) | x0, w > 0 |
| `exp` | exp(b (x − 1)) | b |

Φ = φ1(x1) · φ2(x2) (φ2 ≡ 1 for a law of one term), in the two forms of the shape
(DESIGN §7):

- **factor**: the local rate K_d p_ij dS_i (1 + A Φ), A ≥ 0: more of the wear Archard
  already makes where Φ is large (a pressure threshold, a PV limit, a softer sublayer);
- **deposit**: + D · 1 nm·rad · Φ κ_ij per step, D ≥ 0, κ the kernel of where the pin
  presses (`effects.shape.swept_kernel`): extra wear not tied to sliding (impacts,
  fretting, cold flow), Φ over the variables of events in the cycle.

An exponential may be **bounded** (`law.search.bounded`): held flat beyond a cap
x_c = z_c / z_s above every state met, `exp(b (min(x, x_c) − 1))`, where it would otherwise
make the rate grow without bound where a prediction goes (a longer test, a higher load);
the cap is a held value (`law_cap_k`, `CAP_NONE` where there is none), never fitted.

A = D = 0 is the model as written (nesting). Why one effect with the kinds, variables and
references as held parameters (`LawSpec.held`): they are values in the parameters, not
structure, so every candidate runs on the program compiled once (a compilation of the wear
loop costs more than a fit's evaluations); only the continuous constants are fitted.

`LawSpec` is one candidate: its study parameters, free keys, formula and constants in the
variables' units. `LAW_SEARCH` is registered only while a search runs (`searching`): it is
not a library candidate (`diagnose` never screens it), and its 17 parameters stay out of
every other model's parameters (19: the two caps held too).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._physics.effects._base import Effect, safe_power, scoped_effects
from jaxwear._physics.effects.law_memory import LAW_MEMORY
from jaxwear._physics.effects.parameter import EffectParameter
from jaxwear._physics.effects.shape import DEPOSIT_UNIT_M, VARIABLES, state_variables, swept_kernel

LAW_EFFECT = "law_search"
# the variables a law may depend on (the periodic angles are where and when, not states a
# material law depends on); index = position
LAW_VARIABLES = ("pressure_MPa", "sliding_speed_m_per_s", "sliding_distance_m",
                 "load_turn_rate_deg_per_s", "load_turn_deg_per_deg", "load_N",
                 "worn_depth_um", "pv_MPa_m_per_s")
# states a law may depend on that are made of the shape's variables (`derived_states`):
# name -> (unit, its variables). The frictional power density's p·v (the PV factor of
# bearing design: the frictional heat per unit area is μ p v, the flash temperature's
# driver, and a polymer's PV limit a step in it) is a law's variable, not one of the
# shape's: the shape's variables are the states themselves, and a product of two is what
# the law's products and this derived state are for
DERIVED = {"pv_MPa_m_per_s": ("MPa·m/s", ("pressure_MPa", "sliding_speed_m_per_s"))}
# a deposit is made per step by an event of the cycle: its variables are per step
DEPOSIT_LAW_VARIABLES = ("sliding_speed_m_per_s", "sliding_distance_m",
                         "load_turn_rate_deg_per_s", "load_turn_deg_per_deg", "load_N")
KINDS = ("none", "power", "hinge", "step", "exp")
# the fitted constants of each kind (term k's keys are `law_<c>_<k>`)
KIND_CONSTANTS = {"none": (), "power": ("a",), "hinge": ("x0", "a"), "step": ("x0", "w"),
                  "exp": ("b",)}
HINGE_MIN_EXPONENT = 0.5  # a hinge's slope at its threshold stays finite
POWER_FLOOR = 1e-3  # x below it read as it (a power law of a state that starts at 0)
# an exponential's cap x_c where it has none (`Term.cap` inf): far above any state, so
# min(x, CAP_NONE) = x (finite, so the held parameter stays a number the packing checks)
CAP_NONE = 1e300


def _p(default, off, lower, upper, doc, *, log=False, scale=1.0):
    return EffectParameter(1.0, default, off, lower, upper, doc, log=log, scale=scale)


def _parameters() -> dict:
    out = {
        "law_gain": _p(0.0, 0.0, 0.0, 1e6, "A: strength of the factor law [-]", scale=0.1),
        "law_deposit": _p(0.0, 0.0, 0.0, 1e6, "D: strength of the deposit law [nm·rad per "
                          "step]", scale=1e-3),
        "law_form": _p(0.0, 0.0, 0.0, 1.0, "form: 0 factor, 1 deposit (held)"),
    }
    for k in (1, 2):
        out.update({
            f"law_a_{k}": _p(1.0, 1.0, -3.0, 6.0, f"a{k}: exponent [-]", scale=0.1),
            f"law_x0_{k}": _p(1.0, 1.0, -5.0, 50.0, f"x0{k}: threshold or centre, in "
                              f"units of the reference [-]", scale=0.05),
            f"law_w_{k}": _p(0.1, 0.1, 1e-3, 10.0, f"w{k}: width of the step, in units of "
                             f"the reference [-]", log=True, scale=0.1),
            f"law_b_{k}": _p(0.0, 0.0, -50.0, 50.0, f"b{k}: rate of the exponential per "
                             f"reference [-]", scale=0.1),
            f"law_var_{k}": _p(0.0, 0.0, 0.0, len(LAW_VARIABLES) - 1.0,
                               f"variable of term {k} (index, held)"),
            f"law_kind_{k}": _p(0.0, 0.0, 0.0, len(KINDS) - 1.0,
                                f"kind of term {k} (index, held)"),
            f"law_ref_{k}": _p(1.0, 1.0, 1e-300, 1e300, f"z_s of term {k}: the reference "
                               f"(held, the variable's unit)"),
            f"law_cap_{k}": _p(CAP_NONE, CAP_NONE, -1e300, CAP_NONE,
                               f"x_c of term {k}: an exponential held flat beyond x = x_c "
                               f"(held, in units of the reference; {CAP_NONE:g}: none)"),
        })
    return out


def law_term(kind, x, a, x0, w, b, cap=CAP_NONE):
    """φ(x) of `kind` (index into `KINDS`, traced) at x (...): the kind's branch alone runs
    (`lax.switch`: the index is a held parameter, the same in every tangent of a Jacobian;
    where a `vmap` batches it, every branch runs and one is selected, all finite, so the
    unselected ones' gradients are zero, never NaN). `cap`: the exponential's x_c, beyond
    which it is held flat (module docstring).

    Why a switch: with every kind computed and one selected (`jnp.select`), and every
    variable broadcast and stacked before one was taken (`law_phi`), a law's evaluation on
    the generator's fatigue study (48 x 72, 11 Jacobian columns) took 0.73-0.75 s against
    0.24 s now, the same Jacobian bitwise (a step in p·v; 0.55 -> 0.28-0.30 s for a power
    law and a power·step)."""
    k = jnp.clip(jnp.round(kind), 0, len(KINDS) - 1).astype(jnp.int32)
    return jax.lax.switch(k, [
        lambda: jnp.ones_like(x),
        lambda: safe_power(jnp.maximum(x, POWER_FLOOR), a),
        lambda: safe_power(jnp.maximum(x - x0, 0.0), jnp.maximum(a, HINGE_MIN_EXPONENT)),
        lambda: jax.nn.sigmoid((x - x0) / w),
        lambda: jnp.exp(jnp.clip(b * (jnp.minimum(x, cap) - 1.0), -50.0, 50.0))])


def derived_states(z: dict) -> dict:
    """`z` ({state variable: values}, `effects.shape.state_variables`) with the `DERIVED`
    states added: p·v [MPa·m/s] = pressure_MPa × sliding_speed_m_per_s (broadcast)."""
    return {**z, "pv_MPa_m_per_s": z["pressure_MPa"] * z["sliding_speed_m_per_s"]}


def variable_unit(name: str) -> str:
    """The unit of a law's variable (a shape variable's or a `DERIVED` one's)."""
    return DERIVED[name][0] if name in DERIVED else VARIABLES[name][0]


def law_phi(e: dict, z: dict, shape) -> jax.Array:
    """Φ = φ1 φ2 (steps, nodes) from the law's parameters `e` and the states `z`."""
    z = derived_states(z)
    phi = jnp.ones(shape)
    for k in (1, 2):
        idx = jnp.clip(jnp.round(e[f"law_var_{k}"]).astype(jnp.int32), 0,
                       len(LAW_VARIABLES) - 1)
        # the term's variable alone (a held index: one branch runs), not every variable
        # broadcast and stacked
        x = jax.lax.switch(idx, [lambda n=n: jnp.broadcast_to(z[n], shape).astype(phi.dtype)
                                 for n in LAW_VARIABLES]) / e[f"law_ref_{k}"]
        phi = phi * law_term(e[f"law_kind_{k}"], x, e[f"law_a_{k}"], e[f"law_x0_{k}"],
                             e[f"law_w_{k}"], e[f"law_b_{k}"], e[f"law_cap_{k}"])
    return phi


class LawSearch(Effect):
    """The grammar's law with its structure as held parameters (module docstring)."""

    name = LAW_EFFECT
    parameters = _parameters()
    signature = "a law of the grammar (diagnose's law search)"
    uses_swept_kernel = True  # computed once per run (`RateContext.swept`)

    def local_rate(self, p, rate, ctx):
        e = p.effect_params
        shape = ctx.pressure.shape
        z = state_variables(ctx.pressure, ctx.slide, ctx.dt, ctx.sliding_distance,
                            ctx.load_angle, ctx.load, ctx.worn_depth)
        phi = law_phi(e, z, shape)
        out = rate * (1.0 + e["law_gain"] * phi)
        # the deposit's kernel only where the form is the deposit (a held value: both
        # branches compiled once, one run)
        return out + jax.lax.cond(
            e["law_form"] > 0.5,
            lambda: DEPOSIT_UNIT_M * e["law_deposit"] * phi
            * (swept_kernel(ctx.load_angle, shape[1]) if ctx.swept is None else ctx.swept),
            lambda: jnp.zeros(shape))


LAW_SEARCH = LawSearch()


@contextlib.contextmanager
def searching():
    """`LAW_SEARCH` and the laws with memory (`effects.law_memory`) registered for the
    duration, in this context only (`scoped_effects`: the threads it starts through
    `_core.background` see them, no other thread does; module docstring: never a
    candidate)."""
    with scoped_effects(LAW_SEARCH, LAW_MEMORY):
        yield LAW_SEARCH


@dataclass(frozen=True)
class Term:
    """One term: its kind, variable, reference z_s (the variable's unit) and constants
    (normalised: x0, w in units of z_s); `cap`: an exponential's x_c = z_c / z_s beyond
    which it is held flat (`law.search.bounded`; inf: none)."""

    kind: str
    variable: str
    ref: float
    a: float = 1.0
    x0: float = 1.0
    w: float = 0.1
    b: float = 0.0
    cap: float = math.inf

    @property
    def unit(self) -> str:
        return variable_unit(self.variable)


@dataclass(frozen=True)
class LawSpec:
    """A candidate law: its form, one or two terms and its strength (A for a factor, D
    for a deposit)."""

    form: str
    terms: tuple
    strength: float = 0.0

    @property
    def strength_key(self) -> str:
        return "law_gain" if self.form == "factor" else "law_deposit"

    def free_keys(self) -> tuple:
        """The fitted constants: the strength and each term's (`KIND_CONSTANTS`)."""
        keys = [self.strength_key]
        for k, t in enumerate(self.terms, 1):
            keys += [f"law_{c}_{k}" for c in KIND_CONSTANTS[t.kind]]
        return tuple(keys)

    def values(self) -> dict:
        """Every parameter of `LAW_SEARCH` for this law (study keys, their units)."""
        out = {"law_gain": 0.0, "law_deposit": 0.0,
               "law_form": 0.0 if self.form == "factor" else 1.0}
        out[self.strength_key] = float(self.strength)
        for k in (1, 2):
            t = self.terms[k - 1] if k <= len(self.terms) else Term("none", LAW_VARIABLES[0],
                                                                     1.0)
            out.update({f"law_a_{k}": t.a, f"law_x0_{k}": t.x0, f"law_w_{k}": t.w,
                        f"law_b_{k}": t.b,
                        f"law_cap_{k}": t.cap if t.cap < CAP_NONE else CAP_NONE,
                        f"law_var_{k}": float(LAW_VARIABLES.index(t.variable)),
                        f"law_kind_{k}": float(KINDS.index(t.kind)), f"law_ref_{k}": t.ref})
        return out

    def with_values(self, values: dict) -> LawSpec:
        """This law with its fitted constants from `values` (study keys; a cap where
        `values` holds one, else its own)."""
        terms = []
        for k, t in enumerate(self.terms, 1):
            kw = {c: float(values.get(f"law_{c}_{k}", getattr(t, c)))
                  for c in ("a", "x0", "w", "b", "cap")}
            if kw["cap"] >= CAP_NONE:
                kw["cap"] = math.inf
            terms.append(Term(t.kind, t.variable, t.ref, **kw))
        return LawSpec(self.form, tuple(terms),
                       float(values.get(self.strength_key, self.strength)))

    @property
    def label(self) -> str:
        return f"{self.form}: " + " · ".join(f"{t.kind}({t.variable})" for t in self.terms)


# symbols of the variables in formulas and constant names (ASCII: they name study keys)
SYMBOLS = {"pressure_MPa": "p", "sliding_speed_m_per_s": "v", "sliding_distance_m": "S",
           "load_turn_rate_deg_per_s": "omega", "load_turn_deg_per_deg": "turn",
           "load_N": "W", "worn_depth_um": "h", "pv_MPa_m_per_s": "pv"}


def constants(law: LawSpec, se: dict | None = None) -> dict:
    """{NAME: (value, stderr, unit)}: the law's constants in the variables' units (the
    normalised ones times z_s; delta method for the errors), the strength first and each
    reference, and an exponential's cap `{sym}_cap` where it is bounded, as a fixed
    constant (stderr 0: chosen, not fitted). `se`: standard errors of the study keys
    (absent: NaN)."""
    if getattr(law, "memory", False):  # a law with memory (`effects.law_memory`)
        return law.constants(se)
    se = se or {}

    def s(key, factor=1.0):
        v = se.get(key, math.nan)
        return abs(factor) * v if v is not None and math.isfinite(v) else math.nan

    out = {}
    if law.form == "factor":
        out["A"] = (law.strength, s("law_gain"), "-")
    else:
        out["D"] = (law.strength, s("law_deposit"), "nm·rad per step")
    for k, t in enumerate(law.terms, 1):
        sym = f"{SYMBOLS[t.variable]}"
        u = t.unit
        if t.kind in ("power", "hinge", "exp"):
            out[f"{sym}_ref"] = (t.ref, 0.0, u)
        if t.kind == "power":
            out[f"a{k}"] = (t.a, s(f"law_a_{k}"), "-")
        elif t.kind == "hinge":
            out[f"{sym}0"] = (t.x0 * t.ref, s(f"law_x0_{k}", t.ref), u)
            out[f"a{k}"] = (max(t.a, HINGE_MIN_EXPONENT), s(f"law_a_{k}"), "-")
        elif t.kind == "step":
            out[f"{sym}0"] = (t.x0 * t.ref, s(f"law_x0_{k}", t.ref), u)
            # w is fitted in log space: its stderr from the caller is already the value's
            out[f"{sym}_width"] = (t.w * t.ref, s(f"law_w_{k}", t.ref), u)
        elif t.kind == "exp":
            # exp(b (z/z_s − 1)) = exp((z − z_s)/z0), z0 = z_s / b
            flat = abs(t.b) < 1e-12  # a flat exponential: its scale beyond any range
            z0 = 1e12 * t.ref if flat else t.ref / t.b
            out[f"{sym}_e"] = (z0, math.nan if flat else s(f"law_b_{k}", t.ref / t.b ** 2),
                               u)
            if math.isfinite(t.cap):
                out[f"{sym}_cap"] = (t.cap * t.ref, 0.0, u)
    return out


def term_formula(t: Term, k: int) -> str:
    """φ_k in the variable's own symbols and named constants (`constants`)."""
    z = SYMBOLS[t.variable]
    if t.kind == "power":
        return f"({z}/{z}_ref)^a{k}"
    if t.kind == "hinge":
        return f"(max({z} − {z}0, 0)/{z}_ref)^a{k}"
    if t.kind == "step":
        return f"1/(1 + exp(−({z} − {z}0)/{z}_width))"
    if t.kind == "exp":
        if math.isfinite(t.cap):
            return f"exp((min({z}, {z}_cap) − {z}_ref)/{z}_e)"
        return f"exp(({z} − {z}_ref)/{z}_e)"
    return "1"


def formula(law: LawSpec) -> str:
    """The law in words: the local rate with its constants named (`constants`)."""
    if getattr(law, "memory", False):
        return law.formula()
    phi = " · ".join(term_formula(t, k) for k, t in enumerate(law.terms, 1))
    where = ", ".join(f"{SYMBOLS[t.variable]} = {t.variable}" for t in law.terms)
    if law.form == "factor":
        return f"rate = K_d p dS · (1 + A · {phi})   [{where}]"
    return (f"rate = K_d p dS + D · 1 nm·rad · {phi} · κ (where the pin presses)   "
            f"[{where}]")


def law_phi_numpy(law: LawSpec, z: dict):
    """Φ of `law` at the states `z` ({variable: array}) with numpy: the formula as written
    (`formula`), for checks independent of the traced selectors."""
    out = 1.0
    if "pv_MPa_m_per_s" not in z and {"pressure_MPa", "sliding_speed_m_per_s"} <= set(z):
        z = derived_states({k: np.asarray(v, float) for k, v in z.items()})
    for t in law.terms:
        x = np.asarray(z[t.variable], float) / t.ref
        if t.kind == "power":
            out = out * np.maximum(x, POWER_FLOOR) ** t.a
        elif t.kind == "hinge":
            out = out * np.maximum(x - t.x0, 0.0) ** max(t.a, HINGE_MIN_EXPONENT)
        elif t.kind == "step":
            out = out / (1.0 + np.exp(-(x - t.x0) / t.w))
        elif t.kind == "exp":
            out = out * np.exp(np.clip(t.b * (np.minimum(x, t.cap) - 1.0), -50.0, 50.0))
    return out
