"""A non-parametric correction of the local wear, in the two forms missing wear takes
(design.md §7, `--shape`): a factor of the local Archard rate, or extra wear not tied to
sliding deposited where the pin presses.

- **factor**: the local rate K_d p_ij dS_i becomes K_d p_ij dS_i exp(Σ_v g_v(z_v,ij)), each
  g_v a smooth function on a small B-spline basis (what a speed, pressure or running-in
  law does: more or less of the wear Archard already puts there);
- **deposit**: + Σ_v e_v(z_v,i) κ_ij per step, e_v ≥ 0 on nonnegative B-spline coefficients,
  κ_ij the kernel of where the pin bears during step i (`swept_kernel`): a narrow bump at
  the load direction, swept along the arc the load turns through before the next step,
  normalised to unit integral over the bore angle. So e is a depth × arc [m·rad] per
  step: the deposited volume is e R_b B, whatever the node count. This is
  what impacts, fretting or cold flow make: wear where Archard puts little (at a force
  reversal the load dips and the sliding stops, while the load direction sweeps tens of
  degrees within a few crank degrees).

All coefficients zero is the base model exactly (nesting), so one forward-mode Jacobian at
zero gives the linearised fit of every variable in both forms.

State variables (`VARIABLES`), per step i of a cycle and node j of the bore:

| name | unit | what |
|---|---|---|
| `cycle_phase_deg` | deg | crank angle (swing phase, phase in a load file's period): 360 i/steps |
| `pressure_MPa` | MPa | contact pressure p_ij |
| `sliding_speed_m_per_s` | m/s | dS_i / Δt_i |
| `sliding_distance_m` | m | accumulated sliding distance S (time in the test) |
| `load_turn_rate_deg_per_s` | deg/s | how fast the load direction θ_W turns (impacts at reversal) |
| `load_turn_deg_per_deg` | deg/deg | the same per degree of cycle (kinematic: not ∝ speed) |
| `load_N` | N | the joint load magnitude |W_i| |
| `bore_angle_deg` | deg | node angle on the bore, 360 j / nodes |
| `worn_depth_um` | µm | the depth already worn at node j (the surface's own state, DESIGN §7) |

The two angles are periodic: their basis is cubic B-splines on the circle. The others use
cubic B-splines uniform in the wear-weighted quantile of z (`ShapeVariable`, the quantiles
set by `diagnose.shape.analysis` from the data's own states): the load turn rate, which spans
decades (slow turning through most of the cycle, a jump at a force reversal), and the
sliding speed, low only near reversals where little wears, get their resolution where the
wear is.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree

# name -> (unit, periodic, per step (same for every node))
VARIABLES: dict[str, tuple[str, bool, bool]] = {
    "cycle_phase_deg": ("deg", True, True),
    "pressure_MPa": ("MPa", False, False),
    "sliding_speed_m_per_s": ("m/s", False, True),
    "sliding_distance_m": ("m", False, True),
    "load_turn_rate_deg_per_s": ("deg/s", False, True),
    "load_turn_deg_per_deg": ("deg/deg", False, True),
    "load_N": ("N", False, True),
    "bore_angle_deg": ("deg", True, False),
    # the surface's own state: the frozen profile h_j of the cycle (issue 43 item 1); a
    # rate that depends on how worn the layer already is (a harder or softer sublayer,
    # debris in a deep scar) is a function of it, not of the time in the test
    "worn_depth_um": ("µm", False, False),
}
FORMS = ("factor", "deposit")
# deposits come from events in the cycle (when, how hard, how fast the load turns), not
# from where on the bore or at which pressure: those are the kernel's business
DEPOSIT_VARIABLES = ("cycle_phase_deg", "sliding_speed_m_per_s", "sliding_distance_m",
                     "load_turn_rate_deg_per_s", "load_turn_deg_per_deg", "load_N")
SWEEP_SUBSTEPS = 32  # points along the arc the load turns through within one step
DEPOSIT_WIDTH_DEG = 5.0  # width of the bump a deposit is made in at the load direction
DEPOSIT_UNIT_M = 1e-9  # a deposit coefficient of 1 is 1 nm·rad of depth per step


@dataclass(frozen=True)
class ShapeVariable:
    """One variable's basis in one form: `size` cubic B-splines. Periodic variables: uniform
    on the circle [0, 360) deg. The others: uniform in the coordinate t = F(z) ∈ [0, 1], F
    the wear-weighted distribution of z met in the data (`knots`: z at t = 0, 1/Q, ..., 1,
    increasing; F piecewise linear between them), z clamped to [knots[0], knots[-1]]: the
    basis is fine where the wear happens and coarse where little does, and the correction
    is flat beyond the data, never extrapolated."""

    name: str
    size: int
    knots: tuple = ()
    form: str = "factor"

    @property
    def unit(self) -> str:
        return VARIABLES[self.name][0]

    @property
    def periodic(self) -> bool:
        return VARIABLES[self.name][1]

    @property
    def per_step(self) -> bool:
        return VARIABLES[self.name][2]

    @property
    def lo(self) -> float:
        return 0.0 if self.periodic else float(self.knots[0])

    @property
    def hi(self) -> float:
        return 360.0 if self.periodic else float(self.knots[-1])

    @property
    def label(self) -> str:
        """`name` for the factor form (the keys of earlier results), `deposit:name` else."""
        return self.name if self.form == "factor" else f"deposit:{self.name}"

    def keys(self) -> tuple[str, ...]:
        """The effect-parameter keys of the coefficients (dimensionless)."""
        prefix = "shape" if self.form == "factor" else "deposit"
        return tuple(f"{prefix}_{self.name}_{k:02d}" for k in range(self.size))

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
class ShapeTensor:
    """A surface over two variables of one form (issue 43: products of variables): the
    term Σ_kl c_kl B_k(z_a) B_l(z_b) on the tensor product of `a`'s and `b`'s B-splines
    (each a `ShapeVariable` of the same form, few splines: 4 or 5). In the factor form
    it adds to g, so exp(g) holds a product of the two variables that no sum of
    functions of one variable does; in the deposit form it adds to e (coefficients ≥ 0)."""

    a: ShapeVariable
    b: ShapeVariable

    @property
    def form(self) -> str:
        return self.a.form

    @property
    def size(self) -> int:
        return self.a.size * self.b.size

    @property
    def label(self) -> str:
        return f"{self.a.label}*{self.b.name}"

    def keys(self) -> tuple[str, ...]:
        """Row-major over (k of `a`, l of `b`)."""
        prefix = "shape_x" if self.form == "factor" else "deposit_x"
        return tuple(f"{prefix}_{self.a.name}__{self.b.name}_{k:02d}_{m:02d}"
                     for k in range(self.a.size) for m in range(self.b.size))

    def basis(self, za, zb, xp=jnp):
        """(..., size) the products B_k(z_a) B_l(z_b), row-major."""
        W = self.a.basis(za, xp)[..., :, None] * self.b.basis(zb, xp)[..., None, :]
        return W.reshape(*W.shape[:-2], self.size)

    def roughness(self) -> np.ndarray:
        """Second differences along both directions of the coefficient grid: D_a'D_a ⊗ I +
        I ⊗ D_b'D_b (size, size)."""
        return (np.kron(self.a.roughness(), np.eye(self.b.size))
                + np.kron(np.eye(self.a.size), self.b.roughness()))


