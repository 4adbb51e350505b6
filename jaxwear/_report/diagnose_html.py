"""Self-contained HTML report of a diagnosis: figures as embedded base64 PNG, no links out."""

from __future__ import annotations

import base64
import html
import io
import math

import numpy as np

from jaxwear._analyses.diagnose._evidence import rmse_per_experiment, where_it_fails
from jaxwear._analyses.diagnose._shape_text import p_text
from jaxwear._report.figures import PLOT_POINTS, plt, thinned, thinned_label
from jaxwear._report.law_html import law_section
from jaxwear._report.shape_plot import shape_figure, when_where_figure


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt().close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _img(src: str, alt: str) -> str:
    return f'<figure><img src="{src}" alt="{html.escape(alt)}"><figcaption>' \
           f'{html.escape(alt)}</figcaption></figure>'


def _before_after_bars(diag, names, before, after, ylabel, title, height, noise_label):
    """Grouped bars of a per-experiment error before and after the refit, noise marked."""
    pl = plt()
    x = np.arange(len(names))
    fig, ax = pl.subplots(figsize=(7, height))
    ax.bar(x - 0.2, [before.get(n, np.nan) for n in names], 0.4, label="base model")
    ax.bar(x + 0.2, [after.get(n, np.nan) for n in names], 0.4,
           label=f"after ({diag.final.label})")
    ax.axhline(diag.noise_um, color="k", ls="--", lw=1, label=noise_label)
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _png(fig)


def _fig_rmse(diag) -> str:

    m = diag.model
    before = rmse_per_experiment(m, diag.base.ev.r)
    after = rmse_per_experiment(m, diag.final.ev.r)
    return _before_after_bars(diag, m.exp_names, before, after, "RMSE [µm]",
                              "RMSE per experiment, before and after", 3.4,
                              f"noise {diag.noise_um:.3g} µm")


def _fig_loo(diag) -> str | None:
    names = list(diag.loo_before)
    if not names:
        return None
    return _before_after_bars(diag, names, diag.loo_before, diag.loo_after,
                              "prediction RMSE [µm]",
                              "Leave-one-experiment-out prediction error", 3.2, "noise")


