"""Winkler elastic foundation contact of a pin in a (worn) bore (design.md §3, paper §2, §4.1).

The unsymmetric model solves the vector equilibrium Σ_j p_j A_j n_j = W for the pin offset e.
It is the gradient of the convex piecewise-quadratic potential
Σ_j ½ k_j A_j max(e·n_j - g_j, 0)² - W·e, so a semi-smooth Newton method with an Armijo line
search on that potential converges from any start that touches the bore. The cold start is
the exact 1-D solution along the load (monotone Newton from the right on a convex
piecewise-linear function); the wear loop warm-starts from the previous update.

Coulomb friction (design.md §5) needs no solver of its own: n_j + μ s t_j = √(1+μ²) R(β) n_j
with tan β = μ s, so Σ p_j A_j (n_j + μ s t_j) = W is the frictionless problem for the load
R(-β) W / √(1+μ²).

Gradients: the solve runs on `stop_gradient` inputs and one Newton correction
e = e* - J⁻¹ R(e*; θ) is applied with J held fixed. At a converged e* this is the implicit
function theorem, de/dθ = -J⁻¹ ∂R/∂θ: exact first derivatives in forward and reverse mode,
with no backpropagation through the Newton iterations.
R(e*; θ)'s value is the one Newton computed (`_residual_at`, a custom JVP supplies its
derivative): the forward pass spends no sweep over the grid on it.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.ad_checkpoint import checkpoint_name
from jax.custom_batching import custom_vmap

from jaxwear._core import pytree
from jaxwear._core.batching import cond_any, in_chunks
from jaxwear._core.periodic import interp_periodic
from jaxwear._core.types import Array, Float, NodeArray, StepArray, StepNodeArray
from jaxwear._physics.remat import NEWTON

sg = lax.stop_gradient


class ContactSolution(pytree.Struct):
    """Pressure field and pin offsets for every step of a cycle.

    - `pressure` (steps, nodes): p_ij [Pa];
    - `offset` (steps, 2): the pin centre's offset e_i in the bushing frame [m];
    - `residual` (steps,): relative force residual |Σ_j p_j A_j n_j - W| / |W| (0 where
      W = 0; below 1e-9 when solved);
    - `iterations`: Newton iterations used (the largest over the steps).
    """

    pressure: StepNodeArray  # p_ij [Pa]
    offset: Float[Array, "steps 2"]  # e_i, bushing frame [m]
    residual: StepArray  # relative force residual |Σ p A n - W| / |W| (0 where W = 0)
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
    """θ_j = 2πj/N [rad]."""
    return 2 * jnp.pi * jnp.arange(nodes) / nodes


def _newton_1d(load, cosj, g, kA, iters):
    """Solve Σ_j kA_j max(s cos_j - g_j, 0) cos_j = |W| for s ≥ 0 (per step), from the right.

    `cosj` (steps, nodes); `g`, `kA` broadcastable to it. The left side is convex,
    piecewise linear and increasing in s, so Newton from a point where it exceeds |W| moves
    monotonically down and stops exactly on the root's linear piece.
    """
    jstar = jnp.argmax(cosj, axis=1)
    c_star, g_star, k_star = (_at_node(a, jstar, cosj.shape[1]) for a in (cosj, g, kA))
    s = g_star / c_star + load / (k_star * c_star * c_star)  # loaded node alone carries |W|

    def cond(state):
        i, _, done = state
        return (i < iters) & ~jnp.all(done)

    def body(state):
        i, s, done = state
        d = s[:, None] * cosj - g
        act = d > 0
        f = jnp.sum(jnp.where(act, kA * d * cosj, 0.0), axis=1) - load
        df = jnp.sum(jnp.where(act, kA * cosj * cosj, 0.0), axis=1)
        ok = df > 0
        s_new = jnp.where(ok & ~done, s - f / jnp.where(ok, df, 1.0), s)
        # A step that did not move is at its fixed point: every later iteration returns
        # the same s. Round-off can hold |f| just above the tolerance there (1.28e-13 |W|
        # on one step of a rig sweep's point, 120 x 120), and the loop ran on to its 40
        # iterations for nothing: batched, every lane with it (issue 50).
        done = done | (jnp.abs(f) <= 1e-13 * jnp.maximum(load, 1e-300)) | (s_new == s)
        return i + 1, s_new, done

    _, s, _ = lax.while_loop(cond, body, (0, s, load == 0))
    return s


def _moments(ex, ey, nx, ny, g, kA, wx, wy):
    """R(e) = Σ kA max(d,0) n - W, the potential and its Hessian from the penetrations
    d = e·n - g, in components: (rx, ry), potential, (hxx, hxy, hyy), each (steps,).

    All six sums over the nodes are one variadic reduction: one pass that computes d once
    and carries six sums. XLA:CPU runs a plain row sum as its own scalar loop, and a
    stacked sum writes six steps x nodes arrays first (measured, 360 x 360: seven sums
    0.60 ms, stacked 0.21 ms, variadic 0.077 ms)."""
    d = ex[:, None] * nx + ey[:, None] * ny - g
    a = jnp.where(d > 0, kA, 0.0)
    q = a * d  # p_j A_j
    terms = [jnp.broadcast_to(t, d.shape)
             for t in (q * nx, q * ny, q * d, a * nx * nx, a * nx * ny, a * ny * ny)]
    rx, ry, qd, hxx, hxy, hyy = lax.reduce(
        terms, [jnp.zeros((), d.dtype)] * 6,
        lambda x, y: [xi + yi for xi, yi in zip(x, y)], (1,))
    return (rx - wx, ry - wy), 0.5 * qd - (wx * ex + wy * ey), (hxx, hxy, hyy)


@jax.custom_jvp
def _residual_at(e_star, r_star, nx, ny, g, kA, W):
    """R(e*; g, kA, W) at Newton's answer e*, whose value `r_star` Newton computed: the
    forward pass reuses it (one sweep over steps x nodes less per solve, a sixth of a warm
    solve), derivatives come from R's own JVP at e*."""
    return r_star


