"""Self-contained HTML report of a diagnosis: figures as embedded base64 PNG, no links out."""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path

import numpy as np

from jaxwear._analyses.diagnose._evidence import rmse_per_experiment, where_it_fails
from jaxwear._analyses.diagnose._headline import (
    answer,
    corrected,
    law_status,
    num,
    shape_adds,
)
from jaxwear._analyses.diagnose.shape.text import p_text
from jaxwear._core.io import png_bytes
from jaxwear._report.answer_plot import law_figure, profile_caption, profile_figure
from jaxwear._report.figures import plt, thinned, thinned_label
from jaxwear._report.law_html import law_section
from jaxwear._report.shape_plot import shape_figure, when_where_figure


def _png(fig) -> str:
    data = png_bytes(fig, dpi=100)
    plt().close(fig)
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def _img(src: str, alt: str) -> str:
    return f'<figure><img src="{src}" alt="{html.escape(alt)}"><figcaption>' \
           f'{html.escape(alt)}</figcaption></figure>'


def _series(diag, corr):
    """(residual rows [µm], label) of the base model and, where there is one, the
    corrected model (`_headline.corrected`): never an "after" that is the base."""
    out = [(np.asarray(diag.base.ev.r), "base model")]
    if corr is not None:
        out.append((corr[1], f"with {corr[0]}"))
    return out


