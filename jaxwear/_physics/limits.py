"""What the Winkler model can carry: the peak load of a driver, the elastic strain it puts on the
layer, and the error for a contact solve that did not converge (docs/design.md §3)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from jaxwear._core.errors import InputError, ModelFailure
from jaxwear._physics.effects._base import file_effects
from jaxwear._physics.mechanism import forces_from_kinematics, kinematics_by_hand
from jaxwear._physics.params import PARAMETER_KEYS, key_to_si

STRAIN_LIMIT = 0.25  # peak elastic strain p/E_w of the wearing layer, unworn bore
# Smallest peak indentation u/c (pin pressed into the unworn layer, over the clearance) the
# model is run at. The contact solve works in offsets the size of the clearance; below this
# it did not converge (0.01 N on the 15 x 28 mm load-file joint, u/c = 5e-5: relative force
# residual 2e-7 once the bore had worn by a fraction of the indentation; issue 41), and a
# load this light (a few Pa of projected pressure) wears nothing a gauge resolves.
INDENT_LIMIT = 1e-4


@dataclass(frozen=True)
class LoadBound:
    """Peak joint load [N] of a driver without a model evaluation (closed form or NumPy),
    the study key that scales it most and the keys it depends on (for messages)."""

    bound: Callable  # (Params, ModelConfig) -> float [N]
    key: str
    keys: tuple[str, ...]


def crank_slider_peak_load(p, cfg=None) -> float:
    """The peak joint load |F_C| [N] of one crank revolution (design.md §1), by the model's own
    hand-derived eqs 4-10 (`_mechanism.kinematics_by_hand`, `forces_from_kinematics`)
    evaluated in NumPy at 720 crank angles for the ideal joint: no compilation, ~1 ms. The
    clearance link changes |F| by 2e-4 relative at most (design.md §8), the sampling by less."""

    host = SimpleNamespace(**{k.field: float(getattr(p, k.field))
                              for k in PARAMETER_KEYS.values()})
    if math.isnan(host.spring_free_position):
        host.spring_free_position = host.coupler_length - host.crank_length
    if not host.speed > 0 or not host.crank_length < host.coupler_length:
        return math.nan  # no revolution to speak of (refused by the ranges first)
    t = np.arange(720) * (2 * math.pi / host.speed / 720)
    kin = kinematics_by_hand(host, t, 0.0, 0.0, xp=np)
    fx, fy = forces_from_kinematics(host, kin, xp=np)
    return float(np.max(np.hypot(fx, fy))) * float(getattr(p, "load_scale", 1.0))


# driver -> its load bound; a new driver (a preset with its own load) adds one here
LOAD_BOUNDS: dict[str, LoadBound] = {
    "crank_slider": LoadBound(crank_slider_peak_load, "speed_rpm",
                              ("speed_rpm", "slider_mass_kg", "coupler_mass_kg",
                               "spring_N_per_m", "crank_length_mm")),
    "oscillating": LoadBound(lambda p, cfg=None: abs(float(p.load)) * float(p.load_scale),
                             "load_N", ("load_N", "load_scale")),
    "load_history": LoadBound(lambda p, cfg: float(p.load_scale) * max(
        (b.load.peak_load for b in cfg.duty_cycle), default=0.0), "load_scale",
        ("load_scale",)),
}


def _stiffness(p, double_layer: bool) -> tuple[float, float]:
    """(k of the unworn foundation [Pa/m], E_w of the wearing layer [Pa]) (eqs 14-15)."""
    def ew(E, nu):
        E, nu = float(E), float(nu)
        return (1 - nu) * E / ((1 + nu) * (1 - 2 * nu))

    e_layer = ew(p.layer_modulus, p.layer_poisson)
    compliance = float(p.layer_thickness) / e_layer
    if double_layer:
        compliance += float(p.backing_thickness) / ew(p.backing_modulus, p.backing_poisson)
    return 1.0 / compliance, e_layer


def winkler_load(u: float, c: float, kRB: float) -> float:
    """Load [N] that presses a pin a depth `u` [m] into the unworn bore (clearance `c`, k R_b B
    = `kRB` [N/m per rad]): the continuous form of Σ_j p_j A_j n_j = W, ∫ k (s cos θ - c)
    cos θ R_b B dθ over the contact arc |θ| < α, s = c + u, cos α = c/s."""
    s = c + u
    alpha = math.acos(min(1.0, c / s))
    return kRB * (s * (alpha + math.sin(alpha) * math.cos(alpha)) - 2.0 * c * math.sin(alpha))


def peak_strain(p, load: float, double_layer: bool) -> float:
    """Peak elastic strain p_max/E_w of the wearing layer [-] under `load` [N] on the unworn
    bore (the Winkler contact of design.md §3 in closed form: the penetration u solves
    `winkler_load(u) = load` by bisection; p_max = k u)."""
    if not load > 0:
        return 0.0
    k, e_layer = _stiffness(p, double_layer)
    c, kRB = float(p.clearance), k * float(p.bore_radius) * float(p.width)
    lo, hi = 0.0, max(c, 1e-9)
    while winkler_load(hi, c, kRB) < load and hi < 1e6:
        hi *= 4.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if winkler_load(mid, c, kRB) < load:
            lo = mid
        else:
            hi = mid
    return k * hi / e_layer


def strain_load_limit(p, double_layer: bool) -> float:
    """The load [N] at which the layer's peak strain reaches `STRAIN_LIMIT`."""
    k, e_layer = _stiffness(p, double_layer)
    u = STRAIN_LIMIT * e_layer / k
    return winkler_load(u, float(p.clearance), k * float(p.bore_radius) * float(p.width))


