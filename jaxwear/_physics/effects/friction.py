"""Coulomb friction in the contact (design.md §5)."""

import jax.numpy as jnp

from jaxwear._physics.effects._base import Effect
from jaxwear._physics.effects.parameter import EffectParameter


class Friction(Effect):
    """Σ_j A_j p_j (n_j + μ s t_j) = W, s the sign of the pin's rotation relative to the
    bushing: the friction traction tilts the resultant contact force against the sliding
    direction, so the pressure peak moves off the load line.

    Physics: dry PTFE on steel has μ ≈ 0.05-0.2; the base model's frictionless contact
    puts the pressure peak exactly on the load direction.

    Signature in data: each wear zone shifted (by about atan μ) and skewed in angle, in the
    direction set by the sense of sliding during the steps that load it; the same shift at
    every speed and revolution count.
    """

    name = "friction"
    parameters = {"friction_coefficient": EffectParameter(
        1.0, 0.0, 0.0, 0.0, 1.0, "μ: Coulomb friction coefficient [-]", scale=0.1,
        realistic=0.1)}
    signature = "wear zones shifted and skewed in angle against the sliding direction"

    def friction(self, p, sense):
        return p.effect_params["friction_coefficient"] * jnp.asarray(sense)
