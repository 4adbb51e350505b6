"""A user effect in a file of its own: what a study loads with

    [model]
    effect_files = ["debris_effect.py"]   # relative to the study file
    effects = ["debris"]                  # switch it on (or leave it off: a diagnose candidate)

Wear debris trapped in the joint abrades the layer, so the wear rate grows with the sliding
distance already covered: K_d → K_d (1 + g S / 100 m). `custom_effect.py` runs the loop with
it (hidden in a virtual rig, found by `diagnose`, fitted by `calibrate`); docs/effects.md.
"""

import jaxwear as jw


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
