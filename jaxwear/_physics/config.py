"""Static model choices (they select code paths, so changing one recompiles)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from jaxwear._core.errors import InputError

ALGORITHMS = ("scla", "ideal", "li")
CONTACTS = ("unsymmetric", "symmetric")
BUSHINGS = ("coupler", "slider")
DRIVERS = ("crank_slider", "oscillating", "load_history")
TIMED_DRIVERS = ("oscillating", "load_history")  # experiments run for hours


@dataclass(frozen=True)
class DutyBlock:
    """One block of a duty cycle (design.md §2): the oscillating joint's swing of
    `amplitude_deg`, or (preset "load_history") one period of `load`, a `LoadCycle` from a
    file, repeated for `duration_h` (inf: a single file, repeated for the whole run)."""

    amplitude_deg: float
    duration_h: float
    load: object = None  # _load_file.LoadCycle (load_history driver)


@dataclass(frozen=True)
class ModelConfig:
    """Choices that are not numbers to fit.

    - `driver`: `"crank_slider"` (§1), `"oscillating"` (§2) or `"load_history"` (§2, your
      own joint: the load and motion of each duty block from a file).
    - `algorithm`: joint-load algorithm, `"scla"` (default), `"ideal"` or `"li"`.
    - `scla_passes`, `gamma0_rad`: SCLA iterations and start angle.
    - `bushing`: `"coupler"` (bushing in the coupler eye at D, default) or `"slider"`.
    - `contact`: `"unsymmetric"` (default) or `"symmetric"` Winkler foundation.
    - `double_layer`: series springs of a bimetal bearing (§3).
    - `nodes`, `steps_per_rev`: N and n_steps.
    - `effects`: names of the candidate effects switched on (§5).
    - `duty_cycle`: oscillating driver's blocks, repeated (boom: 20° 1 h, then 1° 4 h), or
      the load_history driver's files with their durations.
    - `shape`: a non-parametric correction of the local wear rate (`effects.shape`), used
      by `diagnose --shape`; None (default) is the model as written.
    """

    driver: str = "crank_slider"
    algorithm: str = "scla"
    scla_passes: int = 2
    gamma0_rad: float = 0.0
    bushing: str = "coupler"
    contact: str = "unsymmetric"
    double_layer: bool = False
    nodes: int = 360
    steps_per_rev: int = 360
    effects: tuple[str, ...] = ()
    duty_cycle: tuple[DutyBlock, ...] = field(
        default_factory=lambda: (DutyBlock(20.0, 1.0), DutyBlock(1.0, 4.0)))
    newton_iterations: int = 40
    shape: object = None  # effects.shape.ShapeBasis: exp(g(z)) on the local rate (diagnose)

    def __post_init__(self):
        checks = [
            (self.driver in DRIVERS, f"driver must be one of {DRIVERS}, got {self.driver!r}"),
            (self.algorithm in ALGORITHMS,
             f"algorithm must be one of {ALGORITHMS}, got {self.algorithm!r}"),
            (self.contact in CONTACTS, f"contact must be one of {CONTACTS}, got {self.contact!r}"),
            (self.bushing in BUSHINGS, f"bushing must be one of {BUSHINGS}, got {self.bushing!r}"),
            (isinstance(self.scla_passes, int) and self.scla_passes >= 1,
             f"scla_passes must be an integer >= 1, got {self.scla_passes!r}"),
            (isinstance(self.nodes, int) and self.nodes >= 8,
             f"nodes must be an integer >= 8, got {self.nodes!r}"),
            (isinstance(self.steps_per_rev, int) and self.steps_per_rev >= 4,
             f"steps_per_rev must be an integer >= 4, got {self.steps_per_rev!r}"),
            (math.isfinite(self.gamma0_rad), "gamma0 must be finite"),
            ((self.driver == "load_history") == all(b.load is not None
                                                    for b in self.duty_cycle),
             "a load_history driver takes a load file per duty block (and only it does)"),
        ]
        for ok, msg in checks:
            if not ok:
                raise InputError(msg)

    def replace(self, **kw) -> ModelConfig:
        return replace(self, **kw)


def timed(cfg) -> bool:
    """Experiments of a `ModelConfig` run for hours (oscillating joint, load history), not
    revolutions (anything with a `driver` will do)."""
    return cfg.driver in TIMED_DRIVERS


def boom_config(**kw) -> ModelConfig:
    """The boom preset's structure: oscillating driver, double-layer (bimetal) bearing."""
    base = dict(driver="oscillating", double_layer=True)
    base.update(kw)
    return ModelConfig(**base)
