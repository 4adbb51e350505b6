"""Winkler elastic foundation contact of a pin in a (worn) bore (DESIGN §3, paper §2, §4.1).

The unsymmetric model solves the vector equilibrium Σ_j p_j A_j n_j = W for the pin offset e.
Without friction it is the gradient of the convex piecewise-quadratic potential
Σ ½ k_j A_j max(e·n_j - g_j, 0)² - W·e, so a semi-smooth Newton method started outside the
solution converges; we start from the exact 1-D solution along the load (monotone Newton from
the right on a convex piecewise-linear function) and globalise the 2-D Newton by halving the
step until the residual norm falls.

Gradients: the solve runs on `stop_gradient` inputs and one Newton correction
e = e* - J⁻¹ R(e*; θ) is applied with J held fixed. At a converged e* this is the implicit
function theorem, dE/dθ = -J⁻¹ ∂R/∂θ: exact first derivatives in forward and reverse mode,
with no backpropagation through the Newton iterations.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ._custom_types import Array, Float, NodeArray, StepArray, StepNodeArray

sg = lax.stop_gradient


class ContactSolution(eqx.Module):
    """Pressure field and pin offsets for every step of a cycle."""

    pressure: StepNodeArray  # p_ij [Pa]
    offset: Float[Array, "steps 2"]  # e_i, bushing frame [m]
    residual: StepArray  # |Σ p A m - W| / |W| (0 where W = 0)
    iterations: Array  # Newton iterations used (max over steps)


def equivalent_modulus(E, nu):
    """E_w = (1-ν)E / ((1+ν)(1-2ν)) [Pa] (eq 15)."""
    return (1 - nu) * E / ((1 + nu) * (1 - 2 * nu))


def stiffness_per_area(h: NodeArray, p, double_layer: bool) -> NodeArray:
    """Foundation stiffness k_j [Pa/m] of the worn layer (eq 14; series springs for §4.1).

    The worn layer is thinner (L - h_j), hence stiffer. Depths at or past L are clamped to a
    sliver here; the wear loop reports them as worn through.
    """
    thick = jnp.maximum(p.layer_thickness - h, 1e-6 * p.layer_thickness)
    compliance = thick / equivalent_modulus(p.layer_modulus, p.layer_poisson)
    if double_layer:
        compliance = compliance + p.backing_thickness / equivalent_modulus(
            p.backing_modulus, p.backing_poisson)
    return 1.0 / compliance


def node_angles(nodes: int) -> NodeArray:
    return 2 * jnp.pi * jnp.arange(nodes) / nodes


def interp_periodic(h: NodeArray, angle):
    """Periodic linear interpolation of node values at `angle` [rad]."""
    n = h.shape[-1]
    x = jnp.mod(angle / (2 * jnp.pi) * n, n)
    i0 = jnp.floor(x).astype(jnp.int32) % n
    w = x - jnp.floor(x)
    return (1 - w) * h[i0] + w * h[(i0 + 1) % n]


def _newton_1d(load, cosj, weight, g, kA, iters):
    """Solve Σ_j kA_j max(s cos_j - g_j, 0) w_j = |W| for s (per step), from the right.

    `cosj`, `weight`: (steps, nodes); `g`, `kA`: (steps|1, nodes). Monotone and finite for a
    convex piecewise-linear left side; returns s (steps,).
    """
    jstar = jnp.argmax(cosj, axis=1)
    pick = lambda a: jnp.take_along_axis(jnp.broadcast_to(a, cosj.shape), jstar[:, None], 1)[:, 0]
    c_star, g_star, k_star, w_star = pick(cosj), pick(g), pick(kA), pick(weight)
    s = g_star / c_star + load / (k_star * c_star * jnp.maximum(w_star, 0.5 * c_star))

    def f_and_df(s):
        d = s[:, None] * cosj - g
        act = d > 0
        f = jnp.sum(jnp.where(act, kA * d * weight, 0.0), axis=1) - load
        df = jnp.sum(jnp.where(act, kA * cosj * weight, 0.0), axis=1)
        return f, df

    def cond(state):
        i, _, done = state
        return (i < iters) & ~jnp.all(done)

    def body(state):
        i, s, done = state
        f, df = f_and_df(s)
        ok = df > 0
        s_new = jnp.where(ok & ~done, s - f / jnp.where(ok, df, 1.0), s)
        done = done | (jnp.abs(f) <= 1e-13 * jnp.maximum(load, 1e-300)) | (load == 0)
        return i + 1, s_new, done

    _, s, _ = lax.while_loop(cond, body, (0, s, load == 0))
    return s


def _residual_2d(e, nx, ny, mx, my, g, kA, W):
    d = e[:, 0:1] * nx + e[:, 1:2] * ny - g
    q = jnp.where(d > 0, kA * d, 0.0)  # p_j A_j
    r = jnp.stack([jnp.sum(q * mx, 1), jnp.sum(q * my, 1)], axis=1) - W
    return r, d


def _jacobian_2d(d, nx, ny, mx, my, kA):
    a = jnp.where(d > 0, kA, 0.0)
    jxx = jnp.sum(a * mx * nx, 1)
    jxy = jnp.sum(a * mx * ny, 1)
    jyx = jnp.sum(a * my * nx, 1)
    jyy = jnp.sum(a * my * ny, 1)
    return jxx, jxy, jyx, jyy


def _solve2(j, r, ridge=0.0):
    jxx, jxy, jyx, jyy = j
    # With fewer than two active nodes J is singular: the ridge keeps the step finite (the
    # iteration then relies on the step cap and line search). It changes steps, never the
    # fixed point; the implicit-gradient solve uses a negligible one.
    ridge = ridge + 1e-12 * (jnp.abs(jxx) + jnp.abs(jyy)) + 1e-300
    jxx, jyy = jxx + ridge, jyy + ridge
    det = jxx * jyy - jxy * jyx
    dx = (jyy * r[:, 0] - jxy * r[:, 1]) / det
    dy = (-jyx * r[:, 0] + jxx * r[:, 1]) / det
    return jnp.stack([dx, dy], axis=1)


def _merit(e, r, d, kA, W, potential):
    if potential:  # Σ ½ kA max(d,0)² - W·e: convex, and Newton steps descend on it
        return 0.5 * jnp.sum(jnp.where(d > 0, kA * d * d, 0.0), 1) - jnp.sum(W * e, 1)
    return 0.5 * jnp.sum(r * r, 1)


def _newton_2d(e0, nx, ny, mx, my, g, kA, W, wnorm, iters, tol, potential, cap):
    """Damped semi-smooth Newton for R(e) = 0, vectorised over steps.

    Each loop iteration evaluates one trial point per step: accepted if the merit falls
    (Armijo), otherwise the step is halved. Steps that have converged are frozen. Step
    lengths are capped at `cap` [m] (a fraction of the clearance): the offset never needs
    to move further than that in one go, and a singular J cannot throw the iterate away.
    """
    ridge = 1e-9 * jnp.max(kA)

    def newton_step(d, r):
        st = -_solve2(_jacobian_2d(d, nx, ny, mx, my, kA), r, ridge)
        st = jnp.where(jnp.isfinite(st), st, 0.0)
        norm = jnp.linalg.norm(st, axis=1, keepdims=True)
        return st * jnp.minimum(1.0, cap / jnp.maximum(norm, 1e-300))

    r0, d0 = _residual_2d(e0, nx, ny, mx, my, g, kA, W)
    step0 = newton_step(d0, r0)
    m0 = _merit(e0, r0, d0, kA, W, potential)
    scale = jnp.maximum(wnorm, 1e-300)

    def slope(r, step):
        return jnp.sum(r * step, 1) if potential else -jnp.sum(r * r, 1)

    def cond(state):
        i, _, r, _, _, _ = state
        return (i < iters) & jnp.any(jnp.linalg.norm(r, axis=1) > tol * scale)

    def body(state):
        i, e, r, m, step, alpha = state
        trial = e + alpha[:, None] * step
        rt, dt = _residual_2d(trial, nx, ny, mx, my, g, kA, W)
        mt = _merit(trial, rt, dt, kA, W, potential)
        active = jnp.linalg.norm(r, axis=1) > tol * scale
        decrease = mt <= m + 1e-4 * alpha * slope(r, step)
        # Round-off can hide the decrease of a near-converged step; accept a smaller residual.
        better = jnp.linalg.norm(rt, axis=1) < 0.5 * jnp.linalg.norm(r, axis=1)
        accept = active & (decrease | better)
        new_step = newton_step(dt, rt)
        e = jnp.where(accept[:, None], trial, e)
        r = jnp.where(accept[:, None], rt, r)
        m = jnp.where(accept, mt, m)
        step = jnp.where(accept[:, None], new_step, step)
        alpha = jnp.where(accept, 1.0, jnp.where(active, 0.5 * alpha, alpha))
        return i + 1, e, r, m, step, alpha

    alpha0 = jnp.ones_like(m0)
    i, e, r, _, _, _ = lax.while_loop(cond, body, (0, e0, r0, m0, step0, alpha0))
    return e, i


def _solve_nodes(load, angle, nx, ny, g, k, area, contact, iterations, tol, start):
    """Contact on the nodes with normals (`nx`, `ny`) (steps|1, n), gaps `g` and stiffness
    `k` on the same shape. Returns pressure on those nodes, offsets, residuals, iterations."""
    ux, uy = jnp.cos(angle)[:, None], jnp.sin(angle)[:, None]
    cosj = nx * ux + ny * uy  # n_j · û_W
    mx, my, weight = nx, ny, cosj
    W = jnp.stack([load * jnp.cos(angle), load * jnp.sin(angle)], axis=1)
    kA = k * area

    if contact == "symmetric":
        s_star = sg(_newton_1d(sg(load), sg(cosj), sg(weight), sg(g), sg(kA), iterations))
        d = s_star[:, None] * cosj - g
        act = sg(d > 0)
        f = jnp.sum(jnp.where(act, kA * d * weight, 0.0), 1) - load
        df = sg(jnp.sum(jnp.where(act, kA * cosj * weight, 0.0), 1))
        s = s_star - f / jnp.where(df > 0, df, 1.0)
        delta = s[:, None] * cosj - g
        pressure = jnp.where(delta > 0, k * delta, 0.0)
        e = jnp.stack([s * jnp.cos(angle), s * jnp.sin(angle)], axis=1)
        res_vec = jnp.sum(pressure * area * weight, 1) - load
        resid = jnp.abs(res_vec) / jnp.maximum(load, 1e-300)
        return pressure, e, jnp.where(load > 0, resid, 0.0), jnp.asarray(0)

    cap = 0.25 * sg(jnp.min(g))
    newton = lambda e_init, its: _newton_2d(
        e_init, nx, ny, sg(mx), sg(my), sg(g), sg(kA), sg(W), sg(load), its, tol, True, cap)

    def cold():
        s0 = _newton_1d(sg(load), sg(cosj), sg(weight), sg(g), sg(kA), iterations)
        return jnp.stack([s0 * sg(ux[:, 0]), s0 * sg(uy[:, 0])], axis=1)

    if start is None:
        e_star, its = newton(cold(), iterations)
    else:
        # Warm start, moved out along the load until it touches the (further worn) bore.
        e0 = sg(start)
        gap = jnp.max(e0[:, 0:1] * nx + e0[:, 1:2] * ny - sg(g), axis=1)
        e0 = e0 - jnp.minimum(gap, 0.0)[:, None] * jnp.concatenate([sg(ux), sg(uy)], 1)
        e_star, its = newton(e0, min(iterations, 12))
        r_w, _ = _residual_2d(e_star, nx, ny, sg(mx), sg(my), sg(g), sg(kA), sg(W))
        bad = jnp.linalg.norm(r_w, axis=1) > tol * jnp.maximum(sg(load), 1e-300)
        # Rare: the warm start failed somewhere; redo those steps from the cold start.
        e_star, its = lax.cond(
            jnp.any(bad),
            lambda: (lambda ec: (jnp.where(bad[:, None], ec[0], e_star), its + ec[1]))(
                newton(cold(), iterations)),
            lambda: (e_star, its))
    e_star = sg(e_star)
    r, d = _residual_2d(e_star, nx, ny, mx, my, g, kA, W)
    jac = jax.tree_util.tree_map(sg, _jacobian_2d(sg(d), nx, ny, sg(mx), sg(my), sg(kA)))
    e = e_star - _solve2(jac, r)
    delta = e[:, 0:1] * nx + e[:, 1:2] * ny - g
    pressure = jnp.where(delta > 0, k * delta, 0.0)
    q = pressure * area
    res = jnp.stack([jnp.sum(q * mx, 1), jnp.sum(q * my, 1)], axis=1) - W
    resid = jnp.linalg.norm(res, axis=1) / jnp.maximum(load, 1e-300)
    return pressure, e, jnp.where(load > 0, resid, 0.0), its


def solve_contact(load: StepArray, angle: StepArray, h: NodeArray, clearance, k: NodeArray,
                  area, *, contact: str = "unsymmetric", friction=None,
                  iterations: int = 40, tol: float = 1e-12, start=None) -> ContactSolution:
    """Contact pressure for every step of a cycle on a frozen bore profile (DESIGN §3).

    **Arguments:**
    - `load`, `angle`: |W| [N] and θ_W [rad], shape (steps,).
    - `h`: wear depth [m], (nodes,). `clearance`: c [m]. `k`: stiffness [Pa/m], (nodes,).
    - `area`: A_j [m²] (scalar). `contact`: `"unsymmetric"` or `"symmetric"`.
    - `friction`: None, or μ·s per step (steps,): Coulomb friction adds μ s t_j to each
      node's force direction (DESIGN §5). Since n_j + μ s t_j = √(1+μ²) R(β) n_j with
      tan β = μ s, the equation Σ p_j A_j (n_j + μ s t_j) = W is the frictionless one for
      the load R(-β) W / √(1+μ²): friction is solved exactly as a rotated, reduced load.
    - `start`: optional warm start for the offsets (steps, 2) [m], e.g. the previous wear
      update's solution; by default the exact 1-D solution along the load.

    **Returns:** a `ContactSolution`; `residual` is the relative force residual, which the
    caller checks (never assumed).
    """
    if friction is not None:
        angle = angle - jnp.arctan(friction)
        load = load / jnp.sqrt(1 + friction**2)
    nodes = h.shape[0]
    # Normals as host constants: computed inside the trace, XLA re-evaluates the cosines in
    # every fused Newton pass (measured: 10x slower).
    th_np = 2 * np.pi * np.arange(nodes) / nodes
    cos_all, sin_all = jnp.asarray(np.cos(th_np))[None, :], jnp.asarray(np.sin(th_np))[None, :]
    if contact == "symmetric":
        # Traditional Winkler: a circle through the loaded node (gap and stiffness of the
        # bore at θ_W for every node), pin displaced along the load only.
        g_all = jnp.broadcast_to(clearance + interp_periodic(h, angle)[:, None],
                                 (angle.shape[0], nodes))
        k_all = jnp.broadcast_to(interp_periodic(k, angle)[:, None], (angle.shape[0], nodes))
    else:
        g_all = jnp.broadcast_to((clearance + h)[None, :], (1, nodes))
        k_all = k[None, :]
    p, e, r, it = _solve_nodes(load, angle, cos_all, sin_all, g_all, k_all, area, contact,
                               iterations, tol, start)
    return ContactSolution(p, e, r, it)
