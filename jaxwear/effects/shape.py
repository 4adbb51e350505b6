"""A non-parametric correction of the local wear rate: exp(g(z)) along state variables.

The library's effects are parametric corrections of the wear rate along a few state
variables (running-in: sliding distance; speed: sliding speed; ...). `diagnose --shape`
asks the data which shape they want along each variable, including shapes no effect has:
the local rate K_d p_ij dS_i becomes K_d p_ij dS_i exp(Σ_v g_v(z_v,ij)), each g_v a smooth
function on a small B-spline basis. All coefficients zero is the base model exactly
(nesting), so one forward-mode Jacobian at zero gives the linearised fit of every variable.

State variables (`VARIABLES`), per step i of a cycle and node j of the bore:

| name | unit | what |
|---|---|---|
| `cycle_phase_deg` | deg | crank angle (swing phase, phase in a load file's period): 360 i/steps |
| `pressure_MPa` | MPa | contact pressure p_ij |
| `sliding_speed_m_per_s` | m/s | dS_i / Δt_i |
| `sliding_distance_m` | m | accumulated sliding distance S (time in the test) |
| `load_turn_rate_deg_per_s` | deg/s | how fast the load direction θ_W turns (impacts at reversal) |
| `bore_angle_deg` | deg | node angle on the bore, 360 j / nodes |

The two angles are periodic: their basis is cubic B-splines on the circle. The others use
cubic B-splines uniform in the wear-weighted quantile of z (`ShapeVariable`, the quantiles
set by `diagnose._shape` from the data's own states): the load turn rate, which spans
decades (slow turning through most of the cycle, a jump at a force reversal), and the
sliding speed, low only near reversals where little wears, get their resolution where the
wear is.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

# name -> (unit, periodic)
VARIABLES: dict[str, tuple[str, bool]] = {
    "cycle_phase_deg": ("deg", True),
    "pressure_MPa": ("MPa", False),
    "sliding_speed_m_per_s": ("m/s", False),
    "sliding_distance_m": ("m", False),
    "load_turn_rate_deg_per_s": ("deg/s", False),
    "bore_angle_deg": ("deg", True),
}


@dataclass(frozen=True)
class ShapeVariable:
    """One variable's basis: `size` cubic B-splines. Periodic variables: uniform on the
    circle [0, 360) deg. The others: uniform in the coordinate t = F(z) ∈ [0, 1], F the
    wear-weighted distribution of z met in the data (`knots`: z at t = 0, 1/Q, ..., 1,
    increasing; F piecewise linear between them), z clamped to [knots[0], knots[-1]]: the
    basis is fine where the wear happens and coarse where little does, and g is flat beyond
    the data, never extrapolated."""

    name: str
    size: int
    knots: tuple = ()

    @property
    def unit(self) -> str:
        return VARIABLES[self.name][0]

    @property
    def periodic(self) -> bool:
        return VARIABLES[self.name][1]

    @property
    def lo(self) -> float:
        return 0.0 if self.periodic else float(self.knots[0])

    @property
    def hi(self) -> float:
        return 360.0 if self.periodic else float(self.knots[-1])

    def keys(self) -> tuple[str, ...]:
        """The effect-parameter keys of the coefficients (dimensionless)."""
        return tuple(f"shape_{self.name}_{k:02d}" for k in range(self.size))

    def coordinate(self, z, xp=jnp):
        """t = F(z) ∈ [0, 1] (non-periodic variables)."""
        zq = xp.asarray(self.knots)
        return xp.interp(z, zq, xp.linspace(0.0, 1.0, len(self.knots)))

    def at_coordinate(self, t) -> np.ndarray:
        """z at t (numpy): the inverse of `coordinate`."""
        return np.interp(t, np.linspace(0.0, 1.0, len(self.knots)), np.asarray(self.knots))

    def basis(self, z, xp=jnp):
        """B-spline values (..., size) at z (...) in the variable's unit."""
        if self.periodic:
            h = 360.0 / self.size
            centres = xp.arange(self.size) * h
            d = xp.mod(z[..., None] - centres + 180.0, 360.0) - 180.0
            return _cubic_bspline(d / h, xp)
        t = self.coordinate(z, xp)
        h = 1.0 / (self.size - 3)
        centres = (xp.arange(self.size) - 1.0) * h
        return _cubic_bspline((t[..., None] - centres) / h, xp)

    def roughness(self) -> np.ndarray:
        """Second-difference penalty matrix D'D (size, size): zero on constants (and, for
        the clamped basis, on straight lines in t)."""
        n = self.size
        if self.periodic:
            D = np.zeros((n, n))
            for i in range(n):
                D[i, (i - 1) % n], D[i, i], D[i, (i + 1) % n] = 1.0, -2.0, 1.0
        else:
            D = np.zeros((n - 2, n))
            for i in range(n - 2):
                D[i, i:i + 3] = (1.0, -2.0, 1.0)
        return D.T @ D


def _cubic_bspline(t, xp):
    """The cardinal cubic B-spline (support |t| < 2, partition of unity over shifts)."""
    a = xp.abs(t)
    inner = (4.0 - 6.0 * a ** 2 + 3.0 * a ** 3) / 6.0
    outer = (2.0 - a) ** 3 / 6.0
    return xp.where(a < 1.0, inner, xp.where(a < 2.0, outer, 0.0))


@dataclass(frozen=True)
class ShapeBasis:
    """The variables of a shape correction (static: part of `ModelConfig`)."""

    variables: tuple[ShapeVariable, ...]

    def keys(self) -> tuple[str, ...]:
        return tuple(k for v in self.variables for k in v.keys())


def state_variables(pressure, slide, dt, sliding, angle, xp=jnp):
    """Every variable of `VARIABLES` for one cycle, each broadcastable to (steps, nodes).

    `pressure` (steps, nodes) [Pa]; `slide` dS_i (steps,) [m]; `dt` (steps,) [s];
    `sliding` S [m] (scalar); `angle` θ_W (steps,) [rad]."""
    steps, nodes = pressure.shape
    phase = xp.arange(steps) * (360.0 / steps)
    speed = slide / xp.where(dt > 0, dt, 1.0)
    # central difference of the load direction over the cycle, wrapped to (-π, π]
    turn = xp.roll(angle, -1) - xp.roll(angle, 1)
    turn = xp.mod(turn + xp.pi, 2 * xp.pi) - xp.pi
    span = xp.roll(dt, 1) + dt  # from step i-1 to i+1
    turn_rate = xp.degrees(xp.abs(turn)) / xp.where(span > 0, span, 1.0)
    return {
        "cycle_phase_deg": phase[:, None],
        "pressure_MPa": pressure * 1e-6,
        "sliding_speed_m_per_s": speed[:, None],
        "sliding_distance_m": xp.broadcast_to(sliding, (1, 1)),
        "load_turn_rate_deg_per_s": turn_rate[:, None],
        "bore_angle_deg": (xp.arange(nodes) * (360.0 / nodes))[None, :],
    }


def shape_log_factor(shape: ShapeBasis, p, pressure, slide, dt, sliding, angle):
    """Σ_v g_v(z_v) (steps, nodes): the log of the correction of the local wear rate, with
    the coefficients from `p.effect_params` under `ShapeVariable.keys()`."""
    z = state_variables(pressure, slide, dt, sliding, angle)
    g = jnp.zeros(pressure.shape)
    for var in shape.variables:
        coef = jnp.stack([p.effect_params[k] for k in var.keys()])
        g = g + var.basis(z[var.name]) @ coef
    return g
