"""`jaxwear diagnose STUDY.toml [--out DIR] [--json FILE]` (DESIGN §7)."""

from __future__ import annotations

from pathlib import Path

DIAGNOSE_OUTPUTS = ("diagnosis.json", "residuals.csv", "report.html")


def open_diagnose_outputs(study, out_dir, json_file=None):
    """The output guard of `diagnose` (before any work)."""
    from ._io import open_outputs

    return open_outputs(study, out_dir, planned=DIAGNOSE_OUTPUTS, json_file=json_file)


def write_outputs(diag, out_dir, json_file=None) -> dict:
    """Write diagnosis.json, report.html and residuals.csv under `out_dir` (a folder, or the
    `OutputDir` from `open_diagnose_outputs`) and the JSON to `json_file` if given. Returns
    the JSON document."""
    from ._io import OutputDir
    from .diagnose._html import report_html

    out = out_dir if isinstance(out_dir, OutputDir) else open_diagnose_outputs(
        diag.study, out_dir, json_file)
    doc = diag.to_json()
    out.write_json("diagnosis.json", doc)
    m = diag.model
    after = diag.final.ev.pred
    rows = [(m.exp_names[e], x, t, y, pb, pa)
            for e, x, t, y, pb, pa in zip(m.row_exp, m.row_x, m.row_time, m.measured,
                                          diag.base.ev.pred, after)]
    hist = m.is_max.all()
    out.write_csv("residuals.csv", ["experiment", "hours" if hist else "angle_deg",
                                    "hours" if hist else "revolutions", "measured_um",
                                    "base_um", "after_um"], rows)
    out.write_text("report.html", report_html(diag, doc))
    out.write_json_file(doc)
    return doc


def cmd_diagnose(args):
    from ._budget import check_work
    from ._study import load_study
    from .diagnose import diagnose

    study = load_study(args.study)
    out = open_diagnose_outputs(study, args.out, args.json)
    check_work(study, tangents=1 + len(study.experiments) + 4)  # + a candidate's strengths
    diag = diagnose(study, verbose=True)
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
              + ("" if err <= tol else "; ABOVE tolerance: lower numerics.wear_tolerance_um"
                 " and rerun"))
    else:
        print(f"integration (paper, eq 23): {integ['steps']} updates; no error estimate "
              f"(compare with half numerics.revolutions_per_update)")
    print(f"wrote {Path(args.out) / 'report.html'}, {Path(args.out) / 'diagnosis.json'}"
          + (f", {args.json}" if args.json else ""))
