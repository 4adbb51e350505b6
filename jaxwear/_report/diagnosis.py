"""What `diagnose` writes: diagnosis.json, residuals.csv, report.html, the shape figures and the
effect file (docs/design.md §7)."""

from __future__ import annotations

from jaxwear._core.io import OutputDir
from jaxwear._physics.config import TIMED_DRIVERS
from jaxwear._physics.effects.shape import DEPOSIT_VARIABLES, VARIABLES
from jaxwear._report.diagnose_html import report_html
from jaxwear._report.effect_file import effect_file_source
from jaxwear._report.figures import plt
from jaxwear._report.law_file import EFFECT_NAME, law_caveat, law_file_source
from jaxwear._report.shape_plot import WHEN_WHERE, file_stem, shape_figure, when_where_figure
from jaxwear._study.outputs import open_outputs

DIAGNOSE_OUTPUTS = ("diagnosis.json", "residuals.csv", "report.html")


def shape_outputs() -> tuple[str, ...]:
    """The shape analysis's outputs (written when it runs: `--shape`, or an unexplained
    verdict): `shape_<variable>.png` per variable and form (`shape_deposit_<variable>.png`),
    `shape_when_where.png`, the effect file `missing_wear.py`, and the same with
    `shape_after_effect_` / `missing_wear_after_effect.py` on top of an effect found."""

    labels = list(VARIABLES) + [f"deposit:{n}" for n in DEPOSIT_VARIABLES]
    out = []
    for prefix in ("shape", "shape_after_effect"):
        out += [prefix + file_stem(lab).removeprefix("shape") + ".png" for lab in labels]
        out.append(f"{prefix}_when_where.png")
    return tuple(out) + ("missing_wear.py", "missing_wear_after_effect.py", "law.py")


def open_diagnose_outputs(study, out_dir, json_file=None):
    """The output guard of `diagnose` (before any work)."""

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

    out = out_dir if isinstance(out_dir, OutputDir) else open_diagnose_outputs(
        diag.study, out_dir, json_file)
    doc = diag.to_json()
    saved = {}
    for prefix, key, res in (("shape", "shape", diag.shape),
                             ("shape_after_effect", "shape_after_effect",
                              diag.shape_after_effect)):
        if res is None:
            continue

        mine = saved.setdefault(key, {})
        for v in res.variables:
            name = prefix + file_stem(v.label).removeprefix("shape") + ".png"
            if v.label in res.pngs:  # drawn while the refit ran (`diagnose(figures=)`)
                mine[v.label] = out.write_bytes(name, res.pngs[v.label])
                continue
            fig = shape_figure(res, v.label)
            mine[v.label] = out.savefig(fig, name)
            plt().close(fig)
        if res.when_where is not None and WHEN_WHERE in res.pngs:
            mine["when_where"] = out.write_bytes(f"{prefix}_when_where.png",
                                                 res.pngs[WHEN_WHERE])
        elif res.when_where is not None:
            fig = when_where_figure(res)
            mine["when_where"] = out.savefig(fig, f"{prefix}_when_where.png")
        if res.best is not None and res.correction:
            name = "missing_wear.py" if key == "shape" else "missing_wear_after_effect.py"
            out.write_text(name, effect_file_source(res, str(diag.study.path)))
            doc[key]["effect_file"] = name
        law = getattr(res, "law", None)
        if key == "shape" and law is not None and law.best is not None:
            # the law found from the shape, beside missing_wear.py (design.md §7 shape.law)
            b = law.best
            out.write_text("law.py", law_file_source(
                b.law, b.constants, study_path=str(diag.study.path), rmse_um=b.rmse_um,
                loo_rmse_um=b.loo_rmse_um, noise_um=law.noise_um, caveat=law_caveat(law),
                status=law.status, ranges=law.ranges))
            doc[key]["law"].update(file="law.py", effect=EFFECT_NAME)
    out.write_json("diagnosis.json", doc)
    header, rows = residual_table(diag)
    out.write_csv("residuals.csv", header, rows)
    out.write_text("report.html", report_html(diag, doc, saved))
    out.write_json_file(doc)
    return doc
