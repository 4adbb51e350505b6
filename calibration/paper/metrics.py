"""Measures behind the paper reproduction (`reproduce.py`) and its tests (`tests/test_paper.py`).

Everything here is a thin layer over the public jaxwear API plus NumPy: joint forces by the
three algorithms (paper §1), pressure maps of one revolution on a given worn profile (paper
Figs 8-9), an asymmetry index of a pressure distribution about its load direction, and the
width of the wear area.

Units: SI in and out (N, Pa, m, rad) unless a name says otherwise (`_deg`, `_um`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxwear as jw
from jaxwear._physics.cycle import node_area

load_history = eqx.filter_jit(jw.load_history)
"""`jw.load_history`, compiled (its eager nested `jvp`s cost seconds per call)."""


def cycle_times(p: jw.Params, steps: int, cycles: int = 1) -> jnp.ndarray:
    """Step times t_i = i T / steps [s] over `cycles` crank revolutions, T = 2π/ω."""
    period = 2 * jnp.pi / p.speed
    return jnp.arange(steps * cycles) * (period / steps)


@eqx.filter_jit
def _force(p, t, gamma0, algorithm):
    jf = jw.crank_slider_forces(p, t, algorithm, 2, gamma0)
    return jf.fx, jf.fy


def joint_force(p: jw.Params, steps: int, algorithm: str = "scla", gamma0_rad: float = 0.0):
    """F_C over one revolution: (|F| [N], F_x [N], F_y [N]) as NumPy arrays (steps,).

    Compiled once per algorithm; the start angle `gamma0_rad` [rad] is a traced value.
    """
    fx, fy = _force(p, cycle_times(p, steps), jnp.asarray(gamma0_rad, jnp.float64), algorithm)
    fx, fy = np.asarray(fx), np.asarray(fy)
    return np.hypot(fx, fy), fx, fy


@eqx.filter_jit
def _ideal_angle_rates(p, t):
    def gamma(tt):
        jf = jw.crank_slider_forces(p, tt, "ideal")
        return jnp.arctan2(jf.fy, jf.fx)

    def gamma_and_rate(tt):
        return jax.jvp(gamma, (tt,), (jnp.ones_like(tt),))

    (g, gd), (_, gdd) = jax.jvp(gamma_and_rate, (t,), (jnp.ones_like(t),))
    return g, gd, gdd


def ideal_angle_rates(p: jw.Params, steps: int):
    """Angle γ of the ideal joint's force and its time derivatives γ̇ [rad/s], γ̈ [rad/s²]
    (paper eqs 11-13, here by forward-mode autodiff in time): the rates that Li's algorithm
    feeds into the clearance link and the SCLA sets to zero. NumPy arrays (steps,)."""
    g, gd, gdd = _ideal_angle_rates(p, cycle_times(p, steps))
    return np.asarray(g), np.asarray(gd), np.asarray(gdd)


def snap_to_nodes(angle_rad, nodes: int):
    """Load directions rounded to the nearest node (≤ half a node spacing away).

    With θ_W on a node m, the mirror image about θ_W of node m + k is node m - k, so
    `mirror_asymmetry` needs no interpolation and a symmetric distribution scores 0 to
    round-off. Returns (snapped angles [rad] (steps,), node indices (steps,) int).
    """
    idx = np.mod(np.rint(np.asarray(angle_rad) / (2 * np.pi) * nodes), nodes).astype(int)
    return 2 * np.pi * idx / nodes, idx


def pressure_map(p: jw.Params, cfg: jw.ModelConfig, depth_m, snap: bool = True):
    """Contact pressure over one revolution on the frozen profile `depth_m` (nodes,) [m].

    The load history is the model's (`jw.load_history`); with `snap` its directions are
    rounded to the nodes (see `snap_to_nodes`). Raises if a contact solve did not converge
    (relative force residual ≥ 1e-9, design.md §3).

    **Returns:** (pressure [Pa] (steps, nodes), load-node index (steps,), load angle [rad]).
    """
    hist = load_history(p, cfg)
    load, angle = np.asarray(hist.load[0]), np.asarray(hist.angle[0])
    idx = None
    if snap:
        angle, idx = snap_to_nodes(angle, cfg.nodes)
    pressure, residual = _pressure(p, jnp.asarray(load), jnp.asarray(angle),
                                   jnp.asarray(depth_m, jnp.float64), cfg.nodes, cfg.contact,
                                   cfg.double_layer)
    res = float(residual)
    if not res < 1e-9:
        raise RuntimeError(f"contact solve did not converge: relative residual {res:.1e}")
    return np.asarray(pressure), idx, angle


@eqx.filter_jit
def _pressure(p, load, angle, h, nodes, contact, double_layer):
    k = jw.stiffness_per_area(h, p, double_layer)
    sol = jw.solve_contact(load, angle, h, p.clearance, k, node_area(p, nodes), contact=contact)
    return sol.pressure, jnp.max(sol.residual)


def mirror_asymmetry(pressure, centre_idx):
    """Asymmetry of each step's pressure about its load node, in [0, 1].

    A_i = ½ Σ_j |p_i(m+k) - p_i(m-k)| / Σ_j p_ij, m the load node: 0 for a distribution
    mirror-symmetric about θ_W, 1 for one entirely on one side. (The first angular moment
    Σ p_j sin(θ_j - θ_W) is no measure: it vanishes for both models by the equilibrium
    perpendicular to the load.) Steps without load score 0.

    **Arguments:** `pressure` (steps, nodes) [Pa]; `centre_idx` (steps,) node of θ_W.
    """
    pressure = np.asarray(pressure)
    n = pressure.shape[1]
    j = np.arange(n)
    mirror = np.mod(2 * np.asarray(centre_idx)[:, None] - j[None, :], n)
    pm = np.take_along_axis(pressure, mirror, axis=1)
    total = pressure.sum(axis=1)
    diff = 0.5 * np.abs(pressure - pm).sum(axis=1)
    return np.where(total > 0, diff / np.where(total > 0, total, 1.0), 0.0)


def wear_area_nodes(depth, fraction: float = 0.05) -> int:
    """Number of nodes worn deeper than `fraction` of the maximum depth (0 if unworn)."""
    depth = np.asarray(depth)
    top = depth.max()
    return int(np.sum(depth > fraction * top)) if top > 0 else 0


def wear_area_edges_deg(depth, fraction: float = 0.05):
    """Bushing angles [deg] where the wear area (depth > `fraction` × max) begins or ends:
    the nodes worn past the threshold whose neighbour on one side is not."""
    depth = np.asarray(depth)
    n = depth.shape[0]
    inside = depth > fraction * depth.max()
    edge = inside & (~np.roll(inside, 1) | ~np.roll(inside, -1))
    return np.flatnonzero(edge) * 360.0 / n


def angular_distance_deg(a_deg, b_deg):
    """Smallest absolute difference of two angles [deg] (broadcasting)."""
    d = np.mod(np.asarray(a_deg) - np.asarray(b_deg) + 180.0, 360.0) - 180.0
    return np.abs(d)