def _fig_residuals_angle(diag) -> str | None:
    m = diag.model
    prof = ~m.is_max
    if not prof.any():
        return None
    pl = plt()
    fig, axes = pl.subplots(2, 1, figsize=(8, 5.2), sharex=True, sharey=True)
    for ax, fit, title in ((axes[0], diag.base, "base model"),
                           (axes[1], diag.final, f"after ({diag.final.label})")):
        for i, name in enumerate(m.exp_names):
            sel = np.flatnonzero(prof & (m.row_exp == i))
            k = sel[thinned(m.row_x[sel], fit.ev.r[sel])]
            ax.plot(m.row_x[k], fit.ev.r[k], ".", ms=3, label=thinned_label(name, len(sel)))
        ax.axhline(0, color="k", lw=0.8)
        for s in (-2, 2):
            ax.axhline(s * diag.noise_um, color="k", ls=":", lw=0.8)
        ax.set_ylabel("model - measured [µm]")
        ax.set_title(f"Residuals over bushing angle: {title} (dotted: ±2 noise)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[1].set_xlabel("bushing angle [deg]")
    axes[1].set_xlim(0, 360)
    axes[0].legend(fontsize=7, ncol=3)
    fig.tight_layout()
    return _png(fig)


def _fig_residuals_time(diag) -> str:

    pl = plt()
    fig, ax = pl.subplots(figsize=(7, 3.4))
    for fit, label, mk in ((diag.base, "base model", "o-"),
                           (diag.final, f"after ({diag.final.label})", "s-")):
        w = where_it_fails(diag.model, fit.ev.r)
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


def _fig_speed_clearance(diag) -> str | None:

    w = where_it_fails(diag.model, diag.base.ev.r)["per_experiment"]
    if len(w) < 2:
        return None
    pl = plt()
    fig, (a1, a2) = pl.subplots(1, 2, figsize=(8, 3.2), sharey=True)
    wa = {d["experiment"]: d for d in where_it_fails(diag.model, diag.final.ev.r)[
        "per_experiment"]}
    for ax, key, xlabel in ((a1, "speed_rpm", "crank speed [r/min]"),
                            (a2, "clearance_mm", "nominal clearance [mm]")):
        ax.plot([d[key] for d in w], [d["mean_um"] for d in w], "o", label="base: mean")
        ax.plot([d[key] for d in w], [wa[d["experiment"]]["mean_um"] for d in w], "s",
                label="after: mean")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    a1.set_ylabel("mean residual [µm]")
    a1.legend(fontsize=7)
    fig.suptitle("Residuals across speed and clearance", fontsize=10)
    fig.tight_layout()
    return _png(fig)


def _fig_profiles(diag) -> str:
    """Measured data with the base and final model, per experiment."""
    m = diag.model
    pl = plt()
    n = len(m.exp_names)
    cols = min(n, 3)
    rows = int(math.ceil(n / cols))
    fig, axes = pl.subplots(rows, cols, figsize=(3.4 * cols, 2.8 * rows), squeeze=False)
    for i, name in enumerate(m.exp_names):
        ax = axes[i // cols][i % cols]
        sel = m.row_exp == i
        if m.is_max[sel].all():
            x = m.row_time[sel]
            ax.plot(x, m.measured[sel], "ks", label="measured")
            ax.plot(x, diag.base.ev.pred[sel], "o-", label="base")
            ax.plot(x, diag.final.ev.pred[sel], "^-", label="after")
            ax.set_xlabel("hours")
            ax.set_ylabel("max depth [µm]")
        else:
            last = sel & (m.row_time == m.row_time[sel].max())
            order = np.argsort(m.row_x[last])
            x = m.row_x[last][order]
            # break the model lines across unmeasured arcs (between wear scars)
            dx = np.diff(x)
            gap = np.r_[dx > 2.5 * np.median(dx), False] if len(dx) else np.zeros(len(x), bool)

            y = m.measured[last][order]
            k = thinned(x, y)
            ax.plot(x[k], y[k], "k.", ms=3, label=thinned_label("measured", len(x)))
            # the model lines are smooth: every row up to PLOT_POINTS, then every k-th
            keep = np.unique(np.r_[np.arange(0, len(x), max(1, len(x) // PLOT_POINTS)),
                                   np.flatnonzero(gap), np.flatnonzero(gap) + 1,
                                   len(x) - 1]) if len(x) else np.arange(0)
            for pred, label in ((diag.base.ev.pred, "base"), (diag.final.ev.pred, "after")):
                ax.plot(*_with_breaks(x[keep], pred[last][order][keep], gap[keep]), "-", lw=1,
                        label=label)
            ax.set_xlabel("angle [deg]")
            ax.set_ylabel("depth [µm]")
            name += f" @ {m.row_time[sel].max():g} rev"
        ax.set_title(name, fontsize=8)
        ax.grid(alpha=0.3)
        if i == 0:
            ax.legend(fontsize=7)
    for j in range(n, rows * cols):
        axes[j // cols][j % cols].axis("off")
    fig.tight_layout()
    return _png(fig)


def _with_breaks(x, y, gap):
    """x, y with a NaN point after every index where `gap` is True (line breaks)."""
    xs, ys = [], []
    for xi, yi, g in zip(x, y, gap):
        xs.append(xi), ys.append(yi)
        if g:
            xs.append(np.nan), ys.append(np.nan)
    return np.array(xs), np.array(ys)


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


def report_html(diag, doc: dict, saved: dict | None = None) -> str:
    """The report: verdict paragraph, figures, tables (design.md §7 `diagnose --out`).
    `saved`: {"shape" or "shape_after_effect": {figure label: PNG path}} of the shape
    figures already written beside it (embedded as written, not drawn again)."""
    v = doc["verdict"]
    status = {"adequate": "Adequate: the base model fits to noise level",
              "effect_found": f"Missing effect found: {' + '.join(v['effects'])}",
              "partly_explained": "Partly explained: library candidates only approximate "
                                  f"the misfit ({' + '.join(v['partial'])})",
              "unexplained": "Unexplained systematic misfit"}[v["status"]]
    figs = [("Per-experiment RMSE before and after (dashed: noise level)", _fig_rmse(diag)),
            ("Measured data and the two models", _fig_profiles(diag)),
            ("Residuals over bushing angle", _fig_residuals_angle(diag)),
            ("Residuals over revolutions / hours", _fig_residuals_time(diag)),
            ("Residuals across speed and clearance", _fig_speed_clearance(diag)),
            ("Leave-one-experiment-out prediction error", _fig_loo(diag)),
            ("Candidates ranked by evidence", _fig_candidates(diag))]
    b, a = doc["baseline"], doc["after"]
    exp_rows = [(n, _num(b["rmse_per_experiment_um"].get(n), ".3f"),
                 _num(a["rmse_per_experiment_um"].get(n), ".3f"),
                 _num(b["loo_rmse_per_experiment_um"].get(n), ".3f"),
                 _num(a["loo_rmse_per_experiment_um"].get(n), ".3f"))
                for n in diag.model.exp_names]
    exp_rows.append(("all", _num(b["rmse_um"], ".3f"), _num(a["rmse_um"], ".3f"),
                     _num(b["loo_rmse_um"], ".3f"), _num(a["loo_rmse_um"], ".3f")))
    cand_rows = []
    for c in doc["candidates"]:
        strength = "; ".join(
            f"{k} = {_num(p['value'])}" + (f" ± {_num(p['stderr'], '.2g')}"
                                          if p.get("stderr") is not None else "")
            for k, p in c["parameters"].items()
            if not k.startswith("clearance_mm/") and k != "K_d_per_Pa")
        cand_rows.append((c["effect"], _num(c["rmse_um"], ".3f"), _num(c["evidence"], ".1f"),
                          _num(c.get("score"), ".1f"), _num(c.get("p_score"), ".1e"),
                          "refit" if c["refit"] else "screen",
                          {True: "yes", False: "no"}.get(c.get("at_noise_level"), "—"),
                          strength))
    t = b["tests"]
    test_rows = [
        ("noise level (neighbour differences)", f"{b['noise_um']:.4g} µm",
         f"ν = {_num(b['noise_dof'], '.4g')}"),
        ("chi-square ratio RSS/(n-k)/σ̂²", _num(t["chi2_ratio"], ".3f"),
         f"p = {_num(t['p_chi2'], '.2e')}"),
        ("lag-1 autocorrelation (Durbin-Watson)",
         f"{_num(t['lag1_autocorrelation'], '.3f')} (DW {_num(t['durbin_watson'], '.2f')})",
         f"p = {_num(t['p_autocorrelation'], '.2e')}"),
        ("best candidate score test", str(t["score_effect"]),
         f"p = {_num(t['p_score_min'], '.2e')} (Bonferroni)"),
        ("combined (Bonferroni over the three)", "systematic" if t["systematic"] else "noise",
         f"p = {_num(t['p_combined'], '.2e')}, α = {t['alpha']:g}")]
    par_rows = [(k, _num(p["value"]), _num(p.get("stderr"), ".3g"))
                for k, p in a["parameters"].items()]
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>jaxwear diagnose: {html.escape(str(diag.study.path))}</title>",
        "<style>body{font-family:sans-serif;max-width:980px;margin:2em auto;line-height:1.4}"
        "table{border-collapse:collapse;margin:1em 0;font-size:0.9em}"
        "td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}"
        "figure{margin:1em 0}img{max-width:100%}figcaption{font-size:0.85em;color:#555}"
        ".verdict{padding:1em;border-left:6px solid #2a7;background:#f4faf6}"
        ".unexplained,.partly_explained{border-color:#c52;background:#fbf4f1}"
        ".adequate{border-color:#27a;background:#f1f6fb}</style></head><body>",
        f"<h1>Diagnosis of {html.escape(str(diag.study.path))}</h1>",
        f"<div class='verdict {v['status']}'><h2>{html.escape(status)}</h2>"
        f"<p>{html.escape(v['summary'])}</p></div>",
        "<h2>Error before and after</h2>",
        _table(exp_rows, ["experiment", "RMSE base [µm]", "RMSE after [µm]",
                          "left-out base [µm]", "left-out after [µm]"]),
        f"<p>After = {html.escape(a['model'])}; noise level {b['noise_um']:.4g} µm. "
        "Left-out errors: each experiment predicted by a fit without it (one Gauss-Newton "
        "step from the full fit), its clearance at the nominal value.</p>",
        "<h2>Is the misfit noise?</h2>", _table(test_rows, ["test", "value", "p"]),
        "<h2>Candidates</h2>",
        _table(cand_rows, ["candidate", "RMSE [µm]", "evidence (ln BF)", "score", "p (score)",
                           "how", "at noise level", "fitted strength"]),
        "<h2>Fitted parameters (after)</h2>", _table(par_rows, ["parameter", "value", "SE"]),
        "<h2>Figures</h2>",
    ]
    for key, title, res in (("shape", "The shape of the missing wear", diag.shape),
                            ("shape_after_effect",
                             "The shape of what is still missing after the effect",
                             diag.shape_after_effect)):
        if res is not None:
            parts += _shape_section(title, res, (saved or {}).get(key, {}))
    parts += [_img(src, alt) for alt, src in figs if src]
    parts.append(f"<h2>Method</h2><p>{html.escape(doc['method'])}</p>")
    parts.append(f"<p>{html.escape(_integration_text(a['integration']))}</p>")
    parts.append(f"<p>Wall time {doc['wall_time_s']:.1f} s.</p></body></html>")
    return "\n".join(parts)


def _integration_text(integ: dict) -> str:
    if integ["integrator"] == "adaptive":
        return (f"Wear integration (adaptive, at the final fit): error estimate "
                f"{float(integ['error_estimate_um']):.3g} µm against a tolerance of "
                f"{integ['tolerance_um']:g} µm, {integ['steps']} steps.")
    return (f"Wear integration (the paper's eq 23): {integ['steps']} updates, no error "
            "estimate; halve numerics.revolutions_per_update to measure it.")


def _written(path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _shape_section(title: str, res, saved: dict) -> list[str]:
    """The shape analysis: its sentence, a table of the variables in both forms, the figure
    of the best (or the largest share) and the map of when and where (`_shape`)."""

    rows = [(v.name, v.form, f"{v.explained_fraction:.0%}", f"{v.unique_fraction:.0%}",
             _num(v.dof, ".1f"), p_text(v.p_value).removeprefix("p "),
             "yes" if v.significant else "no",
             "carries" if v.carries else (f"stand-in for {v.stand_in_for}"
                                          if v.stand_in_for else ""),
             f"{_num(v.peak_at, '.4g')} [{_num(v.lower, '.4g')}, {_num(v.upper, '.4g')}] "
             f"{v.unit}") for v in sorted(res.variables, key=lambda v: v.aic)]
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
