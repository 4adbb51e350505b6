"""Figures of the shape analysis: the correction along each variable with its band
(`shape_<variable>.png`, `shape_deposit_<variable>.png`), and when in the cycle and where on
the bore the missing wear is made (`shape_when_where.png`)."""

from __future__ import annotations

import numpy as np

from jaxwear._analyses.diagnose.shape.design import LEVEL
from jaxwear._analyses.diagnose.shape.text import p_text
from jaxwear._core.io import png_bytes


def file_stem(label: str) -> str:
    """`shape_<name>` (factor) or `shape_deposit_<name>`."""
    return "shape_" + label.replace("deposit:", "deposit_")


def shape_figure(result, label: str):
    """The correction over the range of its variable met in the data, with its band and its
    peak (factor: g = ln of the rate factor; deposit: e, the extra depth × arc per step);
    beneath, where on the bore of the most-worn experiment it lands (linearised, at its
    last measurement)."""
    from matplotlib.figure import Figure


    form = "deposit" if label.startswith("deposit:") else "factor"
    v = result.variable(label.removeprefix("deposit:"), form)
    # fixed margins, not tight_layout: its text measurement drew every figure twice, a
    # third of the ~30 figures' writing time (the labels here are known and fit). A
    # `Figure`, not pyplot's: `shape_pngs` draws these in a thread of its own.
    fig = Figure(figsize=(7, 5.4))
    axes = fig.subplots(2, 1, gridspec_kw=dict(left=0.14, right=0.97, top=0.9, bottom=0.09,
                                               hspace=0.5))
    ax = axes[0]
    ax.fill_between(v.z, v.g_lower, v.g_upper, color="C0", alpha=0.25,
                    label=f"{int(result_level() * 100)} % band")
    refit = v.refit_rmse_um is not None
    ax.plot(v.z, v.g, "C0", lw=2, label=("g(z)" if form == "factor" else "e(z)")
            + (", the refitted correction's start" if refit else ", linearised fit"))
    ax.axhline(0.0, color="k", lw=0.8)
    ax.axvspan(v.lower, v.upper, color="C3", alpha=0.12, label="peak, 90 % band")
    ax.axvline(v.peak_at, color="C3", lw=1)
    ax.set_xlabel(f"{v.name} [{v.unit}]")
    ax.set_ylabel("g = ln(rate factor)" if form == "factor"
                  else "e [nm·rad of depth per step]")
    sig = "significant" if v.significant else "not significant"
    ax.set_title(f"{v.label}\nexplains {v.explained_fraction:.0%} of the misfit (unique "
                 f"{v.unique_fraction:.0%}), dof {v.dof:.1f}, {p_text(v.p_value)} ({sig})",
                 fontsize=9)
    if v.name.startswith("load_turn") and float(v.z[0]) > 0:
        ax.set_xscale("log")  # spans decades
    ax.legend(fontsize=7)
    ax4 = axes[1]
    if v.extra_wear_um.size:
        ax4.plot(result.bore_deg, v.extra_wear_um, "C1")
    ax4.axhline(0.0, color="k", lw=0.8)
    ax4.set_xlabel("bore angle [deg]")
    ax4.set_ylabel("extra depth [µm]")
    ax4.set_title(f"where it lands ({result.experiment}, last measurement, linearised)",
                  fontsize=9)
    return fig


WHEN_WHERE = "when_where"  # the when/where map's key among a result's `pngs`