@_residual_at.defjvp
def _residual_at_jvp(primals, tangents):
    e_star, r_star, nx, ny, g, kA, W = primals
    _, _, _, _, tg, tk, tw = tangents
    # dR = Σ_j [d_j > 0] (dkA_j d_j - kA_j dg_j) n_j - dW at fixed e*, with plain sums
    # (transposable for reverse mode, which the variadic reduction of `_moments` is not).
    d = e_star[:, 0:1] * nx + e_star[:, 1:2] * ny - g
    dq = jnp.where(d > 0, tk * d - kA * tg, 0.0)
    return r_star, jnp.stack([jnp.sum(dq * nx, 1), jnp.sum(dq * ny, 1)], axis=1) - tw


def _facing_gap(e, angle, nx, ny, g):
    """e·n_j - g_j (steps,) at the node j nearest the load direction of each step."""
    nodes = nx.shape[-1]
    j = jnp.round(angle * nodes / (2 * jnp.pi)).astype(jnp.int32) % nodes
    at = lambda a: _at_node(a, j, nodes)  # noqa: E731
    return e[:, 0] * at(nx) + e[:, 1] * at(ny) - at(g)


def _at_node(a, j, nodes):
    """Each step's value at its node j (steps,) of `a`, broadcastable to (steps, nodes)."""
    a = jnp.broadcast_to(a, (j.shape[0], nodes))
    return jnp.take_along_axis(a, j[:, None], 1)[:, 0]


def _solve2(hess, rx, ry, ridge=0.0):
    """Solve H x = r for symmetric 2x2 H per step, in components: (x, y), each (steps,)."""
    hxx, hxy, hyy = hess
    # With fewer than two active nodes H is singular: the ridge keeps the step finite (the
    # step cap and line search do the rest). It changes steps, never the fixed point; the
    # implicit-gradient solve uses only a negligible one.
    ridge = ridge + 1e-12 * (hxx + hyy) + 1e-300
    hxx, hyy = hxx + ridge, hyy + ridge
    det = hxx * hyy - hxy * hxy
    # No active node at all (zero load): no step, and no 0/0 in the gradient either.
    ok = det > 0
    det = jnp.where(ok, det, 1.0)
    return (jnp.where(ok, (hyy * rx - hxy * ry) / det, 0.0),
            jnp.where(ok, (-hxy * rx + hxx * ry) / det, 0.0))


