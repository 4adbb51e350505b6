"""A user-defined effect in a few lines: registered, then found by `diagnose` and fitted by
`calibrate`, without touching jaxwear's core.

    python calibration/examples/custom_effect.py            # small grid, about a minute
    python calibration/examples/custom_effect.py --out DIR  # also write the report

The effect: wear debris trapped in the joint abrades the layer, so the wear rate grows with
the sliding distance already covered, K_d → K_d (1 + g S / 100 m). See docs/effects.md.
"""

import argparse
import tempfile

import jaxwear as jw


# ---- the effect: 15 lines ------------------------------------------------------------
class DebrisAbrasion(jw.Effect):
    """K_d → K_d (1 + g S/S_ref), S the accumulated sliding distance, S_ref = 100 m.
    Signature: depth grows faster than the base model late in each test."""

    name = "debris"
    parameters = {"debris_gain": jw.EffectParameter(
        to_si=1.0, default=0.0, off=0.0, lower=0.0, upper=20.0,
        doc="g: extra wear per 100 m of sliding [-]", scale=0.1, realistic=0.5)}
    signature = "wear accelerating with sliding distance (late profiles deeper than predicted)"

    def block_factor(self, p, sliding_start, sliding_per_cycle, cycles):
        # exact mean of the linear factor over the block of `cycles` cycles
        mid = sliding_start + 0.5 * cycles * sliding_per_cycle
        return 1.0 + p.effect_params["debris_gain"] * mid / 100.0


jw.register_effect(DebrisAbrasion())
# ---------------------------------------------------------------------------------------


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="write the diagnosis report here")
    args = ap.parse_args(argv)
    small = dict(nodes=64, steps_per_rev=72, revolutions_per_update=500)
    with tempfile.TemporaryDirectory() as tmp:
        # 1. a virtual rig hides the new effect at its realistic strength (g = 0.5)
        res = jw.synthesize(["debris"], "paper", noise_um=0.3, seed=1, numerics=small, out=tmp)
        # 2. diagnose the study as written (base model): the new effect is a candidate
        diag = jw.diagnose(res.study, verbose=True)
        print("verdict:", diag.status, diag.effects)
        if args.out:
            jw.write_diagnosis(diag, args.out)
        # 3. calibrate with the effect switched on: its strength is fitted with K_d, clearances
        fit = jw.calibrate(res.study.with_config(effects=("debris",)))
        g = fit.parameters_json()["debris_gain"]
        print(f"calibrate: debris_gain = {g['value']:.3f} ± {g['stderr']:.3f} "
              f"(truth {res.truth['hidden']['debris']['debris_gain']}); "
              f"RMSE {fit.rmse_um:.3f} µm")
    return diag, fit


if __name__ == "__main__":
    main()
