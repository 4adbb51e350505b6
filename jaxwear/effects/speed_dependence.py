"""Speed-dependent wear coefficient (DESIGN §5)."""

from ._base import Effect, EffectParameter, safe_power

V_REF = 0.01  # m/s


class SpeedDependence(Effect):
    """K_d → K_d (v/v_ref)^q, v = dS_i/Δt_i the sliding speed, v_ref = 0.01 m/s.

    Signature in data: experiments at different crank speeds need different K_d; within a
    revolution, wear shifts towards the fast-sliding steps (dead centres).
    """

    name = "speed_dependence"
    parameters = {"speed_exponent": EffectParameter(1.0, 0.0, 0.0, -3.0, 3.0,
                                                    "q: exponent of sliding speed [-]", scale=0.1)}
    signature = "K_d differs between crank speeds (speed sweep residuals of one sign trend)"

    def local_rate(self, p, rate, ctx):
        q = p.effect_params["speed_exponent"]
        v = ctx.slide / ctx.dt
        return rate * safe_power(v / V_REF, q)[:, None]
