"""Snapshots of a forecast: rows past an early stop filled, and values read at another node
count."""

from __future__ import annotations

import numpy as np

from jaxwear._core.periodic import interp_periodic


def fill_past_stop(snaps, J=None):
    """Snapshots (E, S, N) (and their Jacobian (E, S, N, p)) with the rows after an early
    stop (+inf) replaced by the last computed row of their experiment: the depth never
    decreases, so a lower bound, past every allowed limit (the stop comes only past the
    layer). A band edge that had not reached the limit by the stop stays below it: "not
    reached" rather than a guess."""
    bad = np.isinf(snaps).any(axis=-1)  # (E, S)
    if not bad.any():
        return snaps, J
    idx = np.where(bad, 0, np.arange(snaps.shape[1])[None, :])
    idx = np.maximum.accumulate(idx, axis=1)
    snaps = np.take_along_axis(snaps, idx[..., None], axis=1)
    if J is not None:
        J = np.take_along_axis(J, idx[..., None, None], axis=1)
    return snaps, J


def on_nodes(a, nodes: int):
    """`a` (E, S, N, ...) periodic-linearly interpolated along its node axis to `nodes`
    equally spaced nodes (a Jacobian at the fit's nodes read at a finer level's)."""
    a = np.asarray(a)
    if a.shape[2] == nodes:
        return a
    return interp_periodic(a, 2 * np.pi * np.arange(nodes) / nodes, axis=2)
