"""`missing_wear.py`: the refitted shape of the missing wear as an effect file (design.md §7).

A self-contained Python file: the correction is data inside it (each variable's knots and
B-spline coefficients), evaluated by a dozen lines of plain jax.numpy, so the user can read
it, keep it, replace the spline by a physical law, and load it in any study with
`[model] effect_files = ["missing_wear.py"]` and `effects = ["missing_wear"]`. Its one
strength `missing_wear_gain` is 0 (off: the model as written) to 1 (as fitted).
"""

from __future__ import annotations

import json
import textwrap

from jaxwear._analyses.diagnose.shape.text import FORM_WORDS
from jaxwear._physics.effects.shape import VARIABLES

TEMPLATE = '''"""missing_wear: the shape of the missing wear that `jaxwear diagnose --shape` found.

Study: {study}
Found: {sentence}

The correction is {form_words}, along {variables}. It is data below (B-spline knots and
coefficients, fitted through the wear loop), so this file is all you need:

    [model]
    effect_files = ["missing_wear.py"]    # path relative to the study file
    effects = ["missing_wear"]            # switched on: its gain is fitted from 0 (off)

`missing_wear_gain` = 0 is the model as written, 1 the correction as fitted. Edit
`correction(z)` (or the whole `local_rate`) into a physical law (an impact energy at the
load's reversals, a pressure threshold, ...) with its own parameters, and diagnose again:
the law is right where the error falls as far as the fitted shape's.

In Python: `import jaxwear as jw; jw.register_effect(MissingWear())` before loading a study.
"""

import jax.numpy as jnp

import jaxwear as jw
from jaxwear.effects import state_variables, swept_kernel

FORM = {form!r}  # "factor": rate x exp(gain g(z)); "deposit": rate + gain e(z) kernel
DEPOSIT_UNIT_M = 1e-9  # e = 1 is 1 nm·rad of depth per step (volume e R_b B)
# each variable: name, periodic (angles, on the circle), knots (z at t = 0, 1/Q, .., 1 of the
# wear-weighted coordinate; none for angles) and the coefficients of its cubic B-splines; a
# surface over two variables (a product the sum of one-variable terms cannot make) has its
# second variable under "times" and its coefficients row-major over the two bases
CORRECTION = {correction}


def _bspline(t):
    a = jnp.abs(t)
    return jnp.where(a < 1.0, (4.0 - 6.0 * a ** 2 + 3.0 * a ** 3) / 6.0,
                     jnp.where(a < 2.0, (2.0 - a) ** 3 / 6.0, 0.0))


def _basis(var, z, n):
    """(..., n) the cubic B-splines of one variable at z (in its unit)."""
    if var["periodic"]:
        h = 360.0 / n
        d = jnp.mod(z[..., None] - jnp.arange(n) * h + 180.0, 360.0) - 180.0
        return _bspline(d / h)
    knots = jnp.asarray(var["knots"])
    t = jnp.interp(z, knots, jnp.linspace(0.0, 1.0, len(var["knots"])))
    h = 1.0 / (n - 3)
    return _bspline((t[..., None] - (jnp.arange(n) - 1.0) * h) / h)


def correction(z):
    """g (factor) or e (deposit), (steps, nodes), from the state variables `z`."""
    total = 0.0
    for var in CORRECTION:
        c = jnp.asarray(var["coefficients"])
        if "times" in var:  # a surface: Σ_kl c_kl B_k(z_a) B_l(z_b)
            other = var["times"]
            na, nb = var["size"], other["size"]
            Ba = _basis(var, z[var["name"]], na)
            Bb = _basis(other, z[other["name"]], nb)
            total = total + jnp.einsum("...k,...l,kl->...", Ba, Bb, c.reshape(na, nb))
        else:
            total = total + _basis(var, z[var["name"]], len(c)) @ c
    return total


class MissingWear(jw.Effect):
    name = "missing_wear"
    parameters = {{"missing_wear_gain": jw.EffectParameter(
        1.0, 1.0, 0.0, 0.0, 10.0, "gain of the fitted correction: 0 off, 1 as fitted [-]",
        scale=0.1, realistic=1.0)}}
    signature = {signature!r}
    uses_swept_kernel = FORM == "deposit"  # its kernel computed once per run: ctx.swept

    def local_rate(self, p, rate, ctx):
        z = state_variables(ctx.pressure, ctx.slide, ctx.dt, ctx.sliding_distance,
                            ctx.load_angle, ctx.load, ctx.worn_depth)
        z = {{k: jnp.broadcast_to(v, ctx.pressure.shape) for k, v in z.items()}}
        gain = p.effect_params["missing_wear_gain"]
        if FORM == "factor":
            return rate * jnp.exp(gain * correction(z))
        e = jnp.maximum(correction(z), 0.0)  # a deposit is never negative
        kernel = (swept_kernel(ctx.load_angle, ctx.pressure.shape[1]) if ctx.swept is None
                  else ctx.swept)  # at the load direction
        return rate + gain * DEPOSIT_UNIT_M * e * kernel
'''


def effect_file_source(result, study_path: str) -> str:
    """The text of `missing_wear.py` for a `ShapeResult` with a refitted correction."""

    corr = result.correction
    variables = [{"name": v["name"], "periodic": VARIABLES[v["name"]][1],
                  "knots": [round(k, 12) for k in v["knots"]],
                  "coefficients": [round(c, 12) for c in v["coefficients"]]}
                 for v in corr["variables"]]
    for t in corr.get("tensors", ()):
        (a, b), (na, nb), (ka, kb) = t["variables"], t["size"], t["knots"]
        variables.append({"name": a, "periodic": VARIABLES[a][1],
                          "knots": [round(k, 12) for k in ka], "size": na,
                          "coefficients": [round(c, 12) for c in t["coefficients"]],
                          "times": {"name": b, "periodic": VARIABLES[b][1],
                                    "knots": [round(k, 12) for k in kb], "size": nb}})
    names = [v["name"] + (f" x {v['times']['name']}" if "times" in v else "")
             for v in variables]
    text = json.dumps(variables, indent=4).replace("true", "True").replace("false", "False")
    return TEMPLATE.format(
        study=study_path, sentence="\n".join(textwrap.wrap(result.sentence, 86,
                                                           subsequent_indent="    ")),
        form=corr["form"], form_words=FORM_WORDS[corr["form"]],
        variables=", ".join(names), correction=text,
        signature=f"the missing wear found by diagnose --shape: {corr['form']} along "
                  f"{', '.join(names)}")