def _newton_2d(e0, nx, ny, g, kA, W, wnorm, iters, tol, cap):
    """Damped semi-smooth Newton for R(e) = 0, vectorised over steps.

    Each iteration evaluates one trial point per step: accepted if the potential falls
    (Armijo) or the residual halves, otherwise the step is halved. Converged steps are
    frozen. Steps are capped at `cap` [m]: a singular H cannot throw the iterate away.
    Returns the offsets, their residuals and Hessians, and the number of iterations.

    The iteration works on components ((steps,) arrays, not (steps, 2)), its state packed
    in one array: norms and dots are elementwise, not reductions over a last axis of two,
    and the update is one select (measured on the boom's 25 h at 360 x 360: 1.21-1.26 s
    against 1.22-1.28 s, within the host's noise; the sums over the nodes are the cost).

    Two phases: while more than a quarter of the steps are unconverged, every step's
    trial point is evaluated (a pass over steps x nodes); then the unconverged steps
    alone, gathered into a quarter as many rows (the nodes' data is the same for every
    step, so only the steps' offsets and loads move). On the boom's 25 h (360 x 360) a
    warm solve leaves a median of 210 of 360 steps unconverged after its first iteration
    and 24 after its second, with a tail of iterations that fix a contact arc's edge node
    on a few steps. Each step's iterates are the same either way: its sums over the nodes
    are the same row reduction.

    Batched (`jax.vmap`: a sweep's lanes) the iteration pools every lane's steps
    (`_newton_pooled`): a plain vmap ran each Newton loop until the slowest lane converged,
    its gathered quarter per lane (issue 50).
    """
    f = custom_vmap(functools.partial(_newton_lane, tol=tol))
    f.def_vmap(functools.partial(_newton_pooled, tol=tol))
    return f(e0, nx, ny, g, kA, W, wnorm, jnp.asarray(iters), cap)


def _newton_step(hess, r, ridge, cap):
    """The capped Newton step (sx, sy) from Hessian `hess` and residual `r` (components)."""
    sx, sy = _solve2(hess, *r, ridge)
    sx, sy = -sx, -sy
    sx = jnp.where(jnp.isfinite(sx), sx, 0.0)
    sy = jnp.where(jnp.isfinite(sy), sy, 0.0)
    scale = jnp.minimum(1.0, cap / jnp.maximum(jnp.sqrt(sx * sx + sy * sy), 1e-300))
    return sx * scale, sy * scale


def _norm(x, y):
    return jnp.sqrt(x * x + y * y)


def _pack(e, r, m, step, alpha, hess):
    """The iteration's state, one (steps, 11) array (ex, ey, rx, ry, potential, sx, sy,
    alpha, hxx, hxy, hyy): its update is one select, not one per component."""
    return jnp.stack([*e, *r, m, *step, alpha, *hess], axis=1)


def _unconverged(s, lim):
    return _norm(s[:, 2], s[:, 3]) > lim


def _newton_start(e0, nx, ny, g, kA, W, ridge, cap):
    """The state (steps, 11) at the offsets `e0` (steps, 2)."""
    ex0, ey0 = e0[:, 0], e0[:, 1]
    r0, m0, h0 = _moments(ex0, ey0, nx, ny, g, kA, W[:, 0], W[:, 1])
    return _pack((ex0, ey0), r0, m0, _newton_step(h0, r0, ridge, cap), jnp.ones_like(m0), h0)


def _newton_iterate(s, nx, ny, g, kA, wx, wy, lim, ridge, cap):
    """One damped Newton iteration of the rows of state `s` (rows, 11) whose loads are
    (wx, wy) and tolerances `lim` (each (rows,)); `g`, `kA` (1 or rows, nodes); `ridge`,
    `cap` scalars or (rows,)."""
    ex, ey, rx, ry, m, sx, sy, alpha = (s[:, k] for k in range(8))
    tx, ty = ex + alpha * sx, ey + alpha * sy
    rt, mt, ht = _moments(tx, ty, nx, ny, g, kA, wx, wy)
    rn = _norm(rx, ry)
    active = rn > lim
    decrease = mt <= m + 1e-4 * alpha * (rx * sx + ry * sy)
    # Round-off hides the decrease of a near-converged step; accept a smaller residual.
    accept = active & (decrease | (_norm(*rt) < 0.5 * rn))
    cand = _pack((tx, ty), rt, mt, _newton_step(ht, rt, ridge, cap), jnp.ones_like(mt), ht)
    s = s.at[:, 7].set(jnp.where(active, 0.5 * alpha, alpha))
    return jnp.where(accept[:, None], cand, s)


