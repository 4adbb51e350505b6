"""The validation page's building blocks: constants, plotting, timing and the Page."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(__file__).resolve().parent / "boom_table5.csv"  # copy of shared/data/boom_table5.csv
DPI = 90
MAX_PNG_BYTES = 150_000
STEPS = 360  # steps per revolution, as the paper's step axis (0..359)
NODES = 360


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 8, "axes.titlesize": 9, "axes.grid": True,
                         "grid.alpha": 0.3})
    return plt


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    jax.block_until_ready(out)
    return out, time.perf_counter() - t0


def _median_time(fn, repeats: int) -> float:
    """Median wall time [s] of `fn()` after one warm-up call (compilation excluded)."""
    jax.block_until_ready(fn())
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def _runs(mask):
    """Contiguous runs of True in a boolean array: [(first, last), ...] (not wrapped)."""
    idx = np.flatnonzero(mask)
    if not len(idx):
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    ends = np.concatenate([idx[breaks], [idx[-1]]])
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


def _pct(x):
    return f"{100 * x:.1f}%"


class Page:
    """Markdown text, figures and the numbers behind them."""

    def __init__(self, out: Path):
        self.out = out
        self.lines: list[str] = []
        self.numbers: dict = {}
        self.figures: dict[str, int] = {}

    def add(self, *lines: str):
        self.lines.extend(lines)

    def table(self, header, rows):
        self.add("| " + " | ".join(header) + " |", "|" + "---|" * len(header))
        for r in rows:
            self.add("| " + " | ".join(str(x) for x in r) + " |")
        self.add("")

    def figure(self, fig, name: str, caption: str):
        path = self.out / name
        fig.savefig(path, dpi=DPI)
        _plt().close(fig)
        size = path.stat().st_size
        self.figures[name] = size
        if size > MAX_PNG_BYTES:
            print(f"warning: {name} is {size / 1e3:.0f} kB (> {MAX_PNG_BYTES / 1e3:.0f} kB)",
                  file=sys.stderr)
        self.add(f"![{caption}]({name})", "", f"*{caption}*", "")
