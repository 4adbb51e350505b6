"""Crank-slider with a clearance link: kinematics and the joint reaction force (design.md §1).

All functions are elementwise in time, so one call evaluates every step of a revolution at
once. Time derivatives come from nested `jax.jvp` (exact, no hand algebra to get wrong); the
hand-derived eqs 4-7 are in `kinematics_by_hand` and the tests check that both agree.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from jaxwear._core import pytree, tangents
from jaxwear._core.types import StepArray
from jaxwear._physics.params import Params


class Kinematics(pytree.Struct):
    """Positions and their first/second time derivatives, each shaped like `t`."""

    phi2: StepArray  # Φ2 [rad]
    phi2_d: StepArray
    phi2_dd: StepArray
    xs_dd: StepArray  # ẍ_s [m/s²]
    xs: StepArray  # x_s [m]
    gx_dd: StepArray  # a_G [m/s²]
    gy_dd: StepArray


class JointForce(pytree.Struct):
    """Reaction force F_C of the slider's pin on the coupler, per step."""

    fx: StepArray  # F_Cx [N]
    fy: StepArray  # F_Cy [N]
    kin: Kinematics
    gamma_change: StepArray  # SCLA: |Δγ| of the last pass [rad] (0 for other algorithms)


def _positions(p: Params, t, gamma, xi):
    """Eqs 1-3: Φ2, x_s and the coupler centre G for crank angle ω t and link angle γ."""
    L1, L2 = p.crank_length, p.coupler_length
    phi1 = p.speed * t
    phi2 = jnp.arcsin((L1 * jnp.sin(phi1) + xi * jnp.sin(gamma)) / L2)
    xs = L1 * jnp.cos(phi1) + L2 * jnp.cos(phi2) + xi * jnp.cos(gamma)
    gx = L1 * jnp.cos(phi1) + 0.5 * L2 * jnp.cos(phi2)
    gy = L1 * jnp.sin(phi1) - 0.5 * L2 * jnp.sin(phi2)
    return phi2, xs, gx, gy


def kinematics(p: Params, t: StepArray, gamma_fn, xi) -> Kinematics:
    """Kinematics at times `t` [s] for a link angle γ(t) = `gamma_fn(t)` [rad].

    A `gamma_fn` that ignores its argument is the stationary link (γ̇ = γ̈ = 0) of the SCLA.
    """
    def pos(tt):
        return _positions(p, tt, gamma_fn(tt), xi)

    def pos_vel(tt):
        return jax.jvp(pos, (tt,), (jnp.ones_like(tt),))

    (x, v), (_, a) = jax.jvp(pos_vel, (t,), (jnp.ones_like(t),))
    return Kinematics(phi2=x[0], phi2_d=v[0], phi2_dd=a[0], xs=x[1], xs_dd=a[1], gx_dd=a[2],
                      gy_dd=a[3])


def kinematics_by_hand(p: Params, t: StepArray, gamma, xi, xp=jnp) -> Kinematics:
    """Eqs 4-7 of the paper for a stationary link (γ̇ = γ̈ = 0), written out by hand.
    `xp=numpy` with float parameters evaluates them without JAX (`_plausible`'s peak load,
    before any model is compiled)."""
    L1, L2, w = p.crank_length, p.coupler_length, p.speed
    phi1 = w * t
    phi2 = xp.arcsin((L1 * xp.sin(phi1) + xi * xp.sin(gamma)) / L2)
    c2, s2 = xp.cos(phi2), xp.sin(phi2)
    phi2_d = L1 * w * xp.cos(phi1) / (L2 * c2)  # eq 4
    phi2_dd = (-L1 * w**2 * xp.sin(phi1) + L2 * phi2_d**2 * s2) / (L2 * c2)  # eq 5
    xs = L1 * xp.cos(phi1) + L2 * c2 + xi * xp.cos(gamma)
    xs_dd = (-L1 * w**2 * xp.cos(phi1) - L2 * phi2_dd * s2 - L2 * phi2_d**2 * c2)  # eq 7
    gx_dd = -L1 * w**2 * xp.cos(phi1) - 0.5 * L2 * (phi2_dd * s2 + phi2_d**2 * c2)
    gy_dd = -L1 * w**2 * xp.sin(phi1) - 0.5 * L2 * (phi2_dd * c2 - phi2_d**2 * s2)
    return Kinematics(phi2=phi2, phi2_d=phi2_d, phi2_dd=phi2_dd, xs=xs, xs_dd=xs_dd,
                      gx_dd=gx_dd, gy_dd=gy_dd)