def _quarter(steps, *node_data):
    """The rows of `_newton_2d`'s second phase: a quarter of the steps where there are 64 or
    more and the nodes' data is shared by every step (gathering rows needs it), else all."""
    return steps // 4 if steps >= 64 and all(a.shape[0] == 1 for a in node_data) else steps


def _newton_lane(e0, nx, ny, g, kA, W, wnorm, iters, cap, *, tol):
    """`_newton_2d` of one joint (unbatched)."""
    ridge = 1e-9 * jnp.max(kA)
    steps = e0.shape[0]
    limit = tol * jnp.maximum(wnorm, 1e-300)
    wx, wy = W[:, 0], W[:, 1]

    def iteration(wx, wy, lim):
        def body(c):
            i, s = c
            return i + 1, _newton_iterate(s, nx, ny, g, kA, wx, wy, lim, ridge, cap)
        return body

    state0 = _newton_start(e0, nx, ny, g, kA, W, ridge, cap)
    rows = _quarter(steps, nx, ny, g, kA)

    def full_cond(c):
        i, s = c
        todo = _unconverged(s, limit)
        return (i < iters) & (jnp.sum(todo) > rows if rows < steps else jnp.any(todo))

    i, s = lax.while_loop(full_cond, iteration(wx, wy, limit), (0, state0))
    if rows < steps:
        # At most `rows` steps left: gather them (padded with repeats of the first, whose
        # iterates are the same, so that the scatter back writes one value per step).
        todo = _unconverged(s, limit)
        idx = jnp.nonzero(todo, size=rows, fill_value=0)[0]
        idx = jnp.where(jnp.arange(rows) < jnp.sum(todo), idx, idx[0])
        lim = limit[idx]

        def few_cond(c):
            i, sub = c
            return (i < iters) & jnp.any(_unconverged(sub, lim))

        i, sub = lax.while_loop(few_cond, iteration(wx[idx], wy[idx], lim), (i, s[idx]))
        s = s.at[idx].set(sub)
    return s[:, 0:2], s[:, 2:4], (s[:, 8], s[:, 9], s[:, 10]), i


