"""Running-in: a fresh surface wears faster until asperities are levelled (DESIGN §5)."""

import jax.numpy as jnp

from ._base import Effect, EffectParameter


class RunningIn(Effect):
    """K_d → K_d (1 + a e^(-S/S_r)), S the accumulated sliding distance [m].

    Physics: the first metres of sliding level the surface roughness and lay down a
    transfer film; until then wear is faster. `a` is the initial excess (a = 1: twice the
    steady rate), `S_r` the sliding distance over which it decays.

    Signature in data: more wear early than late, the same excess (in sliding distance) in
    every experiment. It is nearly invisible in one final profile (K_d and the clearances
    absorb it); interrupted tests or depth-vs-time data show a depth that grows faster than
    the base model at first. When the data end long after S_r, only the product a·S_r (the
    extra wear in metres of equivalent steady sliding) is identifiable.

    The factor is averaged exactly over each block of M cycles (profile frozen), so the
    amplification M does not bias it.
    """

    name = "running_in"
    parameters = {
        "running_in_amplitude": EffectParameter(
            1.0, 1.0, 0.0, 0.0, 100.0, "a: initial excess wear factor [-]", scale=1.0,
            realistic=1.0, per="running_in_distance_m"),
        "running_in_distance_m": EffectParameter(
            1.0, 20.0, 20.0, 1e-3, 1e5, "S_r: sliding distance of running-in [m]", log=True),
    }
    signature = ("excess wear early in life, decaying with sliding distance (deeper than "
                 "predicted at the first measurements, in every experiment)")

    def block_factor(self, p, sliding_start, sliding_per_cycle, cycles):
        a = p.effect_params["running_in_amplitude"]
        sr = p.effect_params["running_in_distance_m"]
        x = cycles * sliding_per_cycle / sr
        xs = jnp.where(x > 0, x, 1.0)
        mean_decay = jnp.where(x > 0, -jnp.expm1(-xs) / xs, 1.0)
        return 1.0 + a * jnp.exp(-sliding_start / sr) * mean_decay
