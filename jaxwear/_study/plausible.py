"""Physical plausibility: the ranges the model is valid in, in one table, checked before any
work (issue 29).

A number can be well formed and still far outside what the model describes: `speed_rpm =
1e9` crushed the layer 10¹⁰ times over and ran for a minute before the contact solve gave
up; `wear_tolerance_um = 1e-12` asked the integrator for 200 000 steps below the size of an
atom. Every number a study or a command-line flag carries is checked here against

- `RANGES`: one `Range` per key (study keys by their name, `numerics.`/`fit.`/`experiment.`
  keys by their section), with the reason in one clause; `PRESET_RANGES[preset]` replaces or
  adds entries for one preset (None: the preset does not use the key, not checked);
- `RELATIONS`: ranges of ratios of keys (crank shorter than coupler, clearance against the
  bore radius, layer against the bore radius);
- the layer's elastic strain at the peak load (`peak_strain`): the Winkler foundation is
  linear elasticity of a thin layer; a load that would compress it by more than
  `STRAIN_LIMIT` of its thickness is outside the model. The peak load comes per driver
  from `LOAD_BOUNDS` without a model evaluation (the crank-slider's own hand-derived
  equations in NumPy, the boom's `load_N`), and the Winkler contact in closed form, so
  the check costs about a millisecond.

Rows of data files too: `check_repeats` refuses repeated points (the same angle and
revolutions, or the same hours) whose depths disagree beyond the file's noise.

A new preset adds its keys to `RANGES` (or `PRESET_RANGES[name]`) and, for a new driver,
a `LoadBound` to `LOAD_BOUNDS`; nothing else changes. The study reader (`_study.py`), the
CLI flags (sweep ranges, `--at`, `--noise-um`, synth's options) and `load_study` all ask
here, and the failures are `InputError`s (exit 2) of the form
`WHERE: KEY = VALUE is outside RANGE: REASON`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from jaxwear._core.errors import InputError
from jaxwear._physics.effects import effect_parameter_specs
from jaxwear._physics.limits import (
    INDENT_LIMIT,
    LOAD_BOUNDS,
    STRAIN_LIMIT,
    _stiffness,
    light_load_message,
    load_file_strain_message,
    peak_strain,
    strain_message,
)
from jaxwear._physics.params import MECHANISM_KEYS


@dataclass(frozen=True)
class Range:
    """Plausible values of one key, in its unit: [lo, hi] (`lo_open`: lo excluded)."""

    lo: float
    hi: float
    reason: str  # one clause: why values outside are not this model's
    lo_open: bool = False

    def __contains__(self, v: float) -> bool:
        return (v > self.lo if self.lo_open else v >= self.lo) and v <= self.hi

    def __str__(self) -> str:
        return f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}]"


_LENGTH = "a crank-slider from a millimetre to 10 m"
_MASS = "from massless to 10 t"
_MODULUS = "from a soft elastomer (1 MPa) to diamond (1200 GPa)"
_POISSON = ("ν → 0.5 makes the Winkler stiffness (1-ν)E/((1+ν)(1-2ν)) of an incompressible "
            "layer infinite (and no bearing layer is auxetic, ν < 0)")
_CYCLES = ("at least one whole revolution (one cycle's wear is the model's unit), at most "
           "10¹² (630 years at 3000 r/min)")

# key -> Range. Study parameter keys by name; other study keys by section.key.
RANGES: dict[str, Range | None] = {
    # mechanism (design.md §1, Table 1)
    "crank_length_mm": Range(1.0, 1e4, _LENGTH),
    "coupler_length_mm": Range(1.0, 1e4, _LENGTH),
    "crank_mass_kg": Range(0.0, 1e4, _MASS),
    "coupler_mass_kg": Range(0.0, 1e4, _MASS),
    "slider_mass_kg": Range(0.0, 1e4, _MASS),
    "spring_N_per_m": Range(0.0, 1e9, "from no spring to a spring as stiff as a steel bar"),
    "spring_free_position_mm": Range(-1e5, 1e5, "within 100 m of the crank pivot"),
    "gravity_m_per_s2": Range(-100.0, 100.0, "within 10 g"),
    "speed_rpm": Range(1e-3, 1e5, "from a revolution in 17 hours to 100 000 r/min (no crank "
                                  "mechanism runs outside that)"),
    # joint (design.md §3, Tables 3 and 4)
    "bore_diameter_mm": Range(0.5, 2000.0, "a journal bearing from 0.5 mm to 2 m"),
    "clearance_mm": Range(1e-4, 100.0, "from 0.1 µm (below that the surfaces' roughness is "
                                       "the gap) to 100 mm", lo_open=False),
    "width_mm": Range(0.1, 1e4, "a bearing from 0.1 mm to 10 m wide"),
    "layer_thickness_mm": Range(1e-3, 1e3, "a wearing layer from 1 µm to 1 m"),
    "layer_E_GPa": Range(1e-3, 1200.0, _MODULUS),
    "layer_poisson_ratio": Range(0.0, 0.49, _POISSON),
    "backing_thickness_mm": Range(0.0, 1e3, "no backing, or one up to 1 m"),
    "backing_E_GPa": Range(1e-3, 1200.0, _MODULUS),
    "backing_poisson_ratio": Range(0.0, 0.49, _POISSON),
    "pin_E_GPa": Range(1e-3, 1200.0, _MODULUS),
    "pin_poisson_ratio": Range(0.0, 0.5, "a Poisson ratio of a solid"),
    # wear (design.md §4): specific wear rates of real pairs span ~1e-17..1e-12 1/Pa
    "K_d_per_Pa": Range(1e-20, 1e-9, "from far slower than any measured pair to 1 mm³/(N·m), "
                                     "faster than abrasion"),
    # oscillating joint (design.md §2)
    "load_N": Range(0.0, 1e8, "up to 10 000 t"),
    "load_scale": Range(0.0, 1e4, "a factor on the driver's load, from none to 10 000x "
                                  "(a load in kN under an N header is 1000x)", lo_open=True),
    "load_angle_deg": Range(-360.0, 360.0, "an angle within one turn either way"),
    "swing_period_s": Range(1e-2, 1e5, "a swing from 10 ms to a day"),
    "model.duty_cycle.amplitude_deg": Range(0.0, 180.0, "a swing of at most half a turn each "
                                                        "way", lo_open=True),
    "model.duty_cycle.duration_h": Range(0.0, 1e6, "up to 114 years", lo_open=True),
    "model.scla_passes": Range(1, 100, "the SCLA converges in a few passes (design.md §1)"),
    "model.gamma0_deg": Range(-360.0, 360.0, "an angle within one turn either way"),
    # numerics (design.md §3-4, §6)
    "numerics.nodes": Range(8, 100_000, "from 8 nodes to 0.0036° apart, finer than any "
                                        "profilometer"),
    "numerics.steps_per_rev": Range(4, 100_000, "from 4 steps to 0.0036° of crank angle"),
    "numerics.revolutions_per_update": Range(1.0, 1e12, "eq 23 advances whole cycles: the "
                                                        "wear of one cycle is the model's unit"),
    "numerics.wear_tolerance_um": Range(
        1e-6, 100.0, "below 1 pm the error target is under an atom's size and under what the "
                     "contact solve's 1e-9 relative residual leaves on µm depths (and the "
                     "steps grow like tol^(-1/2)); above 100 µm it is no target"),
    # experiments (design.md §6)
    "experiment.revolutions": Range(1.0, 1e12, _CYCLES),
    "experiment.hours": Range(0.0, 1e6, "up to 114 years of running", lo_open=True),
    "experiment.cycles": Range(1.0, 1e12, "at least one whole period of the load file (one "
                                          "cycle's wear is the model's unit), at most 10¹²"),
    "experiment.angle_offset_deg": Range(-360.0, 360.0, "an angle within one turn either way"),
    # fit (design.md §6)
    "fit.clearance_tolerance_um": Range(0.0, math.inf, "a standard deviation (0 fixes, inf "
                                                       "frees)"),
    "fit.angle_tolerance_deg": Range(0.0, 180.0, "a standard deviation within half a turn"),
    "fit.noise_um": Range(1e-4, 1e3, "from 0.1 nm, below any gauge, to 1 mm, more than a "
                                     "layer"),
}

# Per preset: entries that replace RANGES' (None: the preset does not use the key).
PRESET_RANGES: dict[str, dict[str, Range | None]] = {
    "boom": {"speed_rpm": None},  # the oscillating joint has no crank speed
    # your own joint: its load and motion come from its load files, not from a mechanism
    "load_history": {k: None for k in MECHANISM_KEYS},
}


def key_range(key: str, preset: str | None = None) -> Range | None:
    """The plausible range of `key` (None: not checked). Effect strengths: the effect's own
    bounds (`EffectParameter.lower`/`upper`, what it is defined and fitted on)."""
    table = PRESET_RANGES.get(preset or "", {})
    if key in table:
        return table[key]
    if key in RANGES:
        return RANGES[key]

    spec = effect_parameter_specs().get(key)
    if spec is not None:
        return Range(spec.lower, spec.upper, "the range the effect is defined and fitted on")
    return None


def check_value(where, key: str, value: float, *, preset: str | None = None,
                name: str | None = None) -> float:
    """`value` if it lies in `key`'s range, else `InputError`: `WHERE: NAME = VALUE is outside
    RANGE: REASON` (`where`: the file or the flag; `name`: how the user wrote the key,
    default `key`)."""
    r = key_range(key, preset)
    if r is not None and value not in r:
        name = name or key
        head = name if name.startswith(str(where)) else f"{where}: {name}"
        raise InputError(f"{head} = {value:g} is outside the plausible range {r}: {r.reason}")
    return value


# ------------------------------------------------------------------ relations of keys

@dataclass(frozen=True)
class Relation:
    """A plausible range of a ratio of keys: `value(params)` (SI in, ratio out)."""

    keys: str  # what the ratio is, in study keys (for the message)
    value: Callable
    range: Range
    drivers: tuple[str, ...] | None = None  # None: every driver (the joint's own ratios)


RELATIONS = [
    Relation("crank_length_mm / coupler_length_mm",
             lambda p: float(p.crank_length) / float(p.coupler_length),
             Range(0.0, 0.95, "the crank must be shorter than the coupler to turn (and within "
                              "5 % of it the coupler's swing is singular)", lo_open=True),
             drivers=("crank_slider",)),
    Relation("clearance_mm / (bore_diameter_mm / 2)",
             lambda p: float(p.clearance) / float(p.bore_radius),
             Range(0.0, 0.1, "the clearance-link and Winkler models take a clearance small "
                             "against the bore (0.3 % on the paper's rig)", lo_open=True)),
    Relation("layer_thickness_mm / (bore_diameter_mm / 2)",
             lambda p: float(p.layer_thickness) / float(p.bore_radius),
             Range(0.0, 1.0, "the Winkler foundation is a thin layer: thinner than the bore "
                             "radius", lo_open=True)),
]


def check_relations(where: str, p, driver: str) -> None:
    """`InputError` when a ratio of `p`'s keys (SI `Params`) is outside its range."""
    for rel in RELATIONS:
        if rel.drivers is not None and driver not in rel.drivers:
            continue
        v = rel.value(p)
        if v not in rel.range:
            raise InputError(f"{where}: {rel.keys} = {v:.4g} is outside the plausible range "
                             f"{rel.range}: {rel.range.reason}")


# ------------------------------------------------------------------ load and layer strain


def check_strain(where: str, p, cfg) -> None:
    """`InputError` when the driver's peak load would strain the layer beyond `STRAIN_LIMIT`
    (a driver without a `LoadBound` is not checked)."""
    bound = LOAD_BOUNDS.get(cfg.driver)
    if bound is None:
        return
    load = bound.bound(p, cfg)
    strain = peak_strain(p, load, cfg.double_layer)
    if 0 < strain and strain * _stiffness(p, cfg.double_layer)[1] / _stiffness(
            p, cfg.double_layer)[0] < INDENT_LIMIT * float(p.clearance):
        raise InputError(light_load_message(where, p, cfg, bound, load, strain))
    if strain <= STRAIN_LIMIT:
        return
    if cfg.driver == "load_history":  # the file's numbers, not a key, carry the load
        raise InputError(load_file_strain_message(where, p, cfg, load, strain))
    raise InputError(f"{where}: {strain_message(p, cfg, bound, load, strain)}")


def check_params(where: str, p, cfg) -> None:
    """Relations and the layer strain of one experiment's parameters (SI `Params`)."""
    check_relations(where, p, cfg.driver)
    check_strain(where, p, cfg)


# ------------------------------------------------------------------ repeated rows

REPEAT_LEVELS = 5.0  # repeated rows further apart than 5 √2 noise levels disagree


def check_repeats(path, keys, names: list[str], depth, column: str, sigma: float,
                  gauge_um: float) -> None:
    """Refuse (exit 2) rows that repeat a key (`keys` (rows, k): angle and revolutions, or
    hours) with depths [m] further apart than the noise allows: two readings of one place at
    one time cannot differ by 25 noise levels, one of them is wrong (4 rows of 50 µm among 2
    µm rows once calibrated to an RMSE of 12 µm without a word). Repeats that agree are
    measurements like any other. The allowance is `REPEAT_LEVELS` √2 σ (σ of the file, from
    neighbouring points; NaN when there are too few rows), at least what a gauge resolves
    (`gauge_um`); without a noise estimate, a tenth of the file's depth range.
    `column`: the file's depth column(s), for the message."""
    if len(depth) < 2:
        return
    _, group = np.unique(keys, axis=0, return_inverse=True)
    group = group.ravel()
    n = group.max() + 1
    lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(lo, group, depth)
    np.maximum.at(hi, group, depth)
    floor = gauge_um * 1e-6
    if math.isfinite(sigma):
        allowed = max(REPEAT_LEVELS * math.sqrt(2.0) * sigma, floor)
        why = (f"{REPEAT_LEVELS:g} √2 noise levels of {sigma * 1e6:.3g} µm from neighbouring "
               f"points")
    else:
        allowed = max(0.1 * float(np.ptp(depth)), floor)
        why = "a tenth of the file's depth range: too few rows to estimate the noise"
    bad = np.flatnonzero(hi - lo > allowed)
    if not len(bad):
        return
    first = np.full(n, len(depth))
    np.minimum.at(first, group, np.arange(len(depth)))
    g = bad[np.argmin(first[bad])]  # the first in the file
    rows = np.flatnonzero(group == g)
    i, j = rows[np.argmin(depth[rows])], rows[np.argmax(depth[rows])]
    i, j = sorted((int(i), int(j)))
    at = ", ".join(f"{nm} {v:g}" for nm, v in zip(names, keys[i]))
    scale, unit = (1e3, "depth_mm") if column == "depth_mm" else (1e6, column)
    if "," in column:  # two raw scans
        unit = "depths [µm] (radius_after_um - radius_before_um)"
    more = f"; {len(bad) - 1} more repeated point(s) disagree too" if len(bad) > 1 else ""
    raise InputError(f"{path}: lines {i + 2} and {j + 2} measure the same point ({at}) as "
                     f"{unit} {depth[i] * scale:.4g} and {depth[j] * scale:.4g}, "
                     f"{abs(depth[j] - depth[i]) * 1e6:.3g} µm apart, beyond the "
                     f"{allowed * 1e6:.3g} µm that the noise allows ({why}){more}: one of "
                     f"them is wrong; correct or remove it (repeats that agree within the "
                     f"noise are fine)")


# ------------------------------------------------------------------ a whole study

_SECTIONS = {"numerics": ("nodes", "steps_per_rev", "revolutions_per_update",
                          "wear_tolerance_um"),
             "fit": ("angle_tolerance_deg", "noise_um"),
             "model": ("scla_passes", "gamma0_deg")}


def check_study(study):
    """Every number of a loaded study (`_study.load_study`) against `RANGES`, then each
    experiment's parameters against `RELATIONS` and the layer strain. Returns the study.

    Numbers are read from the study as the file gave them (`study.raw`, already checked to
    be finite numbers), so that messages name the key as written."""
    path, preset, raw = study.path, study.preset, study.raw

    def check(key, value, name):
        check_value(path, key, float(value), preset=preset, name=name)

    model = raw.get("model", {})
    for k, v in model.get("parameters", {}).items():
        check(k, v, f"model.parameters.{k}")
    for section, keys in _SECTIONS.items():
        table = raw.get(section, {})
        for k in keys:
            if k in table:
                check(f"{section}.{k}", table[k], f"{section}.{k}")
    for i, block in enumerate(study.config.duty_cycle if "duty_cycle" in model else ()):
        # a load file's block swings as its file says (no amplitude of its own)
        keys = ("duration_h",) if getattr(block, "load", None) is not None else (
            "amplitude_deg", "duration_h")
        for k in keys:
            check(f"model.duty_cycle.{k}", getattr(block, k), f"model.duty_cycle[{i}].{k}")
    if math.isfinite(study.clearance_tolerance_um):
        check("fit.clearance_tolerance_um", study.clearance_tolerance_um,
              "fit.clearance_tolerance_um")
    for exp, given in zip(study.experiments, raw.get("experiment", [])):
        where = f"experiment {exp.name!r}"
        for k, v in exp.overrides.items():
            check(k, v, f"{where}.{k}")
        if exp.revolutions is not None:
            check("experiment.revolutions", exp.revolutions, f"{where}.revolutions")
        if "cycles" in given:  # named as written, before the hours it converts to
            check("experiment.cycles", given["cycles"], f"{where}.cycles")
        if exp.hours is not None:
            check("experiment.hours", exp.hours, f"{where}.hours" if "hours" in given
                  else f"{where}: hours (the last of its history)")
        if exp.profile is not None:
            check("experiment.angle_offset_deg", exp.profile.angle_offset_deg,
                  f"{where}.angle_offset_deg")
        check_params(f"{path}: {where}", study.params(exp), study.config)
    return study