def _newton_pooled(axis_size, in_batched, e0, nx, ny, g, kA, W, wnorm, iters, cap, *, tol):
    """`_newton_2d` of a batch of `axis_size` lanes (the `custom_vmap` rule): the lanes'
    steps iterate as one pool. Phase one runs every lane's steps while more than a quarter
    of all the steps are unconverged; phase two gathers the unconverged steps of every lane
    into a quarter as many rows (each row with its lane's node data). Under a plain vmap
    each phase ran until its slowest lane was done, with a quarter of the steps per lane:
    lanes that need 2 to 5 iterations (a 16-lane rig sweep, 120 x 120) all ran 5.

    Every step's iterates are those of an unbatched solve (one loop counter for all: every
    step starts at iteration 0; a converged step is frozen), and each lane's iteration count
    is the one it takes alone: the iteration after which its last step converged."""
    B = axis_size
    e0_b, nx_b, ny_b, g_b, kA_b, W_b, wn_b, it_b, cap_b = in_batched
    if nx_b or ny_b or it_b or not _quarter(e0.shape[-2], nx, ny, g[0] if g_b else g,
                                            kA[0] if kA_b else kA) < e0.shape[-2]:
        # no second phase to pool (few steps, or node data that differs by step): per lane
        axes = [0 if b else None for b in in_batched]
        out = jax.vmap(functools.partial(_newton_lane, tol=tol), in_axes=axes,
                       axis_size=B)(e0, nx, ny, g, kA, W, wnorm, iters, cap)
        return out, jax.tree.map(lambda _: True, out)

    def lanes(x, batched):
        return x if batched else jnp.broadcast_to(x, (B,) + jnp.shape(x))

    e0, g, kA, W, wnorm, cap = (lanes(x, b) for x, b in ((e0, e0_b), (g, g_b), (kA, kA_b),
                                                         (W, W_b), (wnorm, wn_b), (cap, cap_b)))
    steps = e0.shape[1]
    ridge = 1e-9 * jnp.max(kA, axis=(1, 2))  # (B,): each lane's own
    limit = tol * jnp.maximum(wnorm, 1e-300)  # (B, steps)
    each = functools.partial(jax.vmap, axis_size=B)
    state0 = each(_newton_start, in_axes=(0, None, None, 0, 0, 0, 0, 0))(
        e0, nx, ny, g, kA, W, ridge, cap)
    pool = B * _quarter(steps, nx, ny, g[0], kA[0])
    lane_todo = lambda s: jnp.any(each(_unconverged)(s, limit), axis=1)  # noqa: E731
    # the iteration after which each lane's last step converged (-1: not yet)
    done0 = jnp.where(lane_todo(state0), -1, 0)

    def full_cond(c):
        i, s, _ = c
        return (i < iters) & (jnp.sum(each(_unconverged)(s, limit)) > pool)

    def full_body(c):
        i, s, done = c
        s = each(_newton_iterate, in_axes=(0, None, None, 0, 0, 0, 0, 0, 0, 0))(
            s, nx, ny, g, kA, W[..., 0], W[..., 1], limit, ridge, cap)
        return i + 1, s, jnp.where((done < 0) & ~lane_todo(s), i + 1, done)

    i, s, done = lax.while_loop(full_cond, full_body, (0, state0, done0))
    # the unconverged steps of all lanes, padded with repeats of the first
    flat = s.reshape(B * steps, -1)
    todo = _unconverged(flat, limit.reshape(-1))
    idx = jnp.nonzero(todo, size=pool, fill_value=0)[0]
    idx = jnp.where(jnp.arange(pool) < jnp.sum(todo), idx, idx[0])
    lane = idx // steps
    lim = limit.reshape(-1)[idx]
    wx, wy = W[..., 0].reshape(-1)[idx], W[..., 1].reshape(-1)[idx]
    g_rows, kA_rows = g[lane, 0], kA[lane, 0]  # (pool, nodes)
    ridge_rows, cap_rows = ridge[lane], cap[lane]

    def few_cond(c):
        i, sub, _ = c
        return (i < iters) & jnp.any(_unconverged(sub, lim))

    def few_body(c):
        i, sub, done = c
        sub = _newton_iterate(sub, nx, ny, g_rows, kA_rows, wx, wy, lim, ridge_rows, cap_rows)
        left = jnp.zeros(B, bool).at[lane].max(_unconverged(sub, lim))
        return i + 1, sub, jnp.where((done < 0) & ~left, i + 1, done)

    i, sub, done = lax.while_loop(few_cond, few_body, (i, flat[idx], done))
    s = flat.at[idx].set(sub).reshape(B, steps, -1)
    its = jnp.where(done < 0, i, done)
    out = (s[..., 0:2], s[..., 2:4], (s[..., 8], s[..., 9], s[..., 10]), its)
    return out, jax.tree.map(lambda _: True, out)


def _pair_start(angle, nx, ny, g, kA, W):
    """Offsets (steps, 2) [m] that put the load on the two nodes either side of its
    direction alone: Σ_{j in pair} kA_j (e·n_j - g_j) n_j = W, a 2x2 linear system (the
    answer wherever no other node touches, e.g. under a light load)."""
    nodes = nx.shape[-1]
    j0 = jnp.floor(jnp.mod(angle, 2 * jnp.pi) * nodes / (2 * jnp.pi)).astype(jnp.int32) % nodes
    j1 = (j0 + 1) % nodes
    hxx = hxy = hyy = bx = by = 0.0
    for j in (j0, j1):
        ax, ay, gj, kj = (_at_node(a, j, nodes) for a in (nx, ny, g, kA))
        hxx, hxy, hyy = hxx + kj * ax * ax, hxy + kj * ax * ay, hyy + kj * ay * ay
        bx, by = bx + kj * gj * ax, by + kj * gj * ay
    ex, ey = _solve2((hxx, hxy, hyy), W[:, 0] + bx, W[:, 1] + by)
    return jnp.stack([ex, ey], axis=1)


