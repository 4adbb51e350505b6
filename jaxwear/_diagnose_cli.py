"""`jaxwear diagnose STUDY.toml [--out DIR] [--json FILE]` (DESIGN §7)."""

from __future__ import annotations

from pathlib import Path


def _inputs(study):
    files = [study.path]
    for e in study.experiments:
        for d in (e.profile, e.history):
            if d is not None and d.path:
                files.append(Path(d.path))
    return files


def write_outputs(diag, out_dir, json_file=None) -> dict:
    """Write diagnosis.json, report.html and residuals.csv under `out_dir` (and the JSON to
    `json_file` if given). Returns the JSON document."""
    from ._report import OutputDir
    from .diagnose._html import report_html

    out = OutputDir(out_dir, _inputs(diag.study))
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
    out.path("report.html").write_text(report_html(diag, doc), encoding="utf-8")
    if json_file:
        p = Path(json_file)
        if p.resolve() in {Path(f).resolve() for f in _inputs(diag.study)}:
            from ._errors import InputError

            raise InputError(f"{p}: refusing to overwrite an input file; choose another --json")
        p.parent.mkdir(parents=True, exist_ok=True)
        out.write_json(p.resolve(), doc)
    return doc


def cmd_diagnose(args):
    from ._study import load_study
    from .diagnose import diagnose

    study = load_study(args.study)
    diag = diagnose(study, verbose=True)
    doc = write_outputs(diag, args.out, args.json)
    v = doc["verdict"]
    name = " + ".join(v["effects"]) if v["effects"] else "none"
    print(f"verdict: {v['status']} (missing effect: {name}); base RMSE "
          f"{doc['baseline']['rmse_um']:.4g} µm, after {doc['after']['rmse_um']:.4g} µm, "
          f"noise {doc['baseline']['noise_um']:.4g} µm")
    print(f"wrote {Path(args.out) / 'report.html'}, {Path(args.out) / 'diagnosis.json'}"
          + (f", {args.json}" if args.json else ""))