@dataclass(frozen=True)
class ShapeBasis:
    """The variables of a shape correction, each in its form, and at most a few surfaces
    over two of them (`tensors`) (static: part of `ModelConfig`). Coefficients in the
    order of `keys()`: the variables', then the surfaces'.

    `gated`: the terms (indices into `terms()`: the variables, then the surfaces) that
    are switched on or off by data, the parameters' `TERMS_ON` (len(gated),) per
    experiment (1 on, 0 off; all on as built), so that one compiled program serves uses
    that need different terms: a term off costs nothing in the loop (a `lax.cond`),
    where a term held at zero costs its basis and its tangents at every stage (measured
    on the generator's fatigue study, min of 6 evaluations: the shape refit with a 5 x 5
    surface held at zero 0.79 s, switched off 0.42 s, without it 0.38 s). A term off
    is 0 and so is its Jacobian: its columns are computed only where it is on. The
    others have no switch (a switch costs its term's fusion with the rest of the stage:
    ~15 % of that refit's evaluation with every term switched)."""

    variables: tuple[ShapeVariable, ...]
    tensors: tuple[ShapeTensor, ...] = ()
    gated: tuple[int, ...] = ()

    def terms(self) -> tuple:
        """The terms, in the order `gated` counts them: the variables, then the surfaces."""
        return tuple(self.variables) + tuple(self.tensors)

    def keys(self) -> tuple[str, ...]:
        return (tuple(k for v in self.variables for k in v.keys())
                + tuple(k for t in self.tensors for k in t.keys()))

    def of_form(self, form: str) -> tuple[ShapeVariable, ...]:
        return tuple(v for v in self.variables if v.form == form)

    def has_deposit(self) -> bool:
        return bool(self.of_form("deposit")) or any(t.form == "deposit" for t in self.tensors)