def _symmetric(load, angle, nx, ny, g, k, area, iterations):
    """Traditional Winkler: a circle through the loaded node (its gap and stiffness for every
    node), the pin displaced along the load only; one scalar equation per step."""
    cosj = nx * jnp.cos(angle)[:, None] + ny * jnp.sin(angle)[:, None]
    kA = k * area
    s_star = checkpoint_name(sg(_newton_1d(sg(load), sg(cosj), sg(g), sg(kA), iterations)),
                             NEWTON)  # kept by the wear loops' checkpoints (`remat`)
    d = s_star[:, None] * cosj - g
    act = sg(d > 0)
    f = jnp.sum(jnp.where(act, kA * d * cosj, 0.0), 1) - load
    df = sg(jnp.sum(jnp.where(act, kA * cosj * cosj, 0.0), 1))
    s = s_star - f / jnp.where(df > 0, df, 1.0)  # implicit-function correction
    delta = s[:, None] * cosj - g
    pressure = jnp.where(delta > 0, k * delta, 0.0)
    e = jnp.stack([s * jnp.cos(angle), s * jnp.sin(angle)], axis=1)
    res = jnp.abs(jnp.sum(pressure * area * cosj, 1) - load) / jnp.maximum(load, 1e-300)
    return ContactSolution(pressure, e, jnp.where(load > 0, res, 0.0), jnp.asarray(0))


def _unsymmetric(load, angle, nx, ny, g, k, area, iterations, tol, start):
    ux, uy = jnp.cos(angle), jnp.sin(angle)
    W = jnp.stack([load * ux, load * uy], axis=1)
    kA = k * area
    cap = 0.25 * sg(jnp.min(g))
    # The solve's data, passed to its branches explicitly (not closed over): `cond_any`
    # needs every batched value among its operands.
    data = (sg(ux), sg(uy), sg(load), sg(angle), sg(g), sg(kA), sg(W), cap,
            tol * jnp.maximum(sg(load), 1e-300))

    def newton(d, e_init, its):
        ux, uy, load, angle, g, kA, W, cap, limit = d
        return _newton_2d(e_init, nx, ny, g, kA, W, load, its, tol, cap)

    def cold(d):
        ux, uy, load, angle, g, kA, W, cap, limit = d
        cosj = nx * ux[:, None] + ny * uy[:, None]
        s0 = _newton_1d(load, cosj, g, kA, iterations)
        along = jnp.stack([s0 * ux, s0 * uy], axis=1)
        # The 1-D start presses the pin along the load onto the node nearest it. Under a
        # light load (an indentation far below the gap's change from node to node) the
        # answer rests on the two nodes either side of the load, and the pin must slide
        # round to the second one by a distance set by the geometry, not by the load: from
        # the 1-D start the damped steps took > 40 iterations at 0.01 N (a 2e-10 m
        # indentation; issue 41, "contact solve did not converge" on a light load file).
        # Pressed on those two nodes alone is the exact answer there; each step starts
        # from whichever of the two has the lower potential.
        pair = _pair_start(angle, nx, ny, g, kA, W)
        m_along = _moments(along[:, 0], along[:, 1], nx, ny, g, kA, W[:, 0], W[:, 1])[1]
        m_pair = _moments(pair[:, 0], pair[:, 1], nx, ny, g, kA, W[:, 0], W[:, 1])[1]
        better = jnp.all(jnp.isfinite(pair), axis=1) & (m_pair < m_along)
        return jnp.where(better[:, None], pair, along)

    # `in_chunks`: batched, the solve runs 16 lanes at a time (its arrays the size of 16
    # lanes' however wide the batch; the data is held out of differentiation)
    if start is None:
        e_star, r_star, hess, its = in_chunks(lambda d: newton(d, cold(d), iterations), data)
    else:
        # Warm start, moved out along the load until the node facing the load touches the
        # (further worn) bore: a sweep over all nodes for the deepest gap cost a fifth of a
        # warm solve at 360 x 360, and Newton on the convex potential starts as well from a
        # pin pushed in a little too far (the predictor in the wear loop already moves it
        # out by the wear along the load).
        e0 = sg(start)
        gap = _facing_gap(e0, sg(angle), nx, ny, sg(g))
        e0 = e0 - jnp.minimum(gap, 0.0)[:, None] * jnp.stack([sg(ux), sg(uy)], 1)

        # Two tries in one loop, so that a program holds one Newton solve, not three (compile
        # time is most of a cold answer): first from the warm start (<= 12 iterations; rows
        # of NaN, each regime's first solve in the wear loops, from the cold start); then,
        # rarely, the steps that did not converge again from the cold start. Both branches
        # are `cond_any`: batched (a sweep under vmap) a plain cond ran the cold start and
        # the second try on every update of every lane, more than half of the batched
        # program's time (issue 50; benchmarks/RESULTS-kernel.md, 2026-11-29). The cold
        # start runs lane by lane (`sequential`): it is once per regime, and its
        # (steps, nodes) arrays stay in the cache, which a wide batch's do not.
        def run(k, carry, d):
            e, r, hess, its, todo = carry
            init = cond_any(jnp.any(todo),
                            lambda todo, e, d: jnp.where(todo[:, None], cold(d), e),
                            lambda todo, e, d: e, todo, e, d, sequential=True)
            e1, r1, h1, i1 = newton(d, init, jnp.where(k == 0, min(iterations, 12),
                                                       iterations))
            take = (k == 0) | todo
            e1 = jnp.where(take[:, None], e1, e)
            r1 = jnp.where(take[:, None], r1, r)
            h1 = tuple(jnp.where(take, a, b) for a, b in zip(h1, hess))
            return e1, r1, h1, its + i1, jnp.linalg.norm(r1, axis=1) > d[-1]

        def tries(e0, d):
            def attempt(carry, k):
                return cond_any((k == 0) | jnp.any(carry[-1]), run, lambda k, c, d: c, k,
                                carry, d), None

            zero = jnp.zeros_like(d[2])
            first = (e0, jnp.zeros_like(e0), (zero, zero, zero), jnp.zeros((), jnp.int32),
                     jnp.isnan(e0[:, 0]))
            return lax.scan(attempt, first, jnp.arange(2))[0][:4]

        e_star, r_star, hess, its = in_chunks(tries, e0, data)
    # kept by the wear loops' checkpoints: reverse mode does not iterate again (`remat`)
    e_star, r_star, hess = checkpoint_name(sg((e_star, r_star, hess)), NEWTON)
    r = _residual_at(e_star, r_star, nx, ny, g, kA, W)  # differentiable in g, k, W
    e = e_star - jnp.stack(_solve2(hess, r[:, 0], r[:, 1]), axis=1)
    delta = e[:, 0:1] * nx + e[:, 1:2] * ny - g
    pressure = jnp.where(delta > 0, k * delta, 0.0)
    res = jnp.linalg.norm(sg(r_star), axis=1) / jnp.maximum(sg(load), 1e-300)
    return ContactSolution(pressure, e, jnp.where(load > 0, res, 0.0),
                           jnp.asarray(its, jnp.int32))


