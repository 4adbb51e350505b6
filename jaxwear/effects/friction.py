"""Coulomb friction in the contact (DESIGN §5)."""

import jax.numpy as jnp

from ._base import Effect, EffectParameter


class Friction(Effect):
    """Σ_j A_j p_j (n_j + μ s t_j) = W, s the sign of the pin's rotation relative to the
    bushing: friction tilts the contact against the sliding direction.

    Signature in data: each wear zone shifts in angle (by about atan μ) and skews, in the
    direction set by the sense of sliding; the shift is the same at all speeds.
    """

    name = "friction"
    parameters = {"friction_coefficient": EffectParameter(1.0, 0.0, 0.0, 0.0, 1.0,
                                                          "μ: Coulomb coefficient [-]", scale=0.1)}
    signature = "wear zones shifted and skewed in angle against the sliding direction"

    def friction(self, p, sense):
        return p.effect_params["friction_coefficient"] * jnp.asarray(sense)