def shape_pngs(results, rest: bool = False) -> list[dict]:
    """PNG bytes {label: bytes} of each result's figures (None: {}): those its refit will
    not change (`ShapeResult.settled_labels`), drawn while the refit runs; `rest`: the
    others and the when/where map (key `WHEN_WHERE`), drawn once it has run, while the law
    search runs. `diagnose` draws both in threads of their own (pyplot is not used); the
    CLI writes them.

    Why `rest` (issue 50): drawn by the CLI after the answer, the refitted variables' and
    the maps' figures (6 on the generator's fatigue study) were ~1.7 s of its last
    seconds, on one core."""
    out = []
    for res in results:
        pngs = {}
        if res is not None:
            settled = res.settled_labels()
            for label in ([v.label for v in res.variables if v.label not in settled] if rest
                          else settled):
                pngs[label] = png_bytes(shape_figure(res, label))
            if rest and res.when_where is not None:
                pngs[WHEN_WHERE] = png_bytes(when_where_figure(res))
        out.append(pngs)
    return out


def when_where_figure(result):
    """The extra wear of one cycle of the refitted correction over cycle phase × bore angle
    (µm per 10⁴ cycles), its marginals with bands, and the joint load with its reversals."""
    from matplotlib.figure import Figure

    ww = result.when_where
    # a `Figure`, not pyplot's: `shape_pngs` draws it in a thread of its own
    fig = Figure(figsize=(8, 7.5))
    gs = fig.add_gridspec(3, 2, width_ratios=[4, 1.3], height_ratios=[1.2, 3, 1.4],
                          hspace=0.35, wspace=0.08)
    ax_w = fig.add_subplot(gs[0, 0])
    ax_m = fig.add_subplot(gs[1, 0], sharex=ax_w)
    ax_r = fig.add_subplot(gs[1, 1], sharey=ax_m)
    ax_l = fig.add_subplot(gs[2, 0], sharex=ax_w)
    ph, bo = ww.phase_deg, ww.bore_deg
    ax_w.fill_between(ph, ww.when_lower, ww.when_upper, color="C0", alpha=0.25,
                      label=f"{int(ww.level * 100)} % band")
    ax_w.plot(ph, ww.when_um_rad, "C0", lw=1.5, label="extra wear made in each step")
    ax_w.axhline(0, color="k", lw=0.6)
    ax_w.set_ylabel("µm·rad / 10⁴ cyc")
    ax_w.legend(fontsize=7, loc="upper right")
    ax_w.set_title(f"When and where the missing wear is made ({ww.experiment}, "
                   f"{result.form} along {', '.join(result.carriers)})", fontsize=9)
    m = np.asarray(ww.map_um).T  # (nodes, steps)
    lim = max(float(np.max(np.abs(m))), 1e-30)
    im = ax_m.imshow(m, origin="lower", aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim,
                     extent=(ph[0], ph[-1] + (ph[1] - ph[0]), bo[0],
                             bo[-1] + (bo[1] - bo[0])))
    ax_m.set_ylabel("bore angle [deg]")
    fig.colorbar(im, ax=ax_r, fraction=0.5, label="µm / 10⁴ cycles per step")
    ax_r.fill_betweenx(bo, ww.where_lower, ww.where_upper, color="C1", alpha=0.25)
    ax_r.plot(ww.where_um, bo, "C1", lw=1.5)
    ax_r.axvline(0, color="k", lw=0.6)
    ax_r.set_xlabel("µm / 10⁴ cyc")
    ax_r.tick_params(labelleft=False)
    ax_l.plot(ph, ww.load_N, "k", lw=1.2, label="joint load |W|")
    ax_l.set_ylabel("|W| [N]")
    ax_l.set_xlabel("cycle phase [deg]")
    ax2 = ax_l.twinx()
    ax2.semilogy(ph, np.maximum(ww.turn_rate_deg_per_s, 1e-3), "C2", lw=1)
    ax2.set_ylabel("turn rate [deg/s]", color="C2")
    for ax in (ax_w, ax_m, ax_l):
        for r in ww.reversals_deg:
            ax.axvline(r, color="C2", ls="--", lw=1)
        ax.axvline(ww.peak_load_deg, color="k", ls=":", lw=1)
    ax_l.set_title("load reversals (dashed) and peak load (dotted)", fontsize=8)
    return fig


def result_level() -> float:

    return LEVEL
