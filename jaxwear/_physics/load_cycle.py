"""One period of a joint's load and motion (`LoadCycle`) and its resampling onto the wear loop's
steps (docs/design.md §2). Reading and checking a load file is the study layer's
(`_study.load_file`)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class LoadCycle:
    """One period of a joint's load and motion, as read from `path`.

    - `time`: (rows,) [s] from 0 (the file's first time subtracted), increasing.
    - `force`: (rows, 2) [N], the load on the bushing in the bushing frame; row k's load
      holds on [time_k, time_k+1).
    - `angle`: (rows + 1,) [rad], the pin's rotation relative to the bushing, unwrapped
      (consecutive rows less than π apart), with the closing row: `angle[-1]` is where the
      first row's angle comes again one period later (its value plus whole turns).
    - `period`: [s]. `digest`: the content's hash (equality and hashing use it, so a
      `ModelConfig` holding the cycle stays a cheap static argument of jit).
    """

    path: str
    time: np.ndarray
    force: np.ndarray
    angle: np.ndarray
    period: float
    digest: str

    def __eq__(self, other):
        return isinstance(other, LoadCycle) and other.digest == self.digest

    def __hash__(self):
        return hash(self.digest)

    @property
    def rows(self) -> int:
        return len(self.time)

    @property
    def rotation(self) -> float:
        """Σ |Δangle| over one period [rad]: the sliding per period is R_p times it."""
        return float(np.sum(np.abs(np.diff(self.angle))))

    @property
    def peak_load(self) -> float:
        """Largest |load| of the file [N]."""
        return float(np.max(np.hypot(self.force[:, 0], self.force[:, 1])))


@dataclass(frozen=True)
class Resampled:
    """A load cycle on `steps` equal steps of the period (arrays (steps,)).

    - `load` [N] and `angle` [rad, bushing frame]: the step's load (see `resample`).
    - `rotation`: ∫ |d angle| over the step [rad] (sliding = R_p x it);
      `net`: ∫ d angle [rad] (its sign is the sense of the pin's rotation).
    - `dt` [s]: T / steps. `period` [s].
    """

    load: np.ndarray
    angle: np.ndarray
    rotation: np.ndarray
    net: np.ndarray
    dt: np.ndarray
    period: float


@functools.lru_cache(maxsize=64)
def resample(cycle: LoadCycle, steps: int) -> Resampled:
    """`cycle` on the wear loop's `steps` equal steps, keeping what the wear depends on.

    Step i covers [i, i + 1) T/steps of the period. Within it, the file's angle is linear
    between rows and its load holds from a row to the next (module docstring); the step
    gets, by exact integrals over the pieces where the rows and the steps overlap:
    - rotation ∫ |dφ| and net rotation ∫ dφ: the total sliding of the period and every
      reversal's sliding are kept exactly, whatever the steps (a reversal inside a step
      keeps its sliding, and the step's sense is the net one's);
    - the load magnitude weighted by the sliding, ∫ |W| |dφ| / ∫ |dφ|, so that the step's
      |W| x sliding equals the file's ∫ |W| dS: the Archard work, what the wear is to first
      order (Σ_j p_j A_j = |W| by equilibrium, so a step's worn volume is K_d |W| dS). A
      load peak narrower than a step keeps its work, not its height: its height would
      count its load over the whole step's sliding and overstate the wear, and a peak where
      the pin does not slide (at a reversal, say) wears nothing. The direction is that of
      the sliding-weighted mean load vector. A step without sliding takes the time average
      (the impulse ∫ W dt, what creep sees);
    - `tests/test_load_file.py` checks the wear against a finer resampling.

    Cached per (cycle, steps): a host computation on static data, done once per resolution.
    """
    T = cycle.period
    tau = np.r_[cycle.time, T]  # (rows + 1,): the closing row is the first one period later
    phi = cycle.angle
    s = np.arange(steps + 1) * (T / steps)
    s[-1] = T
    bp = np.union1d(tau, s)
    a, b = bp[:-1], bp[1:]
    keep = b > a
    a, b = a[keep], b[keep]
    mid = 0.5 * (a + b)
    k = np.clip(np.searchsorted(tau, mid, side="right") - 1, 0, cycle.rows - 1)
    i = np.clip(np.searchsorted(s, mid, side="right") - 1, 0, steps - 1)
    frac = (b - a) / (tau[k + 1] - tau[k])
    dphi = (phi[k + 1] - phi[k]) * frac
    adphi = np.abs(dphi)
    f = cycle.force[k]
    mag = np.hypot(f[:, 0], f[:, 1])
    dtau = b - a

    def per_step(w):
        return np.bincount(i, weights=w, minlength=steps)

    rotation, net = per_step(adphi), per_step(dphi)
    dt = np.full(steps, T / steps)
    slides = rotation > 1e-12 * max(float(np.sum(rotation)), 1e-300) / steps
    wsafe = np.where(slides, rotation, 1.0)
    load = np.where(slides, per_step(mag * adphi) / wsafe, per_step(mag * dtau) / dt)
    vx = np.where(slides, per_step(f[:, 0] * adphi), per_step(f[:, 0] * dtau))
    vy = np.where(slides, per_step(f[:, 1] * adphi), per_step(f[:, 1] * dtau))
    angle = np.arctan2(vy, vx)
    return Resampled(load, angle, rotation, net, dt, float(T))