def _key_limit(p, cfg, bound: LoadBound, limit_N: float) -> float | None:
    """The value of `bound.key` (its unit) at which the load bound reaches `limit_N`, by
    bisection (the bound grows with it); None when the other keys alone exceed it."""

    to_si = key_to_si(bound.key)

    def load_at(v):
        return bound.bound(p.with_values({bound.key: v * to_si}), cfg)

    if load_at(0.0) >= limit_N:
        return None
    lo, hi = 0.0, float(p.get(bound.key)) / to_si
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if load_at(mid) < limit_N else (lo, mid)
    return lo


def light_load_message(where: str, p, cfg, bound: LoadBound, load: float, strain: float
                       ) -> str:
    """A peak load that presses the layer in by less than `INDENT_LIMIT` of the clearance:
    the message names the load file (load_history) or the key that sets the load."""
    k, e_layer = _stiffness(p, cfg.double_layer)
    u, c = strain * e_layer / k, float(p.clearance)
    pressure = load / (2.0 * float(p.bore_radius) * float(p.width))
    what = (f"a peak load of {load:.3g} N presses the layer in by {u:.3g} m, {u / c:.2g} of "
            f"the clearance ({pressure:.3g} Pa of projected pressure; loaded joints run at "
            f"1-100 MPa): below the {INDENT_LIMIT:g} of the clearance the contact solve is run "
            f"at, and a load this light wears nothing measurable")
    if cfg.driver == "load_history":
        block = max(cfg.duty_cycle, key=lambda b: b.load.peak_load)
        return (f"{block.load.path}: columns 2-3 (load_x_N, load_y_N): {what} ({where}); "
                f"expected the load on the bushing in newtons (kN written as N?)")
    others = ", ".join(k_ for k_ in bound.keys if k_ != bound.key)
    return (f"{where}: {bound.key} = {float(p.get(bound.key)):g} (SI): {what}; expected a "
            f"larger {bound.key}" + (f" (or {others})" if others else ""))


