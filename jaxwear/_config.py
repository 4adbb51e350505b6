"""Static model choices (they select code paths, so changing one recompiles)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from ._errors import InputError

ALGORITHMS = ("scla", "ideal", "li")
CONTACTS = ("unsymmetric", "symmetric")
BUSHINGS = ("coupler", "slider")
DRIVERS = ("crank_slider", "oscillating")


@dataclass(frozen=True)
class DutyBlock:
    """One block of the oscillating joint's duty cycle (DESIGN §2)."""

    amplitude_deg: float
    duration_h: float


@dataclass(frozen=True)
class ModelConfig:
    """Choices that are not numbers to fit.

    - `driver`: `"crank_slider"` (§1) or `"oscillating"` (§2).
    - `algorithm`: joint-load algorithm, `"scla"` (default), `"ideal"` or `"li"`.
    - `scla_passes`, `gamma0_rad`: SCLA iterations and start angle.
    - `bushing`: `"coupler"` (bushing in the coupler eye at D, default) or `"slider"`.
    - `contact`: `"unsymmetric"` (default) or `"symmetric"` Winkler foundation.
    - `double_layer`: series springs of a bimetal bearing (§3).
    - `nodes`, `steps_per_rev`: N and n_steps.
    - `effects`: names of the candidate effects switched on (§5).
    - `duty_cycle`: oscillating driver's blocks, repeated (boom: 20° 1 h, then 1° 4 h).
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
        ]
        for ok, msg in checks:
            if not ok:
                raise InputError(msg)

    def replace(self, **kw) -> ModelConfig:
        return replace(self, **kw)


def boom_config(**kw) -> ModelConfig:
    """The boom preset's structure: oscillating driver, double-layer (bimetal) bearing."""
    base = dict(driver="oscillating", double_layer=True)
    base.update(kw)
    return ModelConfig(**base)
