"""Non-linear pressure dependence of wear (design.md §5)."""

from jaxwear._physics.effects._base import Effect, safe_power
from jaxwear._physics.effects.parameter import EffectParameter

P_REF = 1.0e6  # Pa


class PressureExponent(Effect):
    """dh = K_d p_ref (p/p_ref)^(1+b) dS, p_ref = 1 MPa.

    Physics: Archard's law is linear in pressure; polymers often wear faster than linearly
    at high contact pressure (b > 0: p^1.2-1.5 is common for PTFE composites), metals
    under mild wear sometimes slower (b < 0).

    Signature in data: b > 0 sharpens the wear zones (deeper peak, narrower flanks) and
    makes the early, high-pressure wear of a fresh bore faster (the pressure falls as the
    bore conforms); small clearances and high loads wear more than K_d predicts.
    """

    name = "pressure_exponent"
    parameters = {"pressure_exponent": EffectParameter(
        1.0, 0.0, 0.0, -0.9, 3.0, "b: extra pressure exponent [-]", scale=0.1,
        realistic=0.3)}
    signature = ("profile shape: peaks deeper and flanks narrower than predicted; faster "
                 "wear while the contact pressure is high")

    def local_rate(self, p, rate, ctx):
        b = p.effect_params["pressure_exponent"]
        return rate * safe_power(ctx.pressure / P_REF, b)
