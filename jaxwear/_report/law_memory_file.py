"""`law.py` for a law with memory (`effects.law_memory.MemoryLaw`): the effect file with its
hidden per-node state and the state's evolution written out (`law_file.law_file_source`
calls it for such a law).

Self-contained like the memoryless `law.py`: the formula and the constants (value ±
standard error) in its docstring, each fitted constant a parameter (its default the fitted
value), the references as module constants, and three hooks of plain jax.numpy: the
cycle's per-node variables, ds/dN (`memory_rate`, `memory_states = 1`: the wear loop
carries s, 0 on a new surface, and integrates it with the depth) and the rate's factor of
s (`local_rate`). Text only: the CLI writes it.
"""

from __future__ import annotations

import math

from jaxwear._physics.effects.law_memory import OUT_OF_CONTACT_PA, POWER_FLOOR, SYMBOLS


def memory_file_source(law, consts: dict, *, keys: dict, header: str) -> str:
    """The text of `law.py` for the fitted memory `law`, its `consts` ({NAME: (value,
    stderr, unit)}, `MemoryLaw.constants`), the study `keys` of its fitted constants
    ({NAME: key}) and the docstring's `header` (everything before the code: the same as a
    memoryless law's)."""
    params = []
    for n, key in keys.items():
        v, s, u = consts[n]
        sd = s if s is not None and math.isfinite(s) and s > 0 else max(0.1 * abs(v), 1e-6)
        if n == "A":
            lo, hi, off, log = 0.0, max(100.0 * abs(v), 1.0), 0.0, False
        elif n == "a":
            lo, hi, off, log = 0.0, 8.0, v, False
        else:  # a rate per cycle or the step's width: positive, fitted in log space
            lo, hi, off, log = min(v / 1e3, 1e-12), max(v * 1e3, 1.0), v, True
            sd = 0.5
        lo, hi = min(lo, v), max(hi, v)
        doc = f"{n}: {'strength' if n == 'A' else 'constant'} of the law [{u}]"
        params.append(f'        "{key}": jw.EffectParameter(\n'
                      f'            1.0, {v!r}, {off!r}, {lo!r}, {hi!r},\n'
                      f'            "{doc}", log={log!r}, scale={sd!r}),')
    e = {n: f'e["{k}"]' for n, k in keys.items()}
    if law.form == "film":
        refs = (f"TOFF_REF = {law.ref!r}  # t_off's reference [s]\n"
                f"WC_REF = {law.ref2!r}  # the contact work's reference [kJ/m²]\n"
                f"SPAN = {law.span!r}  # largest t_off/TOFF_REF or wc/WC_REF met in the fit")
        rate = (f'{e["k1"]} * (1.0 - s) * z["time_out_of_contact_s"] / TOFF_REF\n'
                f'                - {e["k2"]} * s * z["contact_work_kJ_per_m2"] / WC_REF')
        factor = f'1.0 / (1.0 + {e["A"]} * jnp.maximum(s, 0.0))'
        stiff = (f'        # |d(ds/dN)/ds| = k1 t_off/TOFF_REF + k2 wc/WC_REF: the integrator\'s '
                 f'stability bound\n        return ({e["k1"]} + {e["k2"]}) * SPAN')
    else:
        sym = SYMBOLS[law.variable].upper()
        unit = consts[f"{SYMBOLS[law.variable]}_ref"][2]
        refs = f"{sym}_REF = {law.ref!r}  # the driver's reference [{unit}]"
        rate = (f'{e["k1"]} * safe_power(jnp.maximum(z["{law.variable}"] / {sym}_REF, '
                f'{POWER_FLOOR}), {e["a"]})')
        factor = f'1.0 + {e["A"]} * jax.nn.sigmoid((s - 1.0) / {e["width"]})'
        stiff = "        return jnp.zeros(())  # the damage does not feed back on itself"
    return f'''{header}

import jax
import jax.numpy as jnp

import jaxwear as jw
from jaxwear.effects import safe_power

OUT_OF_CONTACT_PA = {OUT_OF_CONTACT_PA!r}  # a node below it is out of contact
{refs}


def cycle_variables(ctx):
    """Per node over one cycle (nodes,): peak pressure [MPa], contact work Σ_i p_ij dS_i
    [kJ/m²], time out of contact [s]."""
    p = ctx.pressure
    return {{"peak_pressure_MPa": jnp.max(p, axis=0) * 1e-6,
            "contact_work_kJ_per_m2": (ctx.slide @ p) * 1e-3,
            "time_out_of_contact_s": ctx.dt @ (p < OUT_OF_CONTACT_PA).astype(ctx.dt.dtype)}}


class FoundLaw(jw.Effect):
    name = "found_law"
    parameters = {{
{chr(10).join(params)}
    }}
    signature = {("the law with memory found by diagnose --shape: " + law.label)!r}
    memory_states = 1  # s per node, 0 on a new surface: the wear loop carries it

    def memory_rate(self, p, ctx):
        """ds/dN per cycle (1, nodes) at s = ctx.memory[0]."""
        e = p.effect_params
        z = cycle_variables(ctx)
        s = ctx.memory[0]
        return ({rate})[None, :]

    def local_rate(self, p, rate, ctx):
        e = p.effect_params
        s = ctx.memory[0]
        return rate * ({factor})[None, :]

    def memory_stiffness(self, p):
        e = p.effect_params
{stiff}
'''
