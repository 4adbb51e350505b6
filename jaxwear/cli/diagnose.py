"""`jaxwear diagnose STUDY.toml [--shape] [--out DIR] [--json FILE]` (design.md §7).

Writes under DIR: `diagnosis.json` (the §7 document), `residuals.csv` (one row per measured
point: measured, base model and the model after, in µm) and `report.html`; `--json FILE`
the document too. With the shape analysis (`--shape`, or an unexplained verdict):
`shape_<variable>.png` per state variable (and `shape_after_effect_<variable>.png`),
`missing_wear.py` and, where the law search found one, `law.py` (design.md §7 `shape.law`).
Its last lines are the verdict's status, `headline` and `summary`, as the JSON has them.
"""

from __future__ import annotations

from pathlib import Path

from jaxwear._analyses import diagnose as _diagnosis
from jaxwear._analyses.diagnose._refit import MIN_TRIPLES, too_few_triples
from jaxwear._analyses.diagnose._stats import noise_triples
from jaxwear._core.errors import InputError
from jaxwear._inference.packing import study_fit_keys
from jaxwear._physics.effects import effect_parameter_specs
from jaxwear._report.diagnosis import DIAGNOSE_OUTPUTS, shape_outputs, write_outputs
from jaxwear._report.shape_plot import shape_pngs
from jaxwear._study.data_checks import check_noise_measurable, check_wear_measured
from jaxwear._study.outside import loud_lines
from jaxwear.cli._pipeline import Verb, fit_columns


class Diagnose(Verb):
    fits_data = True
    name = "diagnose"
    help = "find the physics the base model is missing"
    takes_json = True

    def add_arguments(self, p):
        p.add_argument("--shape", action="store_true",
                       help="always analyse the shape of the missing wear (default: only "
                            "when the verdict is unexplained)")

    def resolve(self, study, opts):
        check_wear_measured(study)  # before the noise: all zeros is the plainer reason
        check_noise_measurable(study)  # a noise level of 0 weights the misfit by 1/0

    def outputs(self, study, opts):
        return list(DIAGNOSE_OUTPUTS + shape_outputs())

    def tangents(self, study, opts):

        # the base fit's columns, and every candidate's strengths: one extended model
        # carries them all (effects switched by masks)
        try:
            keys = study_fit_keys(study)
        except InputError as e:  # the names come from the study here, not from --fit
            raise InputError(f"{study.path}: fit.parameters: "
                             f"{str(e).removeprefix('--fit: ')}") from None
        return fit_columns(study, keys) + len(effect_parameter_specs())

    def run(self, study, out, opts):


        # the data must give their own noise level (unless the study states it): counted
        # from the files before the engine starts, not after its model has compiled
        if study.noise_um is None:
            triples, rows = noise_triples(study)
            if triples < MIN_TRIPLES:
                raise InputError(too_few_triples(study, triples, rows))

        args = opts["args"]
        # the engine looked up at the call: tests stand in for it
        diag = _diagnosis.diagnose(study, verbose=True, shape=bool(getattr(args, "shape", False)),
                            figures=shape_pngs)
        doc = write_outputs(diag, out)
        for line in loud_lines(doc["outside_model"]):  # answers outside the model first
            print(line)
        v = doc["verdict"]
        integ = doc["after"]["integration"]
        if integ["integrator"] == "adaptive":
            err, tol = float(integ["error_estimate_um"]), integ["tolerance_um"]
            print(f"integration (adaptive) at the final fit: error estimate {err:.3g} µm "
                  f"(tolerance {tol:g} µm) in {integ['steps']} steps"
                  + ("" if err <= tol else "; ABOVE tolerance: lower "
                     "numerics.wear_tolerance_um and rerun"))
        else:
            err = integ["error_estimate_um"]
            print(f"integration (paper, eq 23): {integ['steps']} updates; Euler's estimate "
                  f"{err if isinstance(err, str) else f'{err:.3g}'} µm (a bound; compare with "
                  f"half numerics.revolutions_per_update)")
        print(f"wrote {Path(args.out) / 'report.html'}, {Path(args.out) / 'diagnosis.json'}"
              + (f", {args.json}" if args.json else ""))
        # the answer last, as the JSON says it (`_headline`): a script and a person read
        # the same verdict
        print(f"verdict: {v['status']}")
        print(v["headline"])
        if v["summary"]:
            print(v["summary"])
        return diag