def load_file_strain_message(where: str, p, cfg, load: float, strain: float) -> str:
    """A load file whose peak load strains the layer beyond `STRAIN_LIMIT`: the message names
    the file, its row and columns first (a load_history joint's load is the file's numbers;
    `load_scale` only when the study sets it other than 1), then `where` (the experiment)."""
    block = max(cfg.duty_cycle, key=lambda b: b.load.peak_load)
    cyc = block.load
    row = int(np.argmax(np.hypot(cyc.force[:, 0], cyc.force[:, 1])))
    scale = float(p.load_scale)
    limit_N = strain_load_limit(p, cfg.double_layer)
    pressure = strain * _stiffness(p, cfg.double_layer)[1] / 1e6
    scaled = "" if scale == 1.0 else f" x load_scale = {scale:g}"
    return (f"{cyc.path}: data row {row + 1} (time_s = {cyc.time[row] + 0.0:g} from the first), "
            f"columns 2-3 (load_x_N, load_y_N): a peak load of {cyc.peak_load:.4g} N{scaled} "
            f"({where}) gives ~{pressure:.3g} MPa on the layer, an elastic strain of "
            f"~{strain:.3g}, beyond the model's {STRAIN_LIMIT:g} ({limit_N:.3g} N on this "
            f"joint), because the Winkler foundation is linear elasticity of a thin layer; "
            f"expected the load on the bushing in newtons (not mN), or a stiffer layer "
            f"(layer_E_GPa), a wider bearing (width_mm), a smaller clearance_mm"
            + ("" if scale == 1.0 else ", a smaller load_scale"))



def strain_message(p, cfg, bound: LoadBound, load: float, strain: float) -> str:
    """'KEY = V loads the joint with up to L N: ...; plausible for this joint: KEY <= X
    ...; lower KEY ...' (one line, no file)."""

    value = float(p.get(bound.key)) / key_to_si(bound.key)
    limit_N = strain_load_limit(p, cfg.double_layer)
    key_max = _key_limit(p, cfg, bound, limit_N)
    others = ", ".join(k for k in bound.keys if k != bound.key)
    pressure = strain * _stiffness(p, cfg.double_layer)[1] / 1e6
    rng = (f"plausible for this joint: {bound.key} <= {key_max:.3g}" if key_max is not None
           else f"the joint's other loads alone ({others}) exceed it")
    return (f"{bound.key} = {value:g} loads the joint with up to {load:.3g} N"
            + (f" (from {bound.key}, {others})" if others else "")
            + f": ~{pressure:.3g} MPa on the layer, an elastic strain of ~{strain:.3g}; {rng} "
              f"(strain <= {STRAIN_LIMIT:g}, {limit_N:.3g} N), because the Winkler foundation "
              f"is linear elasticity of a thin layer. Lower {bound.key}"
            + (f" (or {others})" if others else "")
            + ", or make the layer stiffer (layer_E_GPa), the bearing wider (width_mm) or "
              "clearance_mm smaller")


def contact_failure(what: str, p, cfg, residual: float, peak_load: float) -> Exception:
    """The error for a contact solve that did not converge (`_wear.check_result`): an
    `InputError` (exit 2) naming the keys and the plausible value when the load strains the
    layer beyond `STRAIN_LIMIT` (the input caused it), else a `RuntimeError` (exit 1) that
    names the keys that drive the contact, since within the model's range it is the
    solver's failure."""
    head = (f"{what}: the contact solve did not converge (relative force residual "
            f"{residual:.2e} >= 1e-9) at a peak joint load of {peak_load:.3g} N")
    bound = LOAD_BOUNDS.get(cfg.driver)
    strain = peak_strain(p, peak_load, cfg.double_layer) if p is not None else math.nan
    if bound is not None and strain > STRAIN_LIMIT:
        if cfg.driver == "load_history":
            return InputError(load_file_strain_message(what, p, cfg, peak_load, strain))
        return InputError(f"{head}; {strain_message(p, cfg, bound, peak_load, strain)}")
    keys = ", ".join((bound.keys if bound is not None else ()) + (
        "clearance_mm", "layer_E_GPa", "layer_thickness_mm"))
    mine = file_effects(cfg.effects)
    if mine:  # a user's hook (NaN at a strength its load-time check did not try) first
        head = (f"{head}, with effect(s) from files switched on: {', '.join(mine)}; check "
                f"their hooks for NaN or inf at the strengths the fit tried")
    return ModelFailure(f"{head} (layer strain ~{strain:.2g}, within the model's range "
                        f"{STRAIN_LIMIT:g}): a failure of the solver, not of the input; the "
                        f"contact is driven by {keys}: a value nearer the paper's, or other "
                        f"numerics.nodes, may avoid it (please report the study)")
