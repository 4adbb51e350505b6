"""`jaxwear sensitivity STUDY.toml [--out DIR]`: normalised sensitivities of every experiment."""

from __future__ import annotations

import sys

import numpy as np

from jaxwear._analyses import sensitivity as sen
from jaxwear._physics.params import PARAMETER_KEYS
from jaxwear._report.figures import sensitivity_chart
from jaxwear.cli._pipeline import Verb

SENSITIVITY_OUTPUTS = ("sensitivity.csv", "sensitivity.json", "sensitivity.png")


class Sensitivity(Verb):
    name = "sensitivity"
    help = "normalised sensitivities by autodiff"

    def outputs(self, study, opts):
        return list(SENSITIVITY_OUTPUTS)

    def tangents(self, study, opts):

        return len(PARAMETER_KEYS)

    def run(self, study, out, opts):

        print(f"sensitivity: {len(study.experiments)} experiments, autodiff through the "
              f"wear loop (forward or reverse mode by the runs' length; the first compiles "
              f"it)", file=sys.stderr, flush=True)
        results = sen.study_sensitivities(study, progress=True)
        rows = []
        for name, r in results.items():
            for k, v, u, a, b in zip(r.keys, r.values, r.units, r.peak, r.volume):
                rows.append((name, k, u, v, a, b))
        out.write_csv("sensitivity.csv", ["experiment", "parameter", "unit", "value",
                                          "dln_peak_depth_dln_param",
                                          "dln_worn_volume_dln_param"], rows)
        out.write_json("sensitivity.json", {name: {
            "peak_depth_um": r.peak_depth_um, "worn_volume_mm3": r.worn_volume_mm3,
            "worn_through_cycle": r.worn_through_cycle, "sensitivities": r.as_dict(),
            "autodiff_mode": r.mode,
            "integration": {"integrator": study.integrator,
                            "error_estimate_um": r.error_estimate_um, "steps": r.steps,
                            "tolerance_um": study.wear_tolerance_um
                            if study.integrator != "paper" else None}}
            for name, r in results.items()})
        sensitivity_chart(out.path("sensitivity.png"), results)
        print("normalised sensitivities d ln y / d ln θ (a 1 % change of θ changes y by S %)")
        for name, r in results.items():
            print(f"\n{name}: peak depth {r.peak_depth_um:.4g} µm, worn volume "
                  f"{r.worn_volume_mm3:.4g} mm³; integration error estimate "
                  f"{r.error_estimate_um:.3g} µm in {r.steps} steps")
            if r.worn_through_cycle >= 0:
                print(f"  WARNING: the layer wears through at cycle {r.worn_through_cycle:.0f};"
                      f" these sensitivities describe a bore worn past its layer")
            w = max(len(k) for k in r.keys) + 2
            print(f"  {'parameter':<{w}}{'value':>12}  {'unit':<8}{'peak depth':>11}"
                  f"{'worn volume':>13}")
            order = np.argsort(-np.abs(r.peak))
            for i in order:
                print(f"  {r.keys[i]:<{w}}{r.values[i]:>12.5g}  {r.units[i]:<8}"
                      f"{r.peak[i]:>+11.4f}{r.volume[i]:>+13.4f}")
        print(f"\nwrote {out.root / 'sensitivity.csv'}, sensitivity.json, sensitivity.png")
        return results
