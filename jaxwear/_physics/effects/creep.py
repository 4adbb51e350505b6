"""Creep (cold flow) of polymer layers (design.md §5)."""

from jaxwear._physics.effects._base import Effect
from jaxwear._physics.effects.parameter import EffectParameter


class Creep(Effect):
    """dh_j += C p_j Δt_i per step, independent of sliding.

    Physics: a polymer layer under sustained pressure flows out of the loaded zone (PTFE
    cold flow), which a profile measurement reads as depth. Linear in pressure and time,
    the simplest law; C ≥ 0.

    Signature in data: depth that scales with time under load, not with sliding: slow
    experiments (more seconds per revolution) wear more per revolution, and depth builds up
    where the load dwells while sliding is slow (Φ̇2 → 0 near the crank's quarter turns).
    """

    name = "creep"
    parameters = {"creep_m_per_Pa_s": EffectParameter(
        1.0, 0.0, 0.0, 0.0, 1e-13, "C: cold-flow rate [m/(Pa s)]", scale=1e-16,
        realistic=1e-15)}
    signature = ("depth that grows with time under load rather than sliding: slow "
                 "experiments deeper than predicted")

    def local_rate(self, p, rate, ctx):
        return rate + p.effect_params["creep_m_per_Pa_s"] * ctx.pressure * ctx.dt[:, None]
