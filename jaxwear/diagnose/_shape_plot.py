"""Figures of the shape analysis: g(z) with its band, per variable (`shape_<name>.png`)."""

from __future__ import annotations

import numpy as np

from .._report import plt


def shape_figure(result, name: str):
    """g(z) = ln(extra wear factor) over the range of z met in the data, with its band and
    its peak; beneath the phase, the joint load and its turn rate over the cycle; beneath
    every variable, where on the bore of the most-worn experiment the extra wear lands
    (linearised, at its last measurement)."""
    from ._shape import p_text

    pl = plt()
    v = result.variable(name)
    phase = name == "cycle_phase_deg" and result.phase_load
    rows = 2 + bool(phase)
    fig, axes = pl.subplots(rows, 1, figsize=(7, 2.4 * rows + 0.6))
    ax = axes[0]
    ax.fill_between(v.z, v.g_lower, v.g_upper, color="C0", alpha=0.25,
                    label=f"{int(result_level(result) * 100)} % band")
    ax.plot(v.z, v.g, "C0", lw=2, label="g(z)" + (", refitted through the loop"
                                                   if v.refit_rmse_um is not None else
                                                   ", linearised fit"))
    ax.axhline(0.0, color="k", lw=0.8)
    ax.axvspan(v.lower, v.upper, color="C3", alpha=0.12, label="peak, 90 % band")
    ax.axvline(v.peak_at, color="C3", lw=1)
    ax.set_xlabel(f"{name} [{v.unit}]")
    ax.set_ylabel("g = ln(rate factor)")
    sig = "significant" if v.significant else "not significant"
    ax.set_title(f"{name}: explains {v.explained_fraction:.0%} of the misfit, "
                 f"dof {v.dof:.1f}, {p_text(v.p_value)} ({sig})", fontsize=9)
    if name == "load_turn_rate_deg_per_s" and float(v.z[0]) > 0:
        ax.set_xscale("log")  # spans decades
    ax.legend(fontsize=7)
    k = 1
    if phase:
        ax2 = axes[1]
        pl_ = result.phase_load
        ax2.plot(pl_["phase_deg"], pl_["load_N"], "k", lw=1.2, label="joint load |W|")
        ax2.set_ylabel("|W| [N]")
        ax2.set_xlabel("cycle phase [deg]")
        ax3 = ax2.twinx()
        ax3.semilogy(pl_["phase_deg"], np.maximum(pl_["turn_rate_deg_per_s"], 1e-3), "C2",
                     lw=1, label="load turn rate")
        ax3.set_ylabel("turn rate [deg/s]", color="C2")
        ax2.set_title(f"joint load over the cycle ({result.experiment})", fontsize=9)
        k = 2
    ax4 = axes[k]
    if v.extra_wear_um.size:
        ax4.plot(result.bore_deg, v.extra_wear_um, "C1")
    ax4.axhline(0.0, color="k", lw=0.8)
    ax4.set_xlabel("bore angle [deg]")
    ax4.set_ylabel("extra depth [µm]")
    ax4.set_title(f"where the extra wear lands ({result.experiment}, last measurement)",
                  fontsize=9)
    fig.tight_layout()
    return fig


def result_level(result) -> float:
    from ._shape import LEVEL

    return LEVEL