def _wrap(a, xp=jnp):
    return xp.mod(a + xp.pi, 2 * xp.pi) - xp.pi


def state_variables(pressure, slide, dt, sliding, angle, load=None, worn=None, xp=jnp):
    """Every variable of `VARIABLES` for one cycle, each broadcastable to (steps, nodes).

    `pressure` (steps, nodes) [Pa]; `slide` dS_i (steps,) [m]; `dt` (steps,) [s];
    `sliding` S [m] (scalar); `angle` θ_W (steps,) [rad]; `load` |W_i| (steps,) [N]
    (None: `load_N` is absent); `worn` h_j (nodes,) [m], the profile the cycle wears on
    (`RateContext.worn_depth`; None: zero, the unworn surface)."""
    steps, nodes = pressure.shape
    phase = xp.arange(steps) * (360.0 / steps)
    speed = slide / xp.where(dt > 0, dt, 1.0)
    # central difference of the load direction over the cycle, wrapped to (-π, π]
    turn = xp.degrees(xp.abs(_wrap(xp.roll(angle, -1) - xp.roll(angle, 1), xp)))
    span = xp.roll(dt, 1) + dt  # from step i-1 to i+1
    out = {
        "cycle_phase_deg": phase[:, None],
        "pressure_MPa": pressure * 1e-6,
        "sliding_speed_m_per_s": speed[:, None],
        "sliding_distance_m": xp.broadcast_to(sliding, (1, 1)),
        "load_turn_rate_deg_per_s": (turn / xp.where(span > 0, span, 1.0))[:, None],
        # per degree of the cycle (two steps of 360/steps degrees each)
        "load_turn_deg_per_deg": (turn / (2 * 360.0 / steps))[:, None],
        "bore_angle_deg": (xp.arange(nodes) * (360.0 / nodes))[None, :],
    }
    if load is not None:
        out["load_N"] = load[:, None]
    out["worn_depth_um"] = (xp.zeros((1, nodes)) if worn is None
                            else xp.asarray(worn)[None, :] * 1e6)
    return out


# variables whose values over a cycle depend on the load history only (not on the worn
# profile or the sliding distance): their basis is computed once per run (`precompute`)
CONSTANT = ("cycle_phase_deg", "sliding_speed_m_per_s", "load_turn_rate_deg_per_s",
            "load_turn_deg_per_deg", "load_N", "bore_angle_deg")


def swept_kernel(angle, nodes: int, substeps: int = SWEEP_SUBSTEPS,
                 width_deg: float = DEPOSIT_WIDTH_DEG):
    """κ_ij [1/rad] (steps, nodes): where the pin presses during step i: at the load
    direction, as it turns over the step's share of the arc, from half-way back to θ_{i−1}
    to half-way on to θ_{i+1}: a narrow bump (Gaussian of `width_deg`, at least 1.5 node
    spacings) at K points evenly along it, averaged, normalised so that Σ_j κ_ij Δθ = 1
    (Δθ = 2π/N). It depends on the load history only (computed once per run,
    `precompute`).

    Why at the load direction and swept: an impact, a fretting micro-slip or cold flow is
    made where the pin bears on the bore, and at a force reversal the load direction turns
    tens of degrees between two steps of a coarse cycle, across the bore between the two
    Archard wear zones; read at the steps' end points alone, a deposit would land in the
    Archard zones, where it cannot be told from K_d."""
    d_node = 2 * jnp.pi / nodes
    w = max(float(np.radians(width_deg)), 1.5 * float(d_node))
    ahead = _wrap(jnp.roll(angle, -1) - angle)  # θ_{i+1} − θ_i (steps,) [rad]
    behind = jnp.roll(ahead, 1)  # θ_i − θ_{i−1}
    s = ((jnp.arange(substeps) + 0.5) / substeps)[:, None]  # (K, 1)
    # from half-way back to θ_{i−1} to half-way on to θ_{i+1}: the step's share of the
    # arc, as the central-difference turn rate of the step (`state_variables`) sees it
    centre = angle[None, :] - 0.5 * behind[None, :] + s * 0.5 * (behind + ahead)[None, :]
    theta = jnp.arange(nodes) * d_node
    d = _wrap(theta[None, None, :] - centre[..., None])  # (K, steps, nodes)
    g = jnp.exp(-0.5 * (d / w) ** 2)
    g = g / (jnp.sum(g, axis=2, keepdims=True) * d_node)
    return jnp.mean(g, axis=0)


