"""Running-in: a fresh surface wears faster until asperities are levelled (DESIGN §5)."""

import jax.numpy as jnp

from ._base import Effect, EffectParameter


class RunningIn(Effect):
    """K_d → K_d (1 + a e^(-S/S_r)), S the accumulated sliding distance.

    Signature in data: more wear early than late. Invisible in one final profile (K_d and the
    clearances absorb it); seen in interrupted tests or depth-vs-time data as a depth that
    grows faster than linearly at first, the same excess in every experiment.
    The factor is averaged exactly over each block of M cycles (profile frozen), so the
    amplification M does not bias it.
    """

    name = "running_in"
    parameters = {
        "running_in_amplitude": EffectParameter(1.0, 1.0, 0.0, 0.0, 100.0,
                                                "a: initial excess wear factor [-]"),
        "running_in_distance_m": EffectParameter(1.0, 20.0, 20.0, 1e-3, 1e5,
                                                 "S_r: sliding distance of running-in [m]",
                                                 log=True),
    }
    signature = "excess wear early in life, decaying with sliding distance (all experiments)"

    def block_factor(self, p, sliding_start, sliding_per_cycle, cycles):
        a = p.effect_params["running_in_amplitude"]
        sr = p.effect_params["running_in_distance_m"]
        x = cycles * sliding_per_cycle / sr
        xs = jnp.where(x > 0, x, 1.0)
        mean_decay = jnp.where(x > 0, -jnp.expm1(-xs) / xs, 1.0)
        return 1.0 + a * jnp.exp(-sliding_start / sr) * mean_decay
