"""`jaxwear diagnose STUDY.toml [--shape] [--out DIR] [--json FILE]` (DESIGN §7).

Writes under DIR: `diagnosis.json` (the §7 document), `residuals.csv` (one row per measured
point: measured, base model and the model after, in µm) and `report.html`; `--json FILE`
the document too. With the shape analysis (`--shape`, or an unexplained verdict):
`shape_<variable>.png` per state variable (and `shape_after_effect_<variable>.png`),
`missing_wear.py` and, where the law search found one, `law.py` (DESIGN §7 `shape.law`).
"""

from __future__ import annotations

from pathlib import Path

from .._config import TIMED_DRIVERS
from .._errors import InputError
from ..diagnose._law_file import EFFECT_NAME, law_file_source
from ._pipeline import Verb, fit_columns

DIAGNOSE_OUTPUTS = ("diagnosis.json", "residuals.csv", "report.html")


def shape_outputs() -> tuple[str, ...]:
    """The shape analysis's outputs (written when it runs: `--shape`, or an unexplained
    verdict): `shape_<variable>.png` per variable and form (`shape_deposit_<variable>.png`),
    `shape_when_where.png`, the effect file `missing_wear.py`, and the same with
    `shape_after_effect_` / `missing_wear_after_effect.py` on top of an effect found."""
    from ..diagnose._shape_plot import file_stem
    from ..effects.shape import DEPOSIT_VARIABLES, VARIABLES

    labels = list(VARIABLES) + [f"deposit:{n}" for n in DEPOSIT_VARIABLES]
    out = []
    for prefix in ("shape", "shape_after_effect"):
        out += [prefix + file_stem(lab).removeprefix("shape") + ".png" for lab in labels]
        out.append(f"{prefix}_when_where.png")
    return tuple(out) + ("missing_wear.py", "missing_wear_after_effect.py", "law.py")


def open_diagnose_outputs(study, out_dir, json_file=None):
    """The output guard of `diagnose` (before any work)."""
    from .._io import open_outputs

    return open_outputs(study, out_dir, planned=DIAGNOSE_OUTPUTS + shape_outputs(),
                        json_file=json_file)


def residual_table(diag) -> tuple[list[str], list[tuple]]:
    """(header, rows) of residuals.csv. A history row has one coordinate, its time in hours
    (it once got an `hours` column twice); a profile row has its angle and the count it was
    measured at (revolutions, or hours for the oscillating joint); the angle is left empty
    on history rows of a study that has both."""
    m = diag.model
    after = diag.final.ev.pred
    hist = [bool(x) for x in m.is_max]
    osc = diag.study.config.driver in TIMED_DRIVERS
    values = ["measured_um", "base_um", "after_um"]
    data = list(zip(m.measured, diag.base.ev.pred, after))
    names = [m.exp_names[e] for e in m.row_exp]
    if all(hist):
        return (["experiment", "hours", *values],
                [(n, t, *v) for n, t, v in zip(names, m.row_time, data)])
    rows = [(n, "" if h else x, t, *v)
            for n, h, x, t, v in zip(names, hist, m.row_x, m.row_time, data)]
    return ["experiment", "angle_deg", "hours" if osc else "revolutions", *values], rows


