"""Laws with memory (issue 48 item 4): a hidden per-node state s that the cycle drives, and
a wear rate that is a factor of it, as one effect whose structure is data (the memory
counterpart of `effects.law`'s grammar; the law search fits it through the wear loop).

Per node and cycle the contact gives three variables (`memory_variables`): the peak
pressure p_max [MPa], the contact work w_c = Σ_i p_ij dS_i [kJ/m²] and the time out of
contact t_off = Σ_i Δt_i [p_ij = 0] [s]. Two forms, s = 0 on a new surface:

| form | ds/dN (per cycle) | rate factor |
|---|---|---|
| `damage` | k1 (z/z_ref)^a, z = p_max or w_c | 1 + A σ((s − 1)/w) |
| `film` | k1 (1 − s) t_off/t_ref − k2 s w_c/w_ref | 1/(1 + A s) |

- **damage**: an accumulation (Miner's sum: fatigue, delamination); once s passes 1 the
  surface gives way and the rate steps up by A (σ the logistic function, w its width in
  units of the state). Its scale is k1: the node fails after about 1/(k1 (z/z_ref)^a)
  cycles.
- **film**: a protective film (tribofilm, oxide) that forms while the node is out of
  contact and is worn off by the contact's work; its steady state is
  s* = g/(g + (k2/k1) h) (g, h the normalised t_off, w_c), reached in about 1/(k1 g + k2 h)
  cycles; a full film divides the rate by 1 + A.

A = 0 is the model as written (nesting). The state rides in the wear loop's state vector
(`Effect.memory_rate`, `RateContext.memory`): the integrator's steps and gradients cover
it. Why one effect with the form, the variable and the references held: as for
`effects.law`, every memory candidate runs on one compiled program; only `MEMORY_KEYS` are
fitted. `MemoryLaw` is one candidate (its study values, free keys, constants and formula,
the interface of `effects.law.LawSpec` the search and `law.py` use).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._physics.effects._base import Effect, safe_power
from jaxwear._physics.effects.parameter import EffectParameter

MEMORY_EFFECT = "law_memory"
FORMS = ("damage", "film")
# the per-node variables of one cycle a state may be driven by; index = position
MEMORY_VARIABLES = ("peak_pressure_MPa", "contact_work_kJ_per_m2", "time_out_of_contact_s")
UNITS = {"peak_pressure_MPa": "MPa", "contact_work_kJ_per_m2": "kJ/m²",
         "time_out_of_contact_s": "s"}
SYMBOLS = {"peak_pressure_MPa": "pmax", "contact_work_kJ_per_m2": "wc",
           "time_out_of_contact_s": "toff"}
# the continuous constants: the columns of the one compiled memory model (a form's unused
# ones held)
MEMORY_KEYS = ("mem_gain", "mem_k1", "mem_k2", "mem_a", "mem_width")
FREE = {"damage": ("mem_gain", "mem_k1", "mem_a", "mem_width"),
        "film": ("mem_gain", "mem_k1", "mem_k2")}
OUT_OF_CONTACT_PA = 1.0  # a node below it is out of contact (the solve's p is exactly 0)
POWER_FLOOR = 1e-3  # z/z_ref below it read as it (a node that never presses)
MAX_RATE = 0.05  # per cycle: k1, k2 above it relax in < 20 cycles (a memoryless factor)


def _p(default, off, lower, upper, doc, *, log=False, scale=1.0):
    return EffectParameter(1.0, default, off, lower, upper, doc, log=log, scale=scale)


def _parameters() -> dict:
    return {
        "mem_gain": _p(0.0, 0.0, 0.0, 1e3, "A: strength of the state's factor [-]", scale=0.1),
        "mem_k1": _p(1e-4, 1e-4, 1e-9, MAX_RATE, "k1: accumulation (damage) or formation "
                     "(film) per cycle at the reference [1/cycle]", log=True, scale=0.5),
        "mem_k2": _p(1e-4, 1e-4, 1e-9, MAX_RATE, "k2: removal of the film per cycle at the "
                     "reference work [1/cycle]", log=True, scale=0.5),
        "mem_a": _p(1.0, 1.0, 0.0, 8.0, "a: exponent of the damage's driver [-]", scale=0.2),
        "mem_width": _p(0.2, 0.2, 0.02, 2.0, "w: width of the damage's step in s [-]",
                        log=True, scale=0.3),
        "mem_form": _p(0.0, 0.0, 0.0, 1.0, "form: 0 damage, 1 film (held)"),
        "mem_var": _p(0.0, 0.0, 0.0, len(MEMORY_VARIABLES) - 1.0,
                      "the damage's driver (index into MEMORY_VARIABLES, held)"),
        "mem_ref_1": _p(1.0, 1.0, 1e-300, 1e300, "z_ref of the damage's driver, or t_ref of "
                        "the film's formation (held, the variable's unit)"),
        "mem_ref_2": _p(1.0, 1.0, 1e-300, 1e300, "w_ref of the film's removal (held) [kJ/m²]"),
        "mem_span": _p(4.0, 4.0, 0.0, 1e300, "largest normalised t_off or w_c met (held): "
                       "the film's relaxation bound"),
    }


def memory_variables(pressure, slide, dt, xp=jnp) -> dict:
    """{name: (nodes,)} of `MEMORY_VARIABLES` over one cycle: `pressure` (steps, nodes)
    [Pa], `slide` dS_i (steps,) [m], `dt` (steps,) [s]."""
    return {"peak_pressure_MPa": xp.max(pressure, axis=0) * 1e-6,
            "contact_work_kJ_per_m2": (slide @ pressure) * 1e-3,
            "time_out_of_contact_s": dt @ (pressure < OUT_OF_CONTACT_PA).astype(dt.dtype)}


def memory_terms(e: dict, z: dict, s):
    """(ds/dN (nodes,) [1/cycle], rate factor (nodes,)) of the held form at state s
    (nodes,), from the parameters `e` and the cycle's variables `z` (`memory_variables`)."""
    film = e["mem_form"] > 0.5
    Z = jnp.stack([z[n] for n in MEMORY_VARIABLES])
    idx = jnp.clip(jnp.round(e["mem_var"]).astype(jnp.int32), 0, len(MEMORY_VARIABLES) - 1)
    x = jnp.maximum(jnp.take(Z, idx, axis=0) / e["mem_ref_1"], POWER_FLOOR)
    damage_rate = e["mem_k1"] * safe_power(x, e["mem_a"])
    g = z["time_out_of_contact_s"] / e["mem_ref_1"]
    h = z["contact_work_kJ_per_m2"] / e["mem_ref_2"]
    film_rate = e["mem_k1"] * (1.0 - s) * g - e["mem_k2"] * s * h
    damage_factor = 1.0 + e["mem_gain"] * jax.nn.sigmoid((s - 1.0) / e["mem_width"])
    film_factor = 1.0 / (1.0 + e["mem_gain"] * jnp.maximum(s, 0.0))
    return (jnp.where(film, film_rate, damage_rate),
            jnp.where(film, film_factor, damage_factor))


