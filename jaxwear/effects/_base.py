"""The effect interface: a candidate piece of physics the base model may be missing (§5).

An effect is a small stateless `eqx.Module` with a name, parameters (study keys with units,
defaults, bounds) and up to three hooks into the wear loop. Every hook's default is the
identity, and the base model never calls an effect that is switched off, so a disabled
effect leaves results bit-for-bit unchanged. Strength parameters at their `off` value give
the base model too (nesting), which is what makes score tests and likelihood ratios valid.

Writing your own (see README, "Add your own effect"):

    class Humidity(Effect):
        name = "humidity"
        parameters = {"humidity_gain": EffectParameter(1.0, 0.0, 0.0, -1.0, 10.0, "...")}
        signature = "uniform extra wear, proportional to sliding"
        def local_rate(self, p, rate, ctx):
            return rate * (1 + p.effect_params["humidity_gain"])

    register_effect(Humidity())
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp


@dataclass(frozen=True)
class EffectParameter:
    """A strength parameter of an effect, in the unit its study key names.

    - `to_si`: factor to SI. `default`: value used when fitting starts / when unset.
    - `off`: the value at which the effect vanishes (nesting). `lower`, `upper`: bounds.
    - `log`: fitted in log space (strictly positive parameters that are not nested at 0).
    - `scale`: typical size of the strength, in the key's unit (conditions the fit).
    """

    to_si: float
    default: float
    off: float
    lower: float
    upper: float
    doc: str = ""
    log: bool = False
    scale: float = 1.0  # typical size of a fitted change (sets the fit's parameter scaling)


class RateContext(eqx.Module):
    """What a local wear-rate hook may use, for one cycle (all SI).

    `pressure` (steps, nodes) [Pa]; `slide` dS_i (steps,) [m]; `dt` Δt_i (steps,) [s];
    `sliding_distance` S at the start of the block [m].
    """

    pressure: object
    slide: object
    dt: object
    sliding_distance: object


class Effect(eqx.Module):
    """Base of all effects. Subclasses set `name`, `parameters`, `signature` and override
    any of the hooks below. They hold no state: their strengths live in
    `Params.effect_params` under the study keys of `parameters`.
    """

    name: ClassVar[str] = ""
    parameters: ClassVar[dict[str, EffectParameter]] = {}
    signature: ClassVar[str] = ""
    structural: ClassVar[bool] = False

    def friction(self, p, sense):
        """Coulomb coefficient times sliding sense per step, or None (no friction)."""
        return None

    def local_rate(self, p, rate, ctx: RateContext):
        """Wear per step and node [m], (steps, nodes). Base model: K_d p_ij dS_i."""
        return rate

    def block_factor(self, p, sliding_start, sliding_per_cycle, cycles):
        """Multiplier of a block of `cycles` cycles' wear (profile frozen within the block)."""
        return jnp.ones(())


_REGISTRY: dict[str, Effect] = {}


def register_effect(effect: Effect) -> Effect:
    """Make an effect available by name to studies, `calibrate` and `diagnose`."""
    if not effect.name or not isinstance(effect.name, str):
        raise ValueError("an effect needs a non-empty string `name`")
    for key, spec in effect.parameters.items():
        if not (spec.lower <= spec.default <= spec.upper):
            raise ValueError(f"effect {effect.name}: default of {key} outside its bounds")
    _REGISTRY[effect.name] = effect
    return effect


def get_effect(name: str) -> Effect:
    return _REGISTRY[name]


def registered_effects() -> dict[str, Effect]:
    return dict(_REGISTRY)


def effect_parameter_specs() -> dict[str, EffectParameter]:
    out = {}
    for eff in _REGISTRY.values():
        out.update(eff.parameters)
    return out


def safe_power(x, exponent):
    """x**exponent for x ≥ 0 with finite gradients at x = 0 (where the result is 0)."""
    pos = x > 0
    return jnp.where(pos, jnp.where(pos, x, 1.0) ** exponent, 0.0)
