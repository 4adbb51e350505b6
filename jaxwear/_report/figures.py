"""Files and figures written by the CLI: CSV tables, JSON summaries, PNG plots.

Outputs go under the user's `--out` folder, never replace an input file and are written
atomically (`_io`).
"""

from __future__ import annotations

import threading

import numpy as np

from jaxwear._core.io import save_figure

_importing = threading.Lock()  # one thread imports the plotting library (`warm_plots`)


def plt():
    """matplotlib's pyplot on the Agg backend (imported here, ~0.3 s: not at start-up)."""
    with _importing:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as pyplot

    return pyplot


def warm_plots(after: threading.Event) -> None:
    """Import the plotting library in a daemon thread once `after` is set (a fit's
    Jacobian program lowered: its XLA compilation leaves the interpreter free for seconds),
    so that the figures at the answer's end do not wait for it (~0.3 s of a cold
    `calibrate`). Importing beside the fit's tracing would only slow that down."""
    from jaxwear._core.background import Background

    def run():
        after.wait()
        plt()

    Background(run)


PLOT_POINTS = 4000  # markers of one series in a figure; beyond, rows are binned


def thinned(x, y, max_points: int = PLOT_POINTS) -> np.ndarray:
    """Indices of the points of a scatter (x, y) to draw: all of them up to `max_points`;
    beyond, the lowest and the highest y in each of `max_points`/2 bins of equal count
    along x, in x order. A figure of a 300 000-row profile once took minutes; this one
    draws in a second and still shows the data's envelope, outliers included."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    n = len(x)
    if n <= max_points:
        return np.arange(n)
    order = np.argsort(x, kind="stable")
    bins = np.arange(n) * (max_points // 2) // n  # the bin of each point, in x order
    by = np.lexsort((y[order], bins))  # by bin, then by y within the bin
    first = np.flatnonzero(np.r_[True, np.diff(bins[by]) > 0])
    last = np.r_[first[1:], n] - 1
    return np.unique(order[by[np.r_[first, last]]])


def thinned_label(label: str, n: int, max_points: int = PLOT_POINTS) -> str:
    """`label`, saying so when its points were binned (`thinned`)."""
    if n <= max_points:
        return label
    return f"{label} ({n} rows: lowest and highest of {max_points // 2} bins)"


def fixed_layout(fig, axes, *, right: float, top: float, bottom: float,
                 hspace: float | None = None) -> None:
    """The figure's margins without `tight_layout`, for a column of axes whose x label and
    title are one line each: `right`, `top`, `bottom` as fractions of the figure (those
    tight_layout chose for these figures), the left margin from the widest y tick label.

    Why: tight_layout measures every text by drawing it, a second partial draw of each
    figure: 0.05-0.16 s of the 0.2-0.45 s a `simulate` figure took (3 per experiment,
    ~1 s of a 5-experiment study's ~10 s; measured 2026-11-30, docs/performance.md). The
    y tick labels are known before drawing (the axis's formatter at its ticks in view);
    the left margin is 0.48 in for the label and the ticks plus 0.09 in a character: 0.01-
    0.08 in wider than tight_layout's on the rig's and the boom's figures, and within 0.1
    in of it for labels of 1 to 6 characters (`tests/test_figure_layout.py`)."""
    chars = 1
    for ax in axes:
        lo, hi = sorted(ax.get_ylim())
        pad = 1e-9 * (hi - lo)
        ticks = [t for t in ax.get_yticks() if lo - pad <= t <= hi + pad]
        labels = ax.yaxis.get_major_formatter().format_ticks(ticks)
        chars = max([chars, *map(len, labels)])
    left = (0.48 + 0.09 * chars) / fig.get_figwidth()
    fig.subplots_adjust(left=left, right=right, top=top, bottom=bottom, hspace=hspace)


def finish(fig, ax, path) -> None:
    """Grid, legend and layout of a one-axes figure (a one-line x label and title),
    written to `path` and closed."""
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fixed_layout(fig, [ax], right=0.96, top=0.9, bottom=0.165)
    save_figure(fig, path)
    plt().close(fig)


def plot_profile(path, name, angle_deg, depth_um, measured=None, snapshots=None,
                 frame="from B→D, counter-clockwise"):
    """Final (and snapshot) wear profiles vs bushing angle, with measured points if any;
    `frame` says where the angle counts from."""
    pl = plt()
    fig, ax = pl.subplots(figsize=(7, 3.6))
    if snapshots:
        for label, d in snapshots:
            ax.plot(angle_deg, d, lw=0.8, alpha=0.6, label=label)
    ax.plot(angle_deg, depth_um, "k-", lw=1.6, label="model")
    if measured is not None:
        k = thinned(*measured)
        ax.plot(np.asarray(measured[0])[k], np.asarray(measured[1])[k], "o", ms=3,
                color="tab:red", label=thinned_label("measured", len(measured[0])))
    ax.set_xlabel(f"bushing angle θ [deg] ({frame})")
    ax.set_ylabel("wear depth [µm]")
    ax.set_xlim(0, 360)
    ax.set_xticks(range(0, 361, 45))
    ax.set_title(f"{name}: wear profile")
    finish(fig, ax, path)


def plot_load(path, name, fx, fy, angle_rad):
    """Joint load over one cycle (paper Fig. 7): components, magnitude and bushing angle."""
    pl = plt()
    steps = np.arange(len(fx))
    fig, (a1, a2) = pl.subplots(2, 1, figsize=(7, 5), sharex=True)
    a1.plot(steps, fx, label="F_Cx")
    a1.plot(steps, fy, label="F_Cy")
    a1.plot(steps, np.hypot(fx, fy), "k", label="|F_C|")
    a1.set_ylabel("joint force [N]")
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    a1.set_title(f"{name}: joint load over one cycle")
    a2.plot(steps, np.degrees(angle_rad) % 360, ".", ms=2)
    a2.set_ylabel("load angle θ_W [deg]")
    a2.set_xlabel("step")
    a2.set_ylim(0, 360)
    a2.grid(alpha=0.3)
    fixed_layout(fig, [a1, a2], right=0.98, top=0.93, bottom=0.115, hspace=0.11)
    save_figure(fig, path)
    pl.close(fig)


def plot_pressure_map(path, title, pressure_pa):
    """Pressure over (step, bushing angle) of one cycle (paper Figs 8-9)."""
    pl = plt()
    steps, nodes = pressure_pa.shape
    fig, ax = pl.subplots(figsize=(7, 4))
    im = ax.imshow(pressure_pa / 1e6, aspect="auto", origin="lower", cmap="viridis",
                   extent=[0, 360, 0, steps])
    ax.set_xlabel("bushing angle θ [deg]")
    ax.set_ylabel("step of the cycle")
    ax.set_title(title)
    fig.colorbar(im, ax=ax, label="contact pressure [MPa]")
    fixed_layout(fig, [ax], right=0.98, top=0.91, bottom=0.145)
    save_figure(fig, path)
    pl.close(fig)


def plot_history(path, name, hours, depth_mm, measured=None):
    pl = plt()
    fig, ax = pl.subplots(figsize=(6, 3.6))
    ax.plot(hours, depth_mm, "k-o", ms=3, label="model")
    if measured is not None:
        ax.plot(measured[0], measured[1], "s", color="tab:red", label="measured")
    ax.set_xlabel("time [h]")
    ax.set_ylabel("maximum wear depth [mm]")
    ax.set_title(f"{name}: depth vs time")
    finish(fig, ax, path)


def sweep_heatmap(path, title, label, res, z):

    pl = plt()
    z = np.where(res.valid, z, np.nan)
    valid = res.valid
    # more than two axes with several values: the first two, at the last value of the others
    varying = [i for i, n in enumerate(res.shape) if n > 1]
    pick = tuple(slice(None) if i in varying[:2] else (-1 if n > 1 else 0)
                 for i, n in enumerate(res.shape))
    z, valid = z[pick], valid[pick]
    names = [list(res.axes)[i] for i in (varying[:2] or [0])]
    at = ", ".join(f"{k} = {v[-1]:g}" for i, (k, v) in enumerate(res.axes.items())
                   if i in varying[2:])
    title = f"{title} ({at})" if at else title
    fig, ax = pl.subplots(figsize=(6.4, 4.6))
    if len(names) == 2:
        x, y = res.axes[names[1]], res.axes[names[0]]
        im = ax.pcolormesh(x, y, z, shading="nearest", cmap="viridis")
        fig.colorbar(im, ax=ax, label=label)
        ax.set_xlabel(names[1])
        ax.set_ylabel(names[0])
        status = np.asarray(res.status)[pick]
        for what, label, mark in (("worn_through", "layer worn through", "x"),
                                  ("contact_failed", "contact solve failed", "s"),
                                  ("integration_failed", "integration failed", "D")):
            if (status == what).any():
                yy, xx = np.nonzero(status == what)
                ax.plot(x[xx], y[yy], mark, color="tab:red", mfc="none", label=label)
        if not valid.all():
            ax.legend(fontsize=8)
    else:  # one axis with several values: a line
        ax.plot(res.axes[names[0]], z.ravel(), "k-o", ms=3)
        ax.set_xlabel(names[0])
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    ax.set_title(title)
    fig.tight_layout()
    save_figure(fig, path)
    pl.close(fig)


def sensitivity_chart(path, results: dict):

    pl = plt()
    names = list(results)
    keys = list(dict.fromkeys(k for r in results.values() for k in r.keys))
    fig, axes = pl.subplots(1, 2, figsize=(11, 0.32 * len(keys) * max(1, len(names)) ** 0.5
                                           + 1.8), sharey=True)
    y = np.arange(len(keys))
    h = 0.8 / len(names)
    for panel, (ax, what, title) in enumerate(zip(
            axes, ("peak", "volume"), ("peak depth", "worn volume"))):
        for j, name in enumerate(names):
            r = results[name]
            vals = [getattr(r, what)[r.keys.index(k)] if k in r.keys else np.nan for k in keys]
            ax.barh(y + (j - (len(names) - 1) / 2) * h, vals, height=h, label=name)
        ax.axvline(0, color="k", lw=0.8)
        ax.set_title(f"d ln({title}) / d ln θ")
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(y)
    axes[0].set_yticklabels(keys, fontsize=8)
    axes[0].invert_yaxis()
    if len(names) > 1:
        axes[1].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    pl.close(fig)