def write_outputs(diag, out_dir, json_file=None) -> dict:
    """Write diagnosis.json, report.html and residuals.csv under `out_dir` (a folder, or the
    `OutputDir` from `open_diagnose_outputs`) and the JSON to `json_file` if given. Returns
    the JSON document."""
    from .._io import OutputDir
    from ..diagnose._html import report_html

    out = out_dir if isinstance(out_dir, OutputDir) else open_diagnose_outputs(
        diag.study, out_dir, json_file)
    doc = diag.to_json()
    saved = {}
    for prefix, key, res in (("shape", "shape", diag.shape),
                             ("shape_after_effect", "shape_after_effect",
                              diag.shape_after_effect)):
        if res is None:
            continue
        from .._report import plt
        from ..diagnose._effect_file import effect_file_source
        from ..diagnose._shape_plot import file_stem, shape_figure, when_where_figure

        mine = saved.setdefault(key, {})
        for v in res.variables:
            name = prefix + file_stem(v.label).removeprefix("shape") + ".png"
            if v.label in res.pngs:  # drawn while the refit ran (`diagnose(figures=)`)
                mine[v.label] = out.write_bytes(name, res.pngs[v.label])
                continue
            fig = shape_figure(res, v.label)
            mine[v.label] = out.savefig(fig, name)
            plt().close(fig)
        if res.when_where is not None:
            fig = when_where_figure(res)
            mine["when_where"] = out.savefig(fig, f"{prefix}_when_where.png")
            plt().close(fig)
        if res.best is not None and res.correction:
            name = "missing_wear.py" if key == "shape" else "missing_wear_after_effect.py"
            out.write_text(name, effect_file_source(res, str(diag.study.path)))
            doc[key]["effect_file"] = name
        law = getattr(res, "law", None)
        if key == "shape" and law is not None and law.best is not None:
            # the law found from the shape, beside missing_wear.py (DESIGN §7 shape.law)
            b = law.best
            out.write_text("law.py", law_file_source(
                b.law, b.constants, study_path=str(diag.study.path), rmse_um=b.rmse_um,
                loo_rmse_um=b.loo_rmse_um, noise_um=law.noise_um))
            doc[key]["law"].update(file="law.py", effect=EFFECT_NAME)
    out.write_json("diagnosis.json", doc)
    header, rows = residual_table(diag)
    out.write_csv("residuals.csv", header, rows)
    out.write_text("report.html", report_html(diag, doc, saved))
    out.write_json_file(doc)
    return doc


class Diagnose(Verb):
    name = "diagnose"
    help = "find the physics the base model is missing"
    takes_json = True

    def add_arguments(self, p):
        p.add_argument("--shape", action="store_true",
                       help="always analyse the shape of the missing wear (default: only "
                            "when the verdict is unexplained)")

    def outputs(self, study, opts):
        return list(DIAGNOSE_OUTPUTS + shape_outputs())

    def tangents(self, study, opts):
        from .._packing import study_fit_keys
        from ..effects import effect_parameter_specs

        # the base fit's columns, and every candidate's strengths: one extended model
        # carries them all (effects switched by masks)
        try:
            keys = study_fit_keys(study)
        except InputError as e:  # the names come from the study here, not from --fit
            raise InputError(f"{study.path}: fit.parameters: "
                             f"{str(e).removeprefix('--fit: ')}") from None
        return fit_columns(study, keys) + len(effect_parameter_specs())

    def run(self, study, out, opts):
        import importlib

        from ..diagnose._refit import MIN_TRIPLES, too_few_triples
        from ..diagnose._stats import noise_triples

        # the data must give their own noise level (unless the study states it): counted
        # from the files before the engine starts, not after its model has compiled
        if study.noise_um is None:
            triples, rows = noise_triples(study)
            if triples < MIN_TRIPLES:
                raise InputError(too_few_triples(study, triples, rows))

        # the package (`jaxwear.diagnose` the attribute is the function), looked up now:
        # tests stand in for the engine
        dia = importlib.import_module("jaxwear.diagnose")

        args = opts["args"]
        diag = dia.diagnose(study, verbose=True, shape=bool(getattr(args, "shape", False)),
                            figures=True)
        doc = write_outputs(diag, out)
        v = doc["verdict"]
        name = " + ".join(v["effects"]) if v["effects"] else "none"
        print(f"verdict: {v['status']} (missing effect: {name}); base RMSE "
              f"{doc['baseline']['rmse_um']:.4g} µm, after {doc['after']['rmse_um']:.4g} µm, "
              f"noise {doc['baseline']['noise_um']:.4g} µm")
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
        return diag