def precompute(shape: ShapeBasis, hist, nodes: int) -> dict:
    """What of the correction does not change within a run, for every regime of the load
    history `hist`: the basis values of the `CONSTANT` variables (by the variable's first
    key: (regimes, steps or 1, nodes or 1, size)) and the sweep's interpolation for the
    deposit. Computed once per run, outside the wear loop, instead of at every stage of
    every step (it dominated the correction's compile and run time)."""
    regimes, steps = hist.angle.shape
    dummy = jnp.zeros((steps, nodes))
    out = {}
    for r in range(regimes):
        z = state_variables(dummy, hist.slide[r], hist.dt[r], 0.0, hist.angle[r], hist.load[r])
        for var in shape.variables:
            if var.name in CONSTANT:
                out.setdefault(var.keys()[0], []).append(var.basis(z[var.name]))
        if shape.has_deposit():
            out.setdefault("kernel", []).append(swept_kernel(hist.angle[r], nodes))
    return {k: jnp.stack(v) for k, v in out.items()}


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def basis_dot(var: ShapeVariable, z, coef):
    """var.basis(z) @ coef (...) at the states z (...) for the coefficients coef (size,)."""
    return var.basis(z) @ coef


@basis_dot.defjvp
def _basis_dot_jvp(var, primals, tangents):
    # Why a rule of its own: the design Jacobian pushes every coefficient column (~140)
    # through the state-dependent basis of the per-node variables (pressure): autodiff's
    # tangent of var.basis(z) is (columns, steps, nodes, size), every piece of the spline
    # differentiated per column, and then contracted with coefficients that are zero at
    # the base fit. Each output depends on its own z only, so d(B(z) c)/dz is one
    # elementwise slope computed once; the tangent is B dc + slope · dz: columns + size
    # per state instead of columns x size (the design's run ~xN faster, same numbers).
    z, coef = primals
    dz, dcoef = tangents
    B, dB = jax.jvp(var.basis, (z,), (jnp.ones_like(z),))  # the basis and its z-slope, once
    return B @ coef, B @ dcoef + (dB @ coef) * dz


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def tensor_dot(t: ShapeTensor, za, zb, coef):
    """t.basis(za, zb) @ coef (...) (`basis_dot` for a surface over two variables)."""
    return t.basis(za, zb) @ coef


@tensor_dot.defjvp
def _tensor_dot_jvp(t, primals, tangents):
    # as `basis_dot`: the tangent is W dc + (∂W/∂z_a c) dz_a + (∂W/∂z_b c) dz_b, the slopes
    # computed once per state instead of per column
    za, zb, coef = primals
    dza, dzb, dcoef = tangents
    C = coef.reshape(t.a.size, t.b.size)
    Ba, dBa = jax.jvp(t.a.basis, (za,), (jnp.ones_like(za),))
    Bb, dBb = jax.jvp(t.b.basis, (zb,), (jnp.ones_like(zb),))
    Ba, Bb, dBa, dBb = jnp.broadcast_arrays(Ba, Bb, dBa, dBb)
    W = (Ba[..., :, None] * Bb[..., None, :]).reshape(*Ba.shape[:-1], t.size)
    BbC = Bb @ C.T  # (..., size_a): Σ_l C_kl B_l
    value = jnp.sum(Ba * BbC, axis=-1)
    slope_a = jnp.sum(dBa * BbC, axis=-1)
    slope_b = jnp.sum(Ba * (dBb @ C.T), axis=-1)
    return value, W @ dcoef + slope_a * dza + slope_b * dzb


PACKED = "__shape_coefficients__"  # `pack`'s key in `Params.effect_params`
TERMS_ON = "__shape_terms_on__"  # a gated basis's switches in `Params.effect_params`