class LawMemory(Effect):
    """The memory law with its form as held parameters (module docstring)."""

    name = MEMORY_EFFECT
    parameters = _parameters()
    signature = "a law with memory (diagnose's law search)"
    memory_states: ClassVar[int] = 1

    def _terms(self, p, ctx):
        z = memory_variables(ctx.pressure, ctx.slide, ctx.dt)
        return memory_terms(p.effect_params, z, ctx.memory[0])

    def memory_rate(self, p, ctx):
        return self._terms(p, ctx)[0][None, :]

    def local_rate(self, p, rate, ctx):
        return rate * self._terms(p, ctx)[1][None, :]

    def memory_stiffness(self, p):
        # |∂(ds/dN)/∂s| of the film: k1 g + k2 h ≤ (k1 + k2) × the largest normalised
        # variable met; the damage does not feed back on itself
        e = p.effect_params
        return jnp.where(e["mem_form"] > 0.5, (e["mem_k1"] + e["mem_k2"]) * e["mem_span"],
                         0.0)


LAW_MEMORY = LawMemory()


@dataclass(frozen=True)
class _Var:
    """A term's variable, as `effects.law.Term` shows it to the search (`as_shape`)."""

    kind: str
    variable: str
    ref: float


@dataclass(frozen=True)
class MemoryLaw:
    """A memory candidate: `form` ("damage", "film"), the damage's driver `variable` and
    reference `ref` (film: t_ref [s] of the formation and `ref2` w_ref [kJ/m²] of the
    removal), its strength A and constants k1, k2 [1/cycle], a, width; `span` the largest
    normalised variable met (the film's relaxation bound, `LawMemory.memory_stiffness`)."""

    form: str
    variable: str
    ref: float
    ref2: float = 1.0
    strength: float = 0.0
    k1: float = 1e-4
    k2: float = 1e-4
    a: float = 1.0
    width: float = 0.2
    span: float = 4.0

    memory: ClassVar[bool] = True
    model_effects: ClassVar[tuple] = (MEMORY_EFFECT,)
    columns: ClassVar[tuple] = MEMORY_KEYS
    strength_key: ClassVar[str] = "mem_gain"

    @property
    def terms(self) -> tuple:
        if self.form == "film":
            return (_Var("power", "time_out_of_contact_s", self.ref),
                    _Var("power", "contact_work_kJ_per_m2", self.ref2))
        return (_Var("power", self.variable, self.ref),)

    def free_keys(self) -> tuple:
        return FREE[self.form]

    def values(self) -> dict:
        """Every parameter of `LAW_MEMORY` for this law (study keys, their units)."""
        return {"mem_gain": float(self.strength), "mem_k1": self.k1, "mem_k2": self.k2,
                "mem_a": self.a, "mem_width": self.width,
                "mem_form": float(FORMS.index(self.form)),
                "mem_var": float(MEMORY_VARIABLES.index(self.variable)),
                "mem_ref_1": self.ref, "mem_ref_2": self.ref2, "mem_span": self.span}

    def with_values(self, values: dict) -> MemoryLaw:
        """This law with its fitted constants from `values` (study keys)."""
        kw = {f: float(values.get(k, getattr(self, f))) for f, k in
              (("strength", "mem_gain"), ("k1", "mem_k1"), ("k2", "mem_k2"),
               ("a", "mem_a"), ("width", "mem_width"))}
        return replace(self, **kw)

    @property
    def label(self) -> str:
        if self.form == "film":
            return "film: forms out of contact, worn by the contact work"
        return f"damage: power({self.variable})"

    def constants(self, se: dict | None = None) -> dict:
        """{NAME: (value, stderr, unit)} (`effects.law.constants`), the references fixed
        (stderr 0). `se`: standard errors of the study keys (absent: NaN)."""
        se = se or {}

        def s(key):
            v = se.get(key, math.nan)
            return v if v is not None and math.isfinite(v) else math.nan

        out = {"A": (self.strength, s("mem_gain"), "-"),
               "k1": (self.k1, s("mem_k1"), "1/cycle")}
        if self.form == "film":
            out["k2"] = (self.k2, s("mem_k2"), "1/cycle")
            out["toff_ref"] = (self.ref, 0.0, "s")
            out["wc_ref"] = (self.ref2, 0.0, "kJ/m²")
        else:
            out["a"] = (self.a, s("mem_a"), "-")
            out["width"] = (self.width, s("mem_width"), "-")
            out[f"{SYMBOLS[self.variable]}_ref"] = (self.ref, 0.0, UNITS[self.variable])
        return out

    def formula(self) -> str:
        if self.form == "film":
            return ("rate = K_d p dS / (1 + A s),  ds/dN = k1 (1 − s) toff/toff_ref − k2 s "
                    "wc/wc_ref,  s = 0 at the start   [toff = time out of contact per cycle, "
                    "wc = contact work per cycle, per node]")
        z = SYMBOLS[self.variable]
        return (f"rate = K_d p dS · (1 + A / (1 + exp(−(s − 1)/width))),  ds/dN = k1 "
                f"({z}/{z}_ref)^a,  s = 0 at the start   [{z} = {self.variable} per cycle, "
                f"per node]")

    def undetermined(self, se: dict) -> tuple:
        """Names of the constants the data do not determine (`law.search.undetermined`): A with
        its standard error above its value; k1, k2, width (fitted in log space: their
        standard errors are the values') above their values; the exponent not known to
        within 1."""
        def bad(key, limit):
            s = se.get(key, math.nan)
            return not (s is not None and math.isfinite(s) and s <= limit)

        out = []
        if bad("mem_gain", abs(self.strength)):
            out.append("A")
        if bad("mem_k1", self.k1):
            out.append("k1")
        if self.form == "film" and bad("mem_k2", self.k2):
            out.append("k2")
        if self.form == "damage":
            if bad("mem_a", 1.0):
                out.append("a")
            if bad("mem_width", self.width):
                out.append("width")
        return tuple(out)


def memory_numpy(law: MemoryLaw, pressure, slide, dt, s):
    """(ds/dN, rate factor) (nodes,) of `law` at state s with numpy: the formula as
    written (`MemoryLaw.formula`), for checks independent of the traced selectors."""
    p = np.asarray(pressure, float)
    z = memory_variables(p, np.asarray(slide, float), np.asarray(dt, float), xp=np)
    s = np.asarray(s, float)
    if law.form == "film":
        ds = (law.k1 * (1 - s) * z["time_out_of_contact_s"] / law.ref
              - law.k2 * s * z["contact_work_kJ_per_m2"] / law.ref2)
        return ds, 1.0 / (1.0 + law.strength * np.maximum(s, 0.0))
    x = np.maximum(z[law.variable] / law.ref, POWER_FLOOR)
    return (law.k1 * x ** law.a,
            1.0 + law.strength / (1.0 + np.exp(-(s - 1.0) / law.width)))
