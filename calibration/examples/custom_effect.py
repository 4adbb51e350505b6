"""A user-defined effect in a few lines (debris_effect.py): loaded, then found by `diagnose`
and fitted by `calibrate`, without touching jaxwear's core.

    python calibration/examples/custom_effect.py            # small grid, about a minute
    python calibration/examples/custom_effect.py --out DIR  # also write the report

The effect: wear debris trapped in the joint abrades the layer, so the wear rate grows with
the sliding distance already covered, K_d → K_d (1 + g S / 100 m). A study uses the same
file with `[model] effect_files = ["debris_effect.py"]` (the command line then needs no
script of yours). See docs/effects.md.
"""

import argparse
import tempfile
from pathlib import Path

import jaxwear as jw
from jaxwear.effects import load_effect_file

# The effect lives in a file of its own (debris_effect.py, 15 lines), as a study loads it
# with `[model] effect_files = ["debris_effect.py"]`; here the script loads it directly.
load_effect_file(Path(__file__).with_name("debris_effect.py"))


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
