"""From the shape of the missing wear to a new effect, and the error falling (docs/effects.md).

    python calibration/examples/shape_to_effect.py            # small grid, a few minutes
    python calibration/examples/shape_to_effect.py --out DIR  # also the reports and plots

1. A virtual rig hides physics the library does not have: extra wear where the joint load
   turns fast (impacts at the force reversals). It is registered only while the data are
   made, so `diagnose` has no candidate for it.
2. `diagnose --shape` on the study as written: the shape of the missing wear names the
   state variable it follows (the load turn rate) and where its g rises.
3. From that plot the user writes the effect below (15 lines): the rate steps up above a
   turn rate ω0, read off the shape where g crosses half-way. It is not the hidden law (a
   smooth rise in log ω): the user's guess, as in real life. ω0 is where ĝ steps up
   (`jaxwear.diagnose.threshold`), what one reads off the plot.
4. `diagnose` with the new effect registered: it is named, and the error falls to noise.
"""

from __future__ import annotations

import argparse
import math
import tempfile

import jax.numpy as jnp

import jaxwear as jw
from jaxwear.diagnose import threshold
from jaxwear.effects.shape import state_variables

SMALL = dict(nodes=64, steps_per_rev=72, revolutions_per_update=500)


# ---- 1. the hidden physics (the virtual rig's, not the user's) -----------------------
class _Impacts(jw.Effect):
    name = "hidden_impacts"
    parameters = {"hidden_impacts_gain": jw.EffectParameter(
        1.0, 0.0, 0.0, 0.0, 100.0, "extra wear factor at fast load turns", realistic=3.0)}
    signature = "hidden"

    def local_rate(self, p, rate, ctx):
        w = state_variables(ctx.pressure, ctx.slide, ctx.dt, ctx.sliding_distance,
                            ctx.load_angle)["load_turn_rate_deg_per_s"]
        x = (jnp.log10(w + 1e-9) - math.log10(300.0)) / 0.1
        return rate * (1.0 + p.effect_params["hidden_impacts_gain"] / (1.0 + jnp.exp(-x)))


# ---- 3. the user's effect, written from the shape plot: 15 lines --------------------
def impact_effect(turn_threshold_deg_per_s: float):
    class ImpactWear(jw.Effect):
        """K_d → K_d (1 + a) where the load direction turns faster than ω0 (impacts)."""

        name = "impact"
        parameters = {"impact_gain": jw.EffectParameter(
            to_si=1.0, default=0.0, off=0.0, lower=0.0, upper=50.0,
            doc="a: extra wear factor where the load turns faster than ω0 [-]", scale=0.5)}
        signature = "extra wear at the force reversals, where the load turns fast"

        def local_rate(self, p, rate, ctx):
            w = state_variables(ctx.pressure, ctx.slide, ctx.dt, ctx.sliding_distance,
                                ctx.load_angle)["load_turn_rate_deg_per_s"]
            fast = (w > turn_threshold_deg_per_s).astype(rate.dtype)
            return rate * (1.0 + p.effect_params["impact_gain"] * fast)

    return ImpactWear()
# ---------------------------------------------------------------------------------------


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="write both diagnoses (reports, plots) here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        jw.register_effect(_Impacts())
        try:
            res = jw.synthesize(["hidden_impacts"], "paper", noise_um=0.3, seed=3,
                                numerics=SMALL, out=tmp)
        finally:
            jw.unregister_effect("hidden_impacts")
        # 2. what is missing, and its shape
        before = jw.diagnose(res.study, shape=True, verbose=True)
        print("verdict:", before.status, before.effects)
        print("shape:", before.shape.sentence)
        if args.out:
            jw.write_diagnosis(before, f"{args.out}/before")
        best = before.shape.best
        if best != "load_turn_rate_deg_per_s":
            raise SystemExit(f"the shape pointed at {best}, not the load turn rate")
        omega0 = threshold(before.shape.variable(best))  # where ĝ steps up
        print(f"read off the shape: the rate steps up above ω0 ≈ {omega0:.0f} deg/s")
        # 3-4. the user's effect, registered: diagnose names it and the error falls
        jw.register_effect(impact_effect(omega0))
        try:
            study = jw.load_study(res.study.path)  # Params now carry impact_gain
            after = jw.diagnose(study, verbose=True)
        finally:
            jw.unregister_effect("impact")
        if args.out:
            jw.write_diagnosis(after, f"{args.out}/after")
    print("verdict with the new effect:", after.status, after.effects)
    print(f"{'':28s}{'RMSE [µm]':>10s}")
    print(f"{'base model':28s}{before.base.rmse:10.3f}")
    print(f"{'+ ' + ' + '.join(after.effects):28s}{after.final.rmse:10.3f}")
    print(f"{'noise level':28s}{after.noise_um:10.3f}")
    return before, after, omega0


if __name__ == "__main__":
    main()