def forces_from_kinematics(p: Params, k: Kinematics, xp=jnp):
    """Eqs 8-10 (d'Alembert), signs fixed as in design.md §1. Returns (F_Cx, F_Cy) [N].
    (`xp`: as for `kinematics_by_hand`.)"""
    L2, m2, m3 = p.coupler_length, p.coupler_mass, p.slider_mass
    spring = -p.spring_rate * (k.xs - p.spring_free_position)
    fx = spring - m3 * k.xs_dd  # slider: the coupler pushes it with -F_C
    dx, dy = L2 * xp.cos(k.phi2), -L2 * xp.sin(k.phi2)  # r_DB
    inertial_x = -m2 * k.gx_dd
    inertial_y = -m2 * k.gy_dd - m2 * p.gravity
    moment_g = 0.5 * (dx * inertial_y - dy * inertial_x)  # r_GB × (-m2 a_G - m2 g ŷ)
    psi_dd = -k.phi2_dd  # ψ = -Φ2 is the coupler's counter-clockwise angle
    inertia = m2 * L2**2 / 12.0  # uniform bar about its centre (our assumption, design.md §1)
    # r_DB × F_C + moment_g - I_G ψ̈ = 0, solved for F_Cy; dx = L2 cos Φ2 > 0 since L1 < L2.
    fy = (dy * fx - moment_g + inertia * psi_dd) / dx
    return fx, fy


def _safe_atan2(y, x):
    # atan2 has an undefined gradient at the origin (a step with zero load): guard it.
    zero = (x == 0.0) & (y == 0.0)
    return jnp.where(zero, 0.0, jnp.arctan2(jnp.where(zero, 1.0, y), jnp.where(zero, 1.0, x)))


def _wrap(a):
    return jnp.mod(a + jnp.pi, 2 * jnp.pi) - jnp.pi


def crank_slider_forces(p: Params, t: StepArray, algorithm: str = "scla", scla_passes: int = 2,
                        gamma0: float = 0.0) -> JointForce:
    """Joint reaction force at times `t` [s] by the chosen algorithm (design.md §1).

    - `ideal`: no clearance (ξ = 0).
    - `scla`: stationary clearance link from a constant γ0, `scla_passes` passes.
    - `li`: γ(t) from the ideal joint's force angle, with its rates γ̇, γ̈ (eqs 11-13, here by
      autodiff), then one pass of the clearance-link model (ref. [8]).
    """
    xi = p.clearance
    if algorithm == "ideal":
        kin = kinematics(p, t, lambda tt: jnp.zeros_like(tt), 0.0)
        fx, fy = forces_from_kinematics(p, kin)
        return JointForce(fx, fy, kin, jnp.zeros_like(t))
    if algorithm == "li":
        def gamma_ideal(tt):
            kin0 = kinematics(p, tt, lambda s: jnp.zeros_like(s), 0.0)
            fx0, fy0 = forces_from_kinematics(p, kin0)
            return _safe_atan2(fy0, fx0)

        kin = kinematics(p, t, gamma_ideal, xi)
        fx, fy = forces_from_kinematics(p, kin)
        return JointForce(fx, fy, kin, jnp.zeros_like(t))
    if algorithm != "scla":
        raise ValueError(f"unknown algorithm {algorithm!r}")

    def one_pass(gamma):
        kin = kinematics(p, t, lambda tt: gamma + 0.0 * tt, xi)
        fx, fy = forces_from_kinematics(p, kin)
        return kin, fx, fy, _safe_atan2(fy, fx)

    def body(_, c):
        gamma = c[3]
        kin, fx, fy, new = one_pass(gamma)
        return kin, fx, fy, new, jnp.abs(_wrap(new - gamma))

    # The passes as a loop, not unrolled: every compiled program holds the load history, and
    # `scla_passes` may be set up to 100 (each unrolled pass added its kinematics to it).
    gamma = jnp.full_like(t, gamma0)
    zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype),
                         jax.eval_shape(one_pass, gamma)[:3])
    # every carry ready for the parameters' tangents: one trace of the pass under forward
    # mode, not two (`_core.tangents`)
    init = tangents.ready((*zeros, gamma, jnp.zeros_like(t)), tangents.anchor_of((p, t)))
    kin, fx, fy, _, change = lax.fori_loop(0, scla_passes, body, init)
    return JointForce(fx, fy, kin, change)
