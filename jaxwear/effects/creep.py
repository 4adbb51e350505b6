"""Creep (cold flow) of polymer layers (DESIGN §5)."""

from ._base import Effect, EffectParameter


class Creep(Effect):
    """dh_j += C p_j Δt_i per step, independent of sliding.

    Signature in data: depth where the load dwells while sliding is slow (near the slider's
    mid-stroke, steps ~90 and ~270, where Φ̇2 → 0), and more depth at low speed for the same
    revolutions (more time per revolution).
    """

    name = "creep"
    parameters = {"creep_m_per_Pa_s": EffectParameter(1.0, 0.0, 0.0, 0.0, 1e-13,
                                                      "C: cold-flow rate [m/(Pa s)]", scale=1e-16)}
    signature = "depth that scales with time under load, not sliding (slow experiments)"

    def local_rate(self, p, rate, ctx):
        return rate + p.effect_params["creep_m_per_Pa_s"] * ctx.pressure * ctx.dt[:, None]