def solve_contact(load: StepArray, angle: StepArray, h: NodeArray, clearance, k: NodeArray,
                  area, *, contact: str = "unsymmetric", friction=None,
                  iterations: int = 40, tol: float = 1e-10, start=None) -> ContactSolution:
    """Contact pressure for every step of a cycle on a frozen bore profile (design.md §3).

    **Arguments:**
    - `load`, `angle`: |W| [N] and θ_W [rad], shape (steps,).
    - `h`: wear depth [m], (nodes,). `clearance`: c [m]. `k`: stiffness [Pa/m], (nodes,).
    - `area`: A_j [m²] (scalar). `contact`: `"unsymmetric"` or `"symmetric"`.
    - `friction`: None, or μ·s per step (steps,): Coulomb friction adds μ s t_j to each
      node's force direction (design.md §5), solved as the rotated, reduced load (see above).
    - `start`: optional warm start for the offsets (steps, 2) [m], e.g. the previous wear
      update's solution; by default (and for the rows that are NaN) the exact 1-D solution
      along the load.

    - `tol`: Newton stops when every step's relative force residual is below it; 1e-10 is a
      tenth of the 1e-9 that design.md §3 requires (and the implicit-gradient correction is one
      more exact Newton step on top).

    **Returns:** a `ContactSolution`; `residual` is the relative force residual of the
    converged Newton iterate, which the caller checks (never assumed).
    """
    if friction is not None:
        angle = angle - jnp.arctan(friction)
        load = load / jnp.sqrt(1 + friction**2)
    nodes = h.shape[0]
    # Normals as host constants: computed inside the trace, XLA re-evaluates the cosines in
    # every fused Newton pass (measured: 10x slower).
    th = 2 * np.pi * np.arange(nodes) / nodes
    nx, ny = jnp.asarray(np.cos(th))[None, :], jnp.asarray(np.sin(th))[None, :]
    if contact == "symmetric":
        g = (clearance + interp_periodic(h, angle))[:, None]
        kw = interp_periodic(k, angle)[:, None]
        return _symmetric(load, angle, nx, ny, g, kw, area, iterations)
    return _unsymmetric(load, angle, nx, ny, (clearance + h)[None, :], k[None, :], area,
                        iterations, tol, start)
