"""Measurements that give a fit nothing to work with, refused before any work (issue 41).

- No wear measured: every depth of every profile and history is exactly 0. The base model
  fits that with K_d = 0, where nothing is identifiable: calibrate ran its whole budget and
  wrote "not converged", predict overflowed, diagnose divided by a noise level of 0 and
  died in LAPACK (`LinAlgError`, once SIGABRT with `--shape`).
- A noise level of 0 from the data (`_noise`'s estimator: every point on the line through
  its two neighbours, e.g. equal depths everywhere): a diagnosis weights its misfit by the
  noise, so it needs a level > 0, from the data or stated (`[fit] noise_um`).

Both read the study's files only (no model is built), so the refusal costs milliseconds.
"""

from __future__ import annotations

import numpy as np

from jaxwear._core import noise as _noise
from jaxwear._core.errors import InputError


def _rows(study):
    """(experiment index, snapshot, coordinate, is history, depth [m], file) per data row."""
    out = []
    for i, e in enumerate(study.experiments):
        if e.profile is not None:
            for x, r, d in zip(np.degrees(e.profile.angle), e.profile.revolutions,
                               e.profile.depth):
                out.append((i, float(r), float(x), False, float(d), e.profile.path))
        if e.history is not None:
            for t, d in zip(e.history.hours, e.history.depth):
                out.append((i, 0.0, float(t), True, float(d), e.history.path))
    return out


def _files(rows) -> str:
    return ", ".join(dict.fromkeys(str(r[5]) for r in rows))


def check_wear_measured(study) -> None:
    """`InputError` when the study has data rows and every depth is exactly 0."""
    rows = _rows(study)
    if rows and all(r[4] == 0 for r in rows):
        raise InputError(f"{study.path}: every measured depth ({len(rows)} rows in "
                         f"{_files(rows)}) is 0: no wear measured, so there is nothing to fit "
                         f"(K_d = 0 fits it exactly and leaves nothing identifiable); expected "
                         f"measured wear depths (a scan is noise around 0 outside the scar)")


def data_noise_um(study) -> float:
    """The noise level [µm] the data's neighbouring points give (`_noise.noise_level`),
    from the files; NaN where there are no neighbour triples."""
    rows = _rows(study)
    if not rows:
        return float("nan")
    exp, snap, x, hist, depth = (np.asarray([r[k] for r in rows]) for k in range(5))
    s = _noise.series(exp, snap, hist.astype(bool), x)
    e = _noise.neighbour_differences(s, depth * 1e6)[0]
    return float(_noise.noise_level(e)[0]) if len(e) else float("nan")


def check_noise_measurable(study) -> None:
    """`InputError` when the noise is not stated and the data's own estimate is exactly 0."""
    if study.noise_um is not None:
        return
    if data_noise_um(study) == 0.0:
        rows = _rows(study)
        raise InputError(f"{study.path}: the measured depths in {_files(rows)} give a noise "
                         f"level of 0 (every point lies on the line through its two "
                         f"neighbours, e.g. equal depths everywhere); the diagnosis weights "
                         f"the misfit by the noise: expected scanned depths with their noise, "
                         f"or the noise stated as [fit] noise_um")
