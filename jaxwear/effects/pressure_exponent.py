"""Non-linear pressure dependence of wear (DESIGN §5)."""

from ._base import Effect, EffectParameter, safe_power

P_REF = 1.0e6  # Pa


class PressureExponent(Effect):
    """dh = K_d p_ref (p/p_ref)^(1+b) dS, p_ref = 1 MPa.

    Signature in data: b > 0 sharpens the wear zones (deeper peak, narrower flanks) and makes
    high-load experiments (small clearance, high speed) wear more than K_d predicts.
    """

    name = "pressure_exponent"
    parameters = {"pressure_exponent": EffectParameter(1.0, 0.0, 0.0, -0.9, 3.0,
                                                       "b: extra pressure exponent [-]", scale=0.1)}
    signature = "profile shape: peak depth vs flank width ratio; load-dependent K_d"

    def local_rate(self, p, rate, ctx):
        b = p.effect_params["pressure_exponent"]
        return rate * safe_power(ctx.pressure / P_REF, b)