def pack(p, shape: ShapeBasis | None):
    """`p` with the correction's coefficients as one array (`ShapeBasis.keys()` order) under
    `PACKED` instead of one scalar per key. Why: the wear loop's `while` and `scan` carry
    every closed-over leaf of `p` (with its tangent) as an operand of their own; ~140
    scalar coefficients made the design Jacobian's compilation ~1 s per variable (measured:
    one variable 7.7 s, eight 15.8 s, fourteen 22 s)."""
    if shape is None or PACKED in p.effect_params or not shape.keys():
        return p

    eff = dict(p.effect_params)
    # last axis: (keys,) for one experiment, (experiments, keys) for a batch
    eff[PACKED] = jnp.stack([jnp.asarray(eff.pop(k)) for k in shape.keys()], axis=-1)
    return pytree.replace(p, effect_params=eff)


def shape_terms(shape: ShapeBasis, p, pressure, slide, dt, sliding, angle, load,
                pre: dict | None = None, regime=None, worn=None):
    """(Σ_v g_v(z_v) (steps, nodes), the deposit Σ_v e_v(z_v) κ (steps, nodes) [m] or None)
    with the coefficients from `p.effect_params` under `ShapeVariable.keys()`; `pre`
    (`precompute`) and the `regime` index give the constant parts; `worn` h_j (nodes,)
    [m] the profile (`worn_depth_um`)."""
    z = None
    g = jnp.zeros(pressure.shape)
    e = jnp.zeros(pressure.shape)
    packed = p.effect_params.get(PACKED)
    at = 0
    on = p.effect_params.get(TERMS_ON) if shape.gated else None
    if on is not None and (shape.tensors or any(v.name not in CONSTANT or pre is None
                                                for v in shape.variables)):
        # outside the switches' branches (a value made in one branch is not the other's)
        z = state_variables(pressure, slide, dt, sliding, angle, load, worn)
    index = iter(range(len(shape.variables) + len(shape.tensors)))

    def switched(make):
        """`make()` (steps, nodes), or zeros where the term has a switch and it is off
        (`ShapeBasis.gated`): a real branch, so an off term costs nothing."""
        i = next(index)
        if on is None or i not in shape.gated:
            return make()
        return jax.lax.cond(on[shape.gated.index(i)] > 0, make,
                            lambda: jnp.zeros(pressure.shape))

    def coefficients(term):
        """The term's coefficients: its slice of the packed vector (in the basis's order,
        variables then surfaces), else its own keys."""
        nonlocal at
        if packed is None:
            return jnp.stack([p.effect_params[k] for k in term.keys()])
        at += term.size
        return packed[at - term.size:at]

    for var in shape.variables:
        coef = coefficients(var)
        if pre is not None and var.name in CONSTANT:
            basis = pre[var.keys()[0]][regime]
            term = switched(lambda b=basis, c=coef: jnp.broadcast_to(b @ c, pressure.shape))
        else:
            if z is None:
                z = state_variables(pressure, slide, dt, sliding, angle, load, worn)
            zv = z[var.name]
            term = switched(lambda v=var, zz=zv, c=coef: jnp.broadcast_to(
                basis_dot(v, zz, c), pressure.shape))
        if var.form == "factor":
            g = g + term
        else:
            e = e + term
    for t in shape.tensors:
        coef = coefficients(t)
        if z is None:
            z = state_variables(pressure, slide, dt, sliding, angle, load, worn)
        za, zb = jnp.broadcast_arrays(z[t.a.name], z[t.b.name])
        term = switched(lambda t=t, za=za, zb=zb, c=coef: jnp.broadcast_to(
            tensor_dot(t, za, zb, c), pressure.shape))
        if t.form == "factor":
            g = g + term
        else:
            e = e + term
    deposit = None
    if shape.has_deposit():
        kern = (pre["kernel"][regime] if pre is not None
                else swept_kernel(angle, pressure.shape[1]))
        deposit = DEPOSIT_UNIT_M * e * kern
    return g, deposit


def shape_log_factor(shape: ShapeBasis, p, pressure, slide, dt, sliding, angle, load=None):
    """Σ_v g_v(z_v) (steps, nodes) of the factor form (see `shape_terms`)."""
    return shape_terms(shape, p, pressure, slide, dt, sliding, angle, load)[0]
