"""Physical parameters of a joint and its driver, as one flat immutable pytree (SI units).

Every field is a float64 scalar so that any of them can be fitted, differentiated or swept
(`jax.vmap` over a batched `Params`). The study file names each field by a unit-suffixed key
(`PARAMETER_KEYS`); the conversion to SI happens once, here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree
from jaxwear._core.errors import InputError
from jaxwear._core.host import to_device
from jaxwear._core.types import Scalar
from jaxwear._physics.effects import effect_parameter_specs


def _f(x) -> Scalar:
    return to_device(x, np.float64)  # a host number: no compilation (`_core.host`)


class Params(pytree.Struct):
    """All physical parameters, SI units (m, kg, N, Pa, s, rad).

    Crank-slider (design.md §1, Table 1) and oscillating driver (§2) share one pytree; fields a
    driver does not use are ignored by it. Effect strengths (§5) live here too, at the value
    that switches them off, so a disabled effect leaves the model unchanged.
    """

    # mechanism (Table 1)
    crank_length: Scalar  # L1 [m]
    coupler_length: Scalar  # L2 [m]
    crank_mass: Scalar  # m1 [kg] (does not enter F_C: the crank turns at constant speed)
    coupler_mass: Scalar  # m2 [kg]
    slider_mass: Scalar  # m3 [kg]
    spring_rate: Scalar  # k [N/m]
    spring_free_position: Scalar  # x0 [m]; NaN means "L2 - L1" (resolved in __init__)
    gravity: Scalar  # g [m/s²], along -y
    speed: Scalar  # crank speed ω [rad/s]
    # joint (Tables 3, 4)
    bore_radius: Scalar  # R_b [m]
    clearance: Scalar  # c = R_b - R_p [m]; also the clearance-link length ξ
    width: Scalar  # B [m]
    layer_thickness: Scalar  # L [m], the wearing layer
    layer_modulus: Scalar  # E [Pa]
    layer_poisson: Scalar  # ν [-]
    backing_thickness: Scalar  # L_st [m] (double layer only)
    backing_modulus: Scalar  # E_st [Pa]
    backing_poisson: Scalar  # ν_st [-]
    pin_modulus: Scalar  # [Pa] (the pin is rigid in the Winkler model; kept for the record)
    pin_poisson: Scalar  # [-]
    # wear
    wear_coefficient: Scalar  # K_d [m²/N = 1/Pa]
    # oscillating joint (§2)
    load: Scalar  # |W| [N]
    load_angle: Scalar  # θ_W0 [rad], bushing frame at φ = 0
    swing_period: Scalar  # T_s [s]
    # every driver: a dimensionless multiplier of the joint load (an uncertain load magnitude
    # to sweep or fit; with depth data only K_d x load_scale is identifiable)
    load_scale: Scalar  # [-]
    # candidate effects (§5): strength parameters by study key, SI values, defaults "off"
    effect_params: dict[str, Scalar]

    @property
    def pin_radius(self) -> Scalar:
        """R_p = R_b - c [m]: changing the clearance changes the pin, not the bore
        (design.md §3)."""
        return self.bore_radius - self.clearance

    def replace(self, **kw) -> Params:
        """A copy with some fields replaced (SI values)."""
        names = [f.name for f in fields(self)]
        for k in kw:
            if k not in names:
                raise KeyError(f"Params has no field {k!r}")
        return pytree.replace(self, **{k: _f(v) for k, v in kw.items()})

    def get(self, key: str) -> Scalar:
        """SI value of a study key (a physical parameter or an effect strength)."""
        if key in PARAMETER_KEYS:
            return getattr(self, PARAMETER_KEYS[key].field)
        return self.effect_params[key]

    def with_values(self, values: dict) -> Params:
        """A copy with study keys set to SI values (traced values allowed)."""
        fields_kw = {PARAMETER_KEYS[k].field: v for k, v in values.items()
                     if k in PARAMETER_KEYS}
        eff = {k: v for k, v in values.items() if k not in PARAMETER_KEYS}
        out = self
        if fields_kw:
            out = pytree.replace(out, **{k: jnp.asarray(v, jnp.float64)
                                         for k, v in fields_kw.items()})
        if eff:
            unknown = [k for k in eff if k not in out.effect_params]
            if unknown:
                raise KeyError(f"unknown parameter keys {unknown}")
            new = dict(out.effect_params)
            new.update({k: jnp.asarray(v, jnp.float64) for k, v in eff.items()})
            out = pytree.replace(out, effect_params=new)
        return out


@dataclass(frozen=True)
class Key:
    """A user-facing parameter key: the Params field it sets and the factor to SI."""

    field: str
    to_si: float
    doc: str
    positive: bool = True  # fitted in log space when True


_MM = 1e-3
_GPA = 1e9
_RPM = 2 * math.pi / 60

# Study-file keys (design.md §6: "the key names its unit"). Dimensionless keys carry no suffix.
PARAMETER_KEYS: dict[str, Key] = {
    "crank_length_mm": Key("crank_length", _MM, "L1, crank AB"),
    "coupler_length_mm": Key("coupler_length", _MM, "L2, coupler BD"),
    "crank_mass_kg": Key("crank_mass", 1.0, "m1"),
    "coupler_mass_kg": Key("coupler_mass", 1.0, "m2"),
    "slider_mass_kg": Key("slider_mass", 1.0, "m3"),
    "spring_N_per_m": Key("spring_rate", 1.0, "k, slider spring", positive=False),
    "spring_free_position_mm": Key("spring_free_position", _MM, "x0 (default L2 - L1)",
                                   positive=False),
    "gravity_m_per_s2": Key("gravity", 1.0, "g", positive=False),
    "speed_rpm": Key("speed", _RPM, "crank speed n"),
    "bore_diameter_mm": Key("bore_radius", _MM / 2, "inner diameter of the bushing"),
    "clearance_mm": Key("clearance", _MM, "radial clearance c = R_b - R_p (= ξ)"),
    "width_mm": Key("width", _MM, "bushing width B"),
    "layer_thickness_mm": Key("layer_thickness", _MM, "wearing layer thickness L"),
    "layer_E_GPa": Key("layer_modulus", _GPA, "wearing layer Young's modulus"),
    "layer_poisson_ratio": Key("layer_poisson", 1.0, "wearing layer Poisson ratio"),
    "backing_thickness_mm": Key("backing_thickness", _MM, "backing (steel) layer thickness"),
    "backing_E_GPa": Key("backing_modulus", _GPA, "backing layer Young's modulus"),
    "backing_poisson_ratio": Key("backing_poisson", 1.0, "backing layer Poisson ratio"),
    "pin_E_GPa": Key("pin_modulus", _GPA, "pin Young's modulus (rigid in the model)"),
    "pin_poisson_ratio": Key("pin_poisson", 1.0, "pin Poisson ratio (rigid in the model)"),
    "K_d_per_Pa": Key("wear_coefficient", 1.0, "Archard linear wear coefficient K_d"),
    "load_N": Key("load", 1.0, "oscillating joint: load magnitude |W|"),
    "load_angle_deg": Key("load_angle", math.pi / 180, "oscillating joint: load direction",
                          positive=False),
    "swing_period_s": Key("swing_period", 1.0, "oscillating joint: swing period T_s"),
    "load_scale": Key("load_scale", 1.0, "multiplier of the joint load (every driver)"),
}
# pin_diameter_mm is accepted too: it sets the default clearance (bore - pin)/2.
DERIVED_KEYS = {"pin_diameter_mm": "sets clearance_mm = (bore_diameter_mm - pin_diameter_mm)/2"}

_RIG = {
    # Table 1 (rig experiments: k = 1009.4 N/m, §3.3) and Table 3
    "crank_length_mm": 70.0, "coupler_length_mm": 200.0, "crank_mass_kg": 0.462,
    "coupler_mass_kg": 1.0943, "slider_mass_kg": 5.0, "spring_N_per_m": 1009.4,
    "spring_free_position_mm": math.nan, "gravity_m_per_s2": 9.81, "speed_rpm": 276.0,
    "bore_diameter_mm": 15.0, "clearance_mm": 0.05, "width_mm": 28.0,
    "layer_thickness_mm": 0.5, "layer_E_GPa": 0.5, "layer_poisson_ratio": 0.3,
    "backing_thickness_mm": 0.0, "backing_E_GPa": 208.0, "backing_poisson_ratio": 0.28,
    "pin_E_GPa": 208.0, "pin_poisson_ratio": 0.28, "K_d_per_Pa": 1.0e-13,
    "load_N": 0.0, "load_angle_deg": 90.0, "swing_period_s": 10.0, "load_scale": 1.0,
}
# Table 4: bimetal bearing, copper layer 0.5 mm on a 2 mm steel backing, same geometry.
# The paper gives neither the boom load nor the swing period: 10 kN (≈ 24 MPa projected
# pressure on a 15 x 28 mm bearing) and 10 s are our documented assumptions; only K_d·|W|
# is identifiable from depth-vs-time data, so K_d is calibrated against them.
_BOOM = dict(_RIG)
_BOOM.update({
    "layer_E_GPa": 103.0, "layer_poisson_ratio": 0.3, "backing_thickness_mm": 2.0,
    "backing_E_GPa": 208.0, "backing_poisson_ratio": 0.28, "K_d_per_Pa": 1.5e-14,
    "load_N": 10000.0, "load_angle_deg": 90.0, "swing_period_s": 10.0,
    "spring_N_per_m": 0.0, "speed_rpm": 0.0,
})
# Your own joint (design.md §2): the load and motion come from files, the joint's geometry and
# materials from [model.parameters]; where a study leaves a key out it is the rig joint's
# (Table 3: bore 15 mm, width 28 mm, PTFE layer 0.5 mm). The mechanism keys do not enter.
_LOAD_HISTORY = dict(_RIG)
_LOAD_HISTORY.update({"spring_N_per_m": 0.0, "speed_rpm": 0.0})
PRESETS = {"rig": _RIG, "boom": _BOOM, "load_history": _LOAD_HISTORY}
# Keys that do not enter a load_history joint (the file gives its load and motion).
MECHANISM_KEYS = ("crank_length_mm", "coupler_length_mm", "crank_mass_kg", "coupler_mass_kg",
                  "slider_mass_kg", "spring_N_per_m", "spring_free_position_mm",
                  "gravity_m_per_s2", "speed_rpm", "load_N", "load_angle_deg",
                  "swing_period_s")


def _resolve(values: dict[str, float], effect_values: dict[str, float]) -> Params:
    si = {}
    for key, spec in PARAMETER_KEYS.items():
        si[spec.field] = float(values[key]) * spec.to_si
    if math.isnan(si["spring_free_position"]):
        # x0 is not in the paper: spring relaxed at inner dead centre (design.md §1).
        si["spring_free_position"] = si["coupler_length"] - si["crank_length"]
    eff = {k: _f(v) for k, v in effect_values.items()}
    return Params(**{k: _f(v) for k, v in si.items()}, effect_params=eff)


def preset(name: str = "rig", **overrides: float) -> Params:
    """Parameters of a preset with optional overrides by study key.

    **Arguments:**
    - `name`: `"rig"` (Tables 1 and 3, k = 1009.4 N/m), `"boom"` (Table 4) or
      `"load_history"` (your own joint: the rig's joint until overridden; its load and
      motion come from files through `ModelConfig.duty_cycle`).
    - `overrides`: study keys with their units, e.g. `clearance_mm=0.1, speed_rpm=148`.

    **Returns:** a `Params` in SI units.
    """
    if name not in PRESETS:
        raise InputError(f"unknown preset {name!r}: expected one of {sorted(PRESETS)}")

    values = dict(PRESETS[name])
    specs = effect_parameter_specs()
    effect_values = {k: spec.default * spec.to_si for k, spec in specs.items()}
    overrides = dict(overrides)
    if "pin_diameter_mm" in overrides:
        pin = float(overrides.pop("pin_diameter_mm"))
        bore = float(overrides.get("bore_diameter_mm", values["bore_diameter_mm"]))
        overrides.setdefault("clearance_mm", (bore - pin) / 2)
    for k, v in overrides.items():
        if k in specs:
            effect_values[k] = float(v) * specs[k].to_si
        elif k in PARAMETER_KEYS:
            values[k] = float(v)
        else:
            raise InputError(f"unknown parameter {k!r}: expected one of "
                             f"{sorted(PARAMETER_KEYS) + sorted(DERIVED_KEYS) + sorted(specs)}")
    return _resolve(values, effect_values)


def key_to_si(key: str) -> float:
    """Factor from a study key's unit to SI (physical parameters and effect strengths)."""
    if key in PARAMETER_KEYS:
        return PARAMETER_KEYS[key].to_si

    return effect_parameter_specs()[key].to_si
