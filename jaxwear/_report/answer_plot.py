"""The figures people look for first (issue 49): the measured profiles with the base and the
corrected model over the bore angle, residuals beneath (`profile_figure`), and the law's
factor or deposit over its variables' range in the data against the shape's band
(`law_figure`)."""

from __future__ import annotations

import math

import numpy as np

from jaxwear._analyses.diagnose.shape.design import LEVEL
from jaxwear._physics.config import TIMED_DRIVERS
from jaxwear._physics.effects.law import law_phi_numpy, variable_unit
from jaxwear._report.figures import PLOT_POINTS, plt, thinned

# experiments per row of the grid; beyond `GRID_AT` experiments the panels shrink
COLUMNS, GRID_AT = 3, 6


def _grid(n: int) -> tuple[int, int, float, float]:
    """(columns, rows, panel width, panel height) [in] of `n` experiments' panels (each a
    profile above its residuals): small multiples when there are many."""
    cols = min(n, COLUMNS if n <= GRID_AT else 4)
    rows = int(math.ceil(n / cols))
    w = 9.6 / cols if n > 1 else 7.0
    h = 2.9 if n <= GRID_AT else 2.1
    return cols, rows, w, h


def _scan_lines(ax, x, y, color, style, lw, label=None):
    """A model line over angle, broken across unmeasured arcs (between wear scars)."""
    if not len(x):
        return
    order = np.argsort(x)
    x, y = x[order], y[order]
    dx = np.diff(x)
    gap = np.r_[dx > 2.5 * np.median(dx), False] if len(dx) else np.zeros(len(x), bool)
    keep = np.unique(np.r_[np.arange(0, len(x), max(1, len(x) // PLOT_POINTS)),
                           np.flatnonzero(gap), np.flatnonzero(gap) + 1, len(x) - 1])
    xs, ys = [], []
    for xi, yi, g in zip(x[keep], y[keep], gap[keep]):
        xs.append(xi), ys.append(yi)
        if g:
            xs.append(np.nan), ys.append(np.nan)
    ax.plot(xs, ys, style, color=color, lw=lw, label=label)


def profile_figure(diag, corrected):
    """Per experiment: each scan measured (dots), the base model (dotted) and the corrected
    model (solid) over the bore angle, coloured by when the scan was taken, and beneath the
    residuals (model - measured) of both with ±2 noise; history rows (maximum depth over
    time) as such. `corrected`: (label, residual rows [µm]) of the answer
    (`_headline.corrected`), or None (the base model only). Returns a Figure."""
    m = diag.model
    n = len(m.exp_names)
    cols, rows, w, h = _grid(n)
    pl = plt()
    fig = pl.figure(figsize=(w * cols, h * rows + 0.5))
    outer = fig.add_gridspec(rows, cols, hspace=0.42, wspace=0.28)
    base = m.measured + diag.base.ev.r
    label, r_corr = corrected if corrected is not None else (None, None)
    after = None if r_corr is None else m.measured + r_corr
    base_style = ":" if after is not None else "-"  # dotted beside the answer's line
    time_unit = "h" if diag.study.config.driver in TIMED_DRIVERS else "rev"
    for i, name in enumerate(m.exp_names):
        row, col = divmod(i, cols)
        inner = outer[row, col].subgridspec(2, 1, height_ratios=[2.2, 1.0], hspace=0.08)
        ax = fig.add_subplot(inner[0])
        axr = fig.add_subplot(inner[1], sharex=ax)
        sel = m.row_exp == i
        hist = sel & m.is_max
        prof = sel & ~m.is_max
        times = sorted(set(m.row_time[prof].tolist()))
        cmap = pl.get_cmap("viridis")
        for k, t in enumerate(times):
            c = cmap(0.15 + 0.7 * k / max(len(times) - 1, 1))
            rows_t = np.flatnonzero(prof & (m.row_time == t))
            x = m.row_x[rows_t]
            keep = thinned(x, m.measured[rows_t], PLOT_POINTS // max(len(times), 1))
            ax.plot(x[keep], m.measured[rows_t][keep], ".", color=c, ms=2, alpha=0.6)
            _scan_lines(ax, x, base[rows_t], c, base_style, 1.2)
            if after is not None:
                _scan_lines(ax, x, after[rows_t], c, "-", 1.4)
            axr.plot(x[keep], diag.base.ev.r[rows_t][keep], ".", color="0.6", ms=1.5)
            if r_corr is not None:
                axr.plot(x[keep], r_corr[rows_t][keep], ".", color=c, ms=1.5)
        if hist.any():  # a history: the maximum depth over time, on its own axis
            rows_h = np.flatnonzero(hist)
            ax.plot(m.row_time[rows_h], m.measured[rows_h], "ks", ms=3)
            ax.plot(m.row_time[rows_h], base[rows_h], "o:", color="C1", ms=3)
            if after is not None:
                ax.plot(m.row_time[rows_h], after[rows_h], "^-", color="C0", ms=3)
            axr.plot(m.row_time[rows_h], diag.base.ev.r[rows_h], "o", color="0.6", ms=3)
            if r_corr is not None:
                axr.plot(m.row_time[rows_h], r_corr[rows_h], "^", color="C0", ms=3)
        for s in (-2, 2):
            axr.axhline(s * diag.noise_um, color="k", ls=":", lw=0.7)
        axr.axhline(0, color="k", lw=0.7)
        span = (f", scans at {_times(times)} {time_unit}" if times else "")
        ax.set_title(f"{name}{span}", fontsize=8)
        ax.tick_params(labelbottom=False, labelsize=7)
        axr.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        axr.grid(alpha=0.3)
        if prof.any():
            ax.set_xlim(0, 360)
            ax.set_xticks(range(0, 361, 90))
            axr.set_xlabel("bore angle [deg]" if row == rows - 1 or i + cols >= n else "",
                           fontsize=8)
        else:
            axr.set_xlabel("hours", fontsize=8)
        if col == 0:
            ax.set_ylabel("depth [µm]", fontsize=8)
            axr.set_ylabel("model − meas.", fontsize=7)
    from matplotlib.lines import Line2D

    scans = bool((~m.is_max).any())
    handles = [Line2D([], [], ls="", marker="." if scans else "s", color="0.3",
                      label="measured (each scan)" if scans else "measured"),
               Line2D([], [], ls=base_style, color="0.3", label="base model")]
    if after is not None:
        handles.append(Line2D([], [], ls="-", color="0.3", label=f"with {label}"))
    handles.append(Line2D([], [], ls=":", lw=0.7, color="k", label="±2 noise"))
    fig.legend(handles=handles, loc="upper center", ncol=len(handles), fontsize=8,
               frameon=False, bbox_to_anchor=(0.5, 1.0))
    fig.subplots_adjust(left=0.08 if cols > 1 else 0.11, right=0.98,
                        bottom=0.45 / (h * rows + 0.5), top=1 - 0.45 / (h * rows + 0.5))
    return fig


def profile_caption(diag, corrected) -> str:
    """The caption of `profile_figure`: what is drawn, over the bore angle or over time."""
    with_ = "" if corrected is None else f" and with {corrected[0]} (solid)"
    scans = bool((~diag.model.is_max).any())
    hist = bool(diag.model.is_max.any())
    what = ((["measured profiles (each scan, dots) over the bore angle"] if scans else [])
            + (["the measured maximum depth over time"] if hist else []))
    text = " and ".join(what)
    base = "(dotted)" if corrected is not None else "(solid)"
    return (f"{text[0].upper()}{text[1:]}, the base model {base}{with_}; beneath, the "
            f"residuals (model − measured; grey: base) within ±2 noise")


def _times(times) -> str:
    """"1000, 2000, 4000" (the first two and the last where there are many)."""
    t = [f"{x:g}" for x in times]
    return ", ".join(t) if len(t) <= 3 else f"{t[0]}, {t[1]} … {t[-1]}"


def law_figure(shape):
    """The law of the shape's search (`shape.law.best`) over each of its variables' range
    in the data: a factor as ln(1 + A Φ) (its level matched to the shape's: K_d carries
    the level), a deposit as D Φ [nm·rad per step]; with the shape's own correction along
    that variable and its band (what the data ask for). A product law's other term is held
    at its reference. Returns a Figure, or None where no variable's range is known."""
    law = shape.law.best.law
    panels = []
    for k, t in enumerate(law.terms):
        z, v = _range(shape, t.variable, law.form)
        if z is not None:
            panels.append((k, t, z, v))
    if not panels:
        return None
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.6 * len(panels), 3.3))
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (k, t, z, v) in zip(axes, panels):
        states = {o.variable: np.full_like(z, o.ref) for o in law.terms}
        states[t.variable] = z
        phi = law_phi_numpy(law, states)
        if law.form == "factor":
            y = np.log1p(law.strength * phi)
            if v is not None:
                y = y - y.mean() + float(np.mean(v.g))
            ylabel = "ln(rate factor)"
        else:
            y = law.strength * phi
            ylabel = "deposit [nm·rad per step]"
        if v is not None:
            ax.fill_between(v.z, v.g_lower, v.g_upper, color="C0", alpha=0.2,
                            label=f"the shape, {int(LEVEL * 100)} % band")
            ax.plot(v.z, v.g, "C0", lw=1, alpha=0.8, label="the shape (spline)")
        ax.plot(z, y, "C3", lw=2, label="the law")
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xlabel(f"{t.variable} [{variable_unit(t.variable)}]", fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        if len(law.terms) > 1:
            ax.set_title("the other variable at its reference", fontsize=8)
        ax.legend(fontsize=7)
    fig.subplots_adjust(left=0.12 / len(panels) + 0.02, right=0.98, bottom=0.17, top=0.9,
                        wspace=0.3)
    return fig


def _range(shape, variable: str, form: str):
    """(z grid over the range met in the data, the shape's `VariableShape` along it in
    `form` or None) of a law's variable; p·v from the ranges of p and v; (None, None)
    where unknown."""
    v = next((x for x in shape.variables if x.name == variable and x.form == form), None)
    if v is None:
        v = next((x for x in shape.variables if x.name == variable), None)
        if v is not None:
            return np.asarray(v.z, float), None
    if v is not None:
        return np.asarray(v.z, float), v
    if variable == "pv_MPa_m_per_s":
        p = next((x for x in shape.variables if x.name == "pressure_MPa"), None)
        s = next((x for x in shape.variables if x.name == "sliding_speed_m_per_s"), None)
        if p is not None and s is not None:
            lo = max(float(np.min(p.z)) * float(np.min(s.z)), 0.0)
            hi = float(np.max(p.z)) * float(np.max(s.z))
            return np.linspace(lo, hi, 121), None
    return None, None