def _fig_residuals_angle(diag, corr) -> str | None:
    m = diag.model
    prof = ~m.is_max
    if not prof.any():
        return None
    pl = plt()
    series = _series(diag, corr)
    fig, axes = pl.subplots(len(series), 1, figsize=(8, 2.6 * len(series) + 0.4),
                            sharex=True, sharey=True, squeeze=False)
    axes = axes[:, 0]
    for ax, (r, title) in zip(axes, series):
        for i, name in enumerate(m.exp_names):
            sel = np.flatnonzero(prof & (m.row_exp == i))
            k = sel[thinned(m.row_x[sel], r[sel])]
            ax.plot(m.row_x[k], r[k], ".", ms=3, label=thinned_label(name, len(sel)))
        ax.axhline(0, color="k", lw=0.8)
        for s in (-2, 2):
            ax.axhline(s * diag.noise_um, color="k", ls=":", lw=0.8)
        ax.set_ylabel("model - measured [µm]")
        ax.set_title(f"Residuals over bushing angle: {title} (dotted: ±2 noise)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("bushing angle [deg]")
    axes[-1].set_xlim(0, 360)
    axes[0].legend(fontsize=7, ncol=3)
    fig.tight_layout()
    return _png(fig)


def _fig_residuals_time(diag, corr) -> str:

    pl = plt()
    fig, ax = pl.subplots(figsize=(7, 3.4))
    for (r, label), mk in zip(_series(diag, corr), ("o-", "s-")):
        w = where_it_fails(diag.model, r)
        t = [d["at"] for d in w["per_time"]]
        ax.plot(t, [d["mean_um"] for d in w["per_time"]], mk, label=f"{label}: mean")
        ax.plot(t, [d["rmse_um"] for d in w["per_time"]], mk, alpha=0.4, label=f"{label}: RMSE")
    ax.axhline(0, color="k", lw=0.8)
    ax.axhline(diag.noise_um, color="k", ls="--", lw=0.8, label="noise")
    unit = where_it_fails(diag.model, diag.base.ev.r)["time_unit"]
    ax.set_xlabel(unit)
    ax.set_ylabel("residual [µm]")
    ax.set_title(f"Residuals over {unit} (all experiments)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _png(fig)


def _fig_speed_clearance(diag, corr) -> str | None:

    w = where_it_fails(diag.model, diag.base.ev.r)["per_experiment"]
    if len(w) < 2:
        return None
    pl = plt()
    fig, (a1, a2) = pl.subplots(1, 2, figsize=(8, 3.2), sharey=True)
    wa = None if corr is None else {d["experiment"]: d for d in where_it_fails(
        diag.model, corr[1])["per_experiment"]}
    for ax, key, xlabel in ((a1, "speed_rpm", "crank speed [r/min]"),
                            (a2, "clearance_mm", "nominal clearance [mm]")):
        ax.plot([d[key] for d in w], [d["mean_um"] for d in w], "o", label="base: mean")
        if wa is not None:
            ax.plot([d[key] for d in w], [wa[d["experiment"]]["mean_um"] for d in w], "s",
                    label=f"with {corr[0]}: mean")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    a1.set_ylabel("mean residual [µm]")
    a1.legend(fontsize=7)
    fig.suptitle("Residuals across speed and clearance", fontsize=10)
    fig.tight_layout()
    return _png(fig)


def _fig_candidates(diag) -> str | None:
    cands = [c for c in diag.candidates]
    if not cands:
        return None
    pl = plt()
    fig, ax = pl.subplots(figsize=(7, 0.45 * len(cands) + 1.2))
    y = np.arange(len(cands))[::-1]
    ev = [max(c.evidence, -5.0) for c in cands]
    colors = ["tab:green" if c.effect in diag.effects else
              ("tab:blue" if c.refit else "tab:gray") for c in cands]
    ax.barh(y, ev, color=colors)
    ax.set_yticks(y)
    ax.set_yticklabels([c.effect + ("" if c.refit else " (screen)") for c in cands], fontsize=8)
    ax.axvline(math.log(150), color="k", ls="--", lw=0.8, label="strong evidence (ln 150)")
    ax.set_xlabel("evidence: ln Bayes factor against the base model")
    ax.set_title("Candidates (green: the verdict; grey: linearised screen only)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return _png(fig)


def _table(rows, header) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>"
                   for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _num(x, fmt=".4g"):
    if x is None:
        return "—"
    try:
        return format(float(x), fmt)
    except (TypeError, ValueError):
        return str(x)


def study_name(path) -> str:
    """The study's name for a title: its file's stem, or its folder's name where the file
    is the generic `study.toml` (never the full machine path)."""
    p = Path(str(path))
    return p.parent.name if p.stem == "study" and p.parent.name else p.stem


STYLE = (
    "body{font-family:sans-serif;max-width:1240px;margin:0.6em auto;padding:0 12px;"
    "line-height:1.35}h1{font-size:1.35em;margin:0.2em 0 0.3em}"
    "table{border-collapse:collapse;margin:0.6em 0;font-size:0.88em;max-width:100%}"
    "td,th{border:1px solid #ccc;padding:2px 7px;text-align:left}"
    "table:not(.errors) td{overflow-wrap:anywhere}"
    "figure{margin:0.6em 0}img{max-width:100%}figcaption{font-size:0.85em;color:#555}"
    "code{overflow-wrap:anywhere}"
    ".verdict{padding:0.5em 1em;border-left:6px solid #2a7;background:#f4faf6}"
    ".verdict .headline{font-size:1.12em;font-weight:bold;margin:0.2em 0}"
    ".verdict .status{font-size:0.8em;color:#555;text-transform:uppercase;"
    "letter-spacing:0.04em}.verdict p{margin:0.3em 0}"
    ".unexplained,.partly_explained{border-color:#c52;background:#fbf4f1}"
    ".adequate{border-color:#27a;background:#f1f6fb}"
    ".first{display:grid;grid-template-columns:max-content minmax(0,1fr);gap:16px;"
    "align-items:start;margin-top:0.5em}.first h2{font-size:1.05em;margin:0.2em 0}"
    ".errors{font-size:0.84em}.errors td,.errors th{white-space:nowrap;padding:2px 5px}"
    ".errors th.model{white-space:normal;overflow-wrap:anywhere;text-align:center;"
    "max-width:9em}.errors td.loo{color:#555}.errors th.ans{background:#eef6ee}"
    ".errors caption{text-align:left;font-size:0.9em;color:#444;caption-side:top}"
    ".errors td.n,.errors th.n{text-align:right}.errors td.ans{font-weight:bold;"
    "background:#eef6ee}.errors tr.all td{border-top:2px solid #888}"
    ".note{font-size:0.82em;color:#444}"
    "#profiles img{max-height:760px}#errors{max-width:620px}#errors .note{max-width:34em}")


def report_html(diag, doc: dict, saved: dict | None = None) -> str:
    """The report (design.md §7 `diagnose --out`), the answer first: the headline and the
    summary (`verdict`), beside each other the one error table (`error_table`) and the
    profiles (`answer_plot.profile_figure`); then the law with its figure, the shape, the
    long text, the tests, the candidates and the other figures. `saved`: {"shape" or
    "shape_after_effect": {figure label: PNG path}} of the shape figures already written
    beside it (embedded as written, not drawn again)."""
    v = doc["verdict"]
    corr = corrected(diag)
    name = study_name(diag.study.path)
    figs = [("Residuals over bushing angle", _fig_residuals_angle(diag, corr)),
            ("Residuals over revolutions / hours", _fig_residuals_time(diag, corr)),
            ("Residuals across speed and clearance", _fig_speed_clearance(diag, corr)),
            ("Candidates ranked by evidence", _fig_candidates(diag))]
    b, a = doc["baseline"], doc["after"]
    cand_rows = []
    for c in doc["candidates"]:
        strength = "; ".join(
            f"{k} = {num(p['value'], 4)}" + (f" ± {num(p['stderr'], 2)}"
                                            if p.get("stderr") is not None else "")
            for k, p in c["parameters"].items()
            if not k.startswith("clearance_mm/") and k != "K_d_per_Pa")
        cand_rows.append((c["effect"], num(c["rmse_um"]), _num(c["evidence"], ".1f"),
                          _num(c.get("score"), ".1f"), _num(c.get("p_score"), ".1e"),
                          "refit" if c["refit"] else "screen",
                          {True: "yes", False: "no"}.get(c.get("at_noise_level"), "—"),
                          strength))
    t = b["tests"]
    test_rows = [
        ("noise level (neighbour differences)", f"{num(b['noise_um'])} µm",
         f"ν = {num(b['noise_dof'])}"),
        ("chi-square ratio RSS/(n-k)/σ̂²", _num(t["chi2_ratio"], ".3f"),
         f"p = {_num(t['p_chi2'], '.2e')}"),
        ("lag-1 autocorrelation (Durbin-Watson)",
         f"{_num(t['lag1_autocorrelation'], '.3f')} (DW {_num(t['durbin_watson'], '.2f')})",
         f"p = {_num(t['p_autocorrelation'], '.2e')}"),
        ("best candidate score test", str(t["score_effect"]),
         f"p = {_num(t['p_score_min'], '.2e')} (Bonferroni)"),
        ("combined (Bonferroni over the three)", "systematic" if t["systematic"] else "noise",
         f"p = {_num(t['p_combined'], '.2e')}, α = {t['alpha']:g}")]
    par_rows = [(k, num(p["value"], 4), num(p.get("stderr"), 2))
                for k, p in a["parameters"].items()]
    par_title = ("Fitted parameters of the base model" if a["model"] == "base" else
                 f"Fitted parameters with {a['model']}")
    profiles = profile_figure(diag, corr)
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(name)}: jaxwear diagnose</title>",
        f"<style>{STYLE}</style></head><body>",
        f"<h1>Diagnosis of {html.escape(name)}</h1>",
        f"<div class='verdict {v['status']}'>"
        f"<div class='status'>{html.escape(_status_words(diag, v['status']))}</div>"
        f"<p class='headline'>{html.escape(v.get('headline') or '')}</p>"
        f"<p class='summary'>{_code(v['summary'])}</p></div>",
        "<div class='first'><div id='errors'><h2>The error, base → answer</h2>",
        error_table(diag, doc),
        f"<p class='note'>{_columns_note(diag)}RMSE of each experiment's measured points; "
        "left out: each "
        "experiment predicted by a fit without it (one Gauss-Newton step from the full fit, "
        "its clearance at the nominal value). A model complete to the noise reaches the "
        "noise level in both.</p></div>",
        f"<div id='profiles'>{_img(_png(profiles), profile_caption(diag, corr))}</div>"
        "</div>",
    ]
    shp, after = diag.shape, diag.shape_after_effect
    if shp is not None and getattr(shp, "law", None) is not None and shp.law.best is not None:
        parts += _law_part(shp)
    for key, title, res in (("shape", "The shape of the missing wear", shp),
                            ("shape_after_effect",
                             "The shape of what is still missing after the effect", after)):
        if res is None:
            continue
        if key == "shape_after_effect" and not shape_adds(shp, res):
            # the same variable again, or nothing: one line, not the analysis again
            parts.append(f"<p class='note'>On top of {html.escape(res.after)}, the shape "
                         "of what is left finds "
                         + ("nothing beyond the noise." if res.best is None else
                            f"the same variable ({html.escape(res.best)}) as on top of the "
                            "base model: not repeated.") + "</p>")
            continue
        parts += _shape_section(title, res, (saved or {}).get(key, {}))
    parts += [f"<h2>Details</h2><p>{_code(v.get('details') or '')}</p>",
              "<h2>Is the misfit noise?</h2>", _table(test_rows, ["test", "value", "p"]),
              "<h2>Candidates</h2>",
              _table(cand_rows, ["candidate", "RMSE [µm]", "evidence (ln BF)", "score",
                                 "p (score)", "how", "at noise level", "fitted strength"]),
              f"<h2>{html.escape(par_title)}</h2>",
              _table(par_rows, ["parameter", "value", "SE"]),
              "<h2>More figures</h2>"]
    parts += [_img(src, alt) for alt, src in figs if src]
    parts.append(f"<h2>Method</h2><p>{html.escape(doc['method'])}</p>")
    parts.append(f"<p>{html.escape(_integration_text(a['integration']))}</p>")
    parts.append(f"<p>Wall time {doc['wall_time_s']:.1f} s.</p></body></html>")
    return "\n".join(parts)


def _status_words(diag, status: str) -> str:
    """The verdict's status in words above the headline; where the answer is a law of the
    shape's search, that the library's status is the library's."""
    words = status.replace("_", " ")
    if answer(diag) == "law":
        return f"{words} by the library's effects · a law found by the search"
    return words


def _code(text: str) -> str:
    """`text` escaped, its `backquoted` commands as <code>."""
    bits = html.escape(text).split("`")
    return "".join(f"<code>{b}</code>" if i % 2 else b for i, b in enumerate(bits))


def error_table(diag, doc: dict) -> str:
    """The one error table (issue 49): per experiment, in-sample and on left-out
    experiments, the base model, the best library candidate, the shape's refitted
    correction and the law, each where it exists (a column is what it is, never an
    "after" that is the base), with the noise; the answer's column in bold."""
    m = diag.model
    cols = [("base", rmse_per_experiment(m, diag.base.ev.r), diag.loo_before,
             diag.base.rmse, _mean(diag.loo_before), answer(diag) == "adequate")]
    cand = _best_candidate(diag)
    if cand is not None:
        fit = cand.fit
        final = fit is diag.final
        cols.append((cand.effect, rmse_per_experiment(m, fit.ev.r),
                     diag.loo_after if final else {}, fit.rmse,
                     _mean(diag.loo_after) if final else None, answer(diag) == "effect"))
    shp = diag.shape
    if shp is not None and shp.best is not None and shp.residual_um is not None:
        loo_all = (doc.get("shape") or {}).get("loo_rmse_um")
        cols.append(("shape", rmse_per_experiment(m, shp.residual_um), {},
                     shp.rmse_after_um, loo_all, False))
    law = None if shp is None else getattr(shp, "law", None)
    if law is not None and law.best is not None:
        st = (((doc.get("shape") or {}).get("law") or {}).get("status")
              or law_status(law))
        lb = law.best
        per = (rmse_per_experiment(m, lb.residual_um) if lb.residual_um is not None
               else {})
        cols.append(("law" if st == "found" else f"law ({st})", per,
                     lb.loo_per_experiment, lb.rmse_um, lb.loo_rmse_um,
                     answer(diag) == "law"))
    has_loo = any(c[2] or c[4] is not None for c in cols)
    per = 2 if has_loo else 1
    head1 = ("<tr><th rowspan='2'>experiment</th>"
             + "".join(f"<th colspan='{per}' class='model{' ans' if c[5] else ''}'>"
                       f"{html.escape(c[0])}</th>" for c in cols) + "</tr>")
    head2 = "<tr>" + "".join(
        ("<th class='n'>RMSE</th><th class='n'>left out</th>" if has_loo
         else "<th class='n'>RMSE</th>") for _ in cols) + "</tr>"

    def cells(pairs):
        out = ""
        for (x, lo), c in zip(pairs, cols):
            cls = "n ans" if c[5] else "n"
            out += f"<td class='{cls}'>{num(x)}</td>"
            if has_loo:
                out += f"<td class='{cls} loo'>{num(lo)}</td>"
        return out

    body = []
    for e in m.exp_names:
        row = cells([(c[1].get(e), c[2].get(e)) for c in cols])
        body.append(f"<tr><td>{html.escape(e)}</td>{row}</tr>")
    row = cells([(c[3], c[4]) for c in cols])
    body.append(f"<tr class='all'><td><b>all</b></td>{row}</tr>")
    body.append(f"<tr><td>noise level</td><td colspan='{per * len(cols)}' class='n'>"
                f"{num(diag.noise_um)} µm</td></tr>")
    return (f"<table class='errors'><caption>RMSE [µm], in-sample and on left-out "
            f"experiments</caption>{head1}{head2}{''.join(body)}</table>")


def _columns_note(diag) -> str:
    """What the columns of the error table are, in a sentence."""
    bits = ["base: the model as the study states it"]
    cand = _best_candidate(diag)
    if cand is None and diag.status == "unexplained":
        bits.append("no library candidate lowers the RMSE")
    if cand is not None:
        role = {"effect_found": "the missing effect found",
                "partly_explained": "the library's best, which only approximates"}.get(
            diag.status, "the library's best candidate")
        bits.append(f"{cand.effect}: {role}")
    shp = diag.shape
    if shp is not None and shp.best is not None and shp.residual_um is not None:
        bits.append("shape: the free correction along " + shp.best)
    if shp is not None and getattr(shp, "law", None) is not None and shp.law.best is not None:
        bits.append("law: the law of the shape's search")
    return html.escape("; ".join(bits)) + ". "


# an unexplained verdict's best candidate gets a column only where it lowers the RMSE by
# more than this fraction: a column equal to the base's reads as "after = base" (issue 49)
LOWERS = 0.01


def _best_candidate(diag):
    """The best library candidate with a usable refit (the verdict's where it named one
    or one approximates; for an unexplained verdict, the best where it lowers the RMSE by
    more than `LOWERS`), or None (an adequate verdict: none is needed)."""
    if diag.status == "adequate":
        return None
    name = (diag.effects and " + ".join(diag.effects)) or (diag.partial or [None])[0]
    for c in diag.candidates:
        if c.fit is not None and c.fit.usable and (name is None or c.effect == name
                                                   or c.fit is diag.final):
            if diag.status == "unexplained" and not c.fit.rmse < (1 - LOWERS) * diag.base.rmse:
                return None
            return c
    return None


def _mean(d: dict):
    return float(np.sqrt(np.mean(np.square(list(d.values()))))) if d else None


def _law_part(shp) -> list[str]:
    """The law's section: its table and constants (`law_html.law_section`) and its factor
    or deposit over its variables' range against the shape's band (`law_figure`)."""
    out = law_section(shp, _table)
    fig = law_figure(shp)
    if fig is not None:
        out.insert(2, _img(_png(fig), "The law over its variables' range in the data, "
                                      "against the shape the data ask for (its band)"))
    return out


def _integration_text(integ: dict) -> str:
    if integ["integrator"] == "adaptive":
        return (f"Wear integration (adaptive, at the final fit): error estimate "
                f"{float(integ['error_estimate_um']):.3g} µm against a tolerance of "
                f"{integ['tolerance_um']:g} µm, {integ['steps']} steps.")
    return (f"Wear integration (the paper's eq 23): {integ['steps']} updates, no error "
            "estimate; halve numerics.revolutions_per_update to measure it.")


def peak_text(v) -> str:
    """"3.03 [2.9, 3.2] µm": a variable's peak with its 90 % band, the band left out where
    it is degenerate (no wider than a millionth of the variable's range: the peak is
    pinned, e.g. at the end of the range) and values below 1e-9 of the range as 0 (float
    noise, not a speed of 3e-18 m/s)."""
    span = max(abs(float(v.range[0])), abs(float(v.range[1])), 1e-300)

    def clean(x):
        x = float(x)
        return 0.0 if math.isfinite(x) and abs(x) < 1e-9 * span else x

    p, lo, hi = clean(v.peak_at), clean(v.lower), clean(v.upper)
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi - lo <= 1e-6 * span:
        return f"{num(p, 4)} {v.unit}"
    return f"{num(p, 4)} [{num(lo, 3)}, {num(hi, 3)}] {v.unit}"


def _written(path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _shape_section(title: str, res, saved: dict) -> list[str]:
    """The shape analysis: its sentence, a table of the variables in both forms, the figure
    of the best (or the largest share) and the map of when and where (`shape.analysis`)."""

    rows = [(v.name, v.form, f"{v.explained_fraction:.0%}", f"{v.unique_fraction:.0%}",
             _num(v.dof, ".1f"), p_text(v.p_value).removeprefix("p "),
             "yes" if v.significant else "no",
             "carries" if v.carries else (f"stand-in for {v.stand_in_for}"
                                          if v.stand_in_for else ""),
             peak_text(v)) for v in sorted(res.variables, key=lambda v: v.aic)]
    out = [f"<h2>{html.escape(title)}</h2>", f"<p>{html.escape(res.sentence)}</p>",
           _table(rows, ["state variable", "form", "misfit explained (alone)",
                         "unique (jointly)", "dof", "p", "significant", "jointly",
                         "peak [90 % band]"]),
           "<p>Each row: a smooth correction along one state variable, as a factor exp(g(z)) "
           "of the local wear rate or as a deposit e(z) ≥ 0 where the pin presses, fitted "
           "to the misfit through the wear loop with a roughness penalty chosen by "
           "generalised cross-validation, the fit's own parameters and the model's "
           "numerical error projected off; p from simulations of the null with the penalty "
           f"choice included, significant below α/{len(res.variables)} (α = {res.alpha:g}, "
           "Bonferroni). Unique: what the variable adds to all the others of its form fitted "
           "together; rows sorted by AIC.</p>"]
    show = (f"deposit:{res.best}" if res.form == "deposit" else res.best) if res.best else \
        max(res.variables, key=lambda v: v.explained_fraction).label
    out.append(_img(_written(saved[show]) if show in saved else _png(shape_figure(res, show)),
                    f"{show}: the extra wear the data ask for"
                    + ("" if res.best else " (not significant: the largest share shown)")))
    if res.when_where is not None:
        out.append(_img(_written(saved["when_where"]) if "when_where" in saved
                        else _png(when_where_figure(res)),
                        "when in the cycle the missing wear is made and where it lands"))
    if getattr(res, "law", None) is not None:
        out += law_section(res, _table)
    return out
