"""The parameter vector of a fit: which study keys are fitted, and how they are packed into u.

Defined once, here, for every fit (calibrate, each diagnose fit, predict's Laplace fit and its
NUTS posterior, the shape of the missing wear): a `Packing` is a tuple of `Column`s and
their start values, and owns the map u ↦ values, its inverse and derivative, the bounds on
u, the projection of product strengths, the Gaussian prior rows and the prior density.

Parameterisation (why each choice):
- positive parameters (K_d, clearances, S_r, ...) as log-multipliers of their start,
  u = ln(value/start): depth is nearly proportional to K_d, and K_d moves by orders;
- nested effect strengths linearly around their `off` value in units of a typical scale,
  u = (value − start)/scale, within bounds by projection: at `off` the model is the base
  model exactly, which a transform would put at infinity (and zero its score);
- a strength with a `per` partner (running-in: amplitude a with distance S_r) as the
  product the data identify: value_i = (start_i + scale_i u_i)·exp(−u_j)
  (`EffectParameter.per`);
- a Gaussian prior (clearance tolerance, registration tolerance; design.md §6) is one row
  (value − centre)/sd, in units of its standard deviation: the least-squares core weights
  the data rows by 1/σ instead, so a prior's weight never depends on the noise level.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree
from jaxwear._core.errors import InputError
from jaxwear._core.host import to_device
from jaxwear._physics.effects import (
    STRUCTURAL_CANDIDATES,
    effect_parameter_specs,
    get_effect,
    product_pairs,
)
from jaxwear._physics.params import PARAMETER_KEYS
from jaxwear._study.plausible import key_range

_UNITS = (("_m_per_Pa_s", "m/(Pa·s)"), ("_N_per_m", "N/m"), ("_m_per_s2", "m/s²"),
          ("_per_Pa", "1/Pa"), ("_ratio", "-"), ("_GPa", "GPa"), ("_rpm", "r/min"),
          ("_deg", "deg"), ("_mm", "mm"), ("_um", "µm"), ("_kg", "kg"), ("_N", "N"),
          ("_s", "s"), ("_m", "m"))

ALIASES = {"K_d": "K_d_per_Pa", "clearance": "clearance_mm", "angle_offset": "angle_offset_deg"}


def unit_of(name: str) -> str:
    """Unit named by a study key's suffix (`clearance_mm/EXP` → mm); dimensionless → "-"."""
    key = name.split("/")[0]
    for suffix, unit in _UNITS:
        if key.endswith(suffix):
            return unit
    return "-"


@dataclass(frozen=True)
class Column:
    """One entry of u.

    - `name`: output name (design.md §7: `K_d_per_Pa`, `clearance_mm/EXP`, an effect key);
      `key`: the study key; `experiment`: its index for a per-experiment parameter.
    - `log`: u = ln(value/start), else u = (value − start)/`scale` (key units per unit u).
    - `to_si`: key unit → SI. `lower`, `upper`: bounds in key units.
    - `group`: "" for the study's own parameters, else the diagnose candidate (or "shape")
      it belongs to; `strength`: a nested strength (its `off` value is the model without it).
    - `prior_sd`, `prior_centre`: a Gaussian prior on the value (key units); inf: none.
    """

    name: str
    key: str
    experiment: int | None
    log: bool
    scale: float
    to_si: float
    lower: float
    upper: float
    group: str = ""
    strength: bool = False
    prior_sd: float = math.inf
    prior_centre: float = math.nan

    @property
    def has_prior(self) -> bool:
        return math.isfinite(self.prior_sd) and self.prior_sd > 0

    @property
    def bounded(self) -> bool:
        """Bounds beyond a positive parameter's (0, inf): an effect's stated range."""
        if self.log:
            return self.lower > 0 or math.isfinite(self.upper)
        return math.isfinite(self.lower) or math.isfinite(self.upper)


class Packing(pytree.Struct):
    """Columns and their start values (key units): u = 0 is the start."""

    columns: tuple = pytree.field(static=True)
    start: jax.Array  # (P,)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.columns)

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(c.key for c in self.columns)

    @property
    def size(self) -> int:
        return len(self.columns)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def _pairs(self):
        return product_pairs(self.keys)

    def values(self, u):
        """Values in key units (P,) at u (traceable)."""
        if not self.columns:
            return jnp.zeros(0)
        # elementwise over the columns, not one scalar expression per column: the shape's
        # design has ~170 columns, and per column these were ~40 % of its program's
        # operations (tangents included), compiled and traced at every model's first
        # evaluation (the same arithmetic element by element: the same values to the bit)
        log = np.array([c.log for c in self.columns], bool)
        scale = np.array([c.scale for c in self.columns], np.float64)
        out = jnp.where(log, self.start * jnp.exp(jnp.where(log, u, 0.0)),
                        self.start + scale * u)
        for i, j in self._pairs():
            out = out.at[i].set(out[i] * jnp.exp(-u[j]))
        return out

    def values_np(self, u) -> np.ndarray:
        """`values` on the host (numpy in, numpy out)."""
        u = np.asarray(u, np.float64)
        s = np.asarray(self.start, np.float64)
        sc = np.array([c.scale for c in self.columns])
        lg = np.array([c.log for c in self.columns], bool)
        with np.errstate(over="ignore", invalid="ignore"):  # inf far out, not an error
            v = np.where(lg, s * np.exp(np.where(lg, u, 0.0)), s + sc * u)
            for i, j in self._pairs():
                v[i] = v[i] * np.exp(-u[j])
        return v

    def value_jacobian(self, u) -> np.ndarray:
        """d values / d u (P, P) at u: diagonal but for the product pairs."""
        u = np.asarray(u, np.float64)
        s = np.asarray(self.start, np.float64)
        G = np.zeros((self.size, self.size))
        # a trial far out (a log coordinate past ~709) gives inf, never an exception: the
        # fit rejects it as not finite (`lsq.solve`)
        with np.errstate(over="ignore", invalid="ignore"):
            for i, c in enumerate(self.columns):
                G[i, i] = s[i] * np.exp(u[i]) if c.log else c.scale
            v = self.values_np(u)
            for i, j in self._pairs():
                G[i, i] *= np.exp(-u[j])
                G[i, j] = -v[i]
        return G

    def u_of(self, values) -> np.ndarray:
        """Inverse of `values` (numpy)."""
        v = np.asarray(values, np.float64)
        s = np.asarray(self.start, np.float64)
        lin = v.copy()
        for i, j in self._pairs():
            lin[i] = v[i] * v[j] / s[j]  # the linear coordinate of the product
        return np.array([math.log(v[i] / s[i]) if c.log else (lin[i] - s[i]) / c.scale
                         for i, c in enumerate(self.columns)])

    def bounds_u(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds on u (P,) from the columns' bounds on the values."""
        s = np.asarray(self.start, np.float64)
        lo, hi = np.full(self.size, -np.inf), np.full(self.size, np.inf)
        for i, c in enumerate(self.columns):
            if c.log:
                lo[i] = math.log(c.lower / s[i]) if c.lower > 0 else -np.inf
                hi[i] = math.log(c.upper / s[i]) if math.isfinite(c.upper) else np.inf
            else:
                lo[i] = (c.lower - s[i]) / c.scale if math.isfinite(c.lower) else -np.inf
                hi[i] = (c.upper - s[i]) / c.scale if math.isfinite(c.upper) else np.inf
        return lo, hi

    def project(self, u) -> np.ndarray:
        """u with every product strength inside its value bounds, by moving its linear
        coordinate: the box on u cannot state a bound on linear·exp(−u_per), and an
        unbounded running-in amplitude (S_r → 0 along the valley of equal a·S_r) makes the
        wear loop arbitrarily stiff."""
        u = np.array(u, np.float64)
        s = np.asarray(self.start, np.float64)
        for i, j in self._pairs():
            c = self.columns[i]
            val = np.clip((s[i] + c.scale * u[i]) * math.exp(-u[j]), c.lower, c.upper)
            u[i] = (val * math.exp(u[j]) - s[i]) / c.scale
        return u

    def prior_rows(self, u) -> tuple[np.ndarray, np.ndarray]:
        """Gaussian prior rows (value − centre)/sd (m,) and their Jacobian (m, P), in units
        of their standard deviation."""
        idx = [i for i, c in enumerate(self.columns) if c.has_prior]
        if not idx:
            return np.zeros(0), np.zeros((0, self.size))
        with np.errstate(over="ignore", invalid="ignore"):  # inf far out, not an error
            v, G = self.values_np(u), self.value_jacobian(u)
            sd = np.array([self.columns[i].prior_sd for i in idx])
            centre = np.array([self.columns[i].prior_centre for i in idx])
            return (v[idx] - centre) / sd, G[idx] / sd[:, None]

    def log_prior(self, u):
        """Log prior density of u (traceable, up to a constant), for the posterior (NUTS):
        a Gaussian prior on the value where the column has one (truncated to its bounds);
        uniform in the value within
        a bounded parameter's bounds (an effect's: log-uniform for its log-fitted shape
        parameters; −inf outside); otherwise weakly informative on u
        (log parameters: a factor 100 per standard deviation; linear: 10 scales); plus the
        log-Jacobian of value ↦ u where the prior is stated on the value."""
        vals = self.values(u)
        lp = 0.0
        for i, c in enumerate(self.columns):
            if c.has_prior:
                lp = lp - 0.5 * ((vals[i] - c.prior_centre) / c.prior_sd) ** 2
                if c.log:
                    lp = lp + u[i]  # log |d value / d u| (value = start·e^u)
                if c.bounded:  # truncated to the plausible range (a clearance's); the
                    # slack keeps a fit held at a bound (u = ln(lower/start)) inside
                    inside = ((vals[i] >= c.lower * (1 - 1e-9))
                              & (vals[i] <= c.upper * (1 + 1e-9)))
                    lp = lp + jnp.where(inside, 0.0, -jnp.inf)
            elif c.bounded:
                inside = (vals[i] >= c.lower) & (vals[i] <= c.upper)
                lp = lp + jnp.where(inside, 0.0, -jnp.inf)
            elif c.log:
                lp = lp - 0.5 * (u[i] / math.log(100.0)) ** 2
            else:
                lp = lp - 0.5 * (u[i] / 10.0) ** 2
        # a strength fitted as a product with its partner (value = linear·e^(−u_j)): uniform
        # in the value means + log |d value / d u_i| = −u_j in u
        for _, j in self._pairs():
            lp = lp - u[j]
        return lp

    def mask(self, groups=None) -> np.ndarray:
        """Columns of the study's own parameters and of the named groups (all: None)."""
        if groups is None:
            return np.ones(self.size, bool)
        groups = set(groups)
        return np.array([c.group == "" or c.group in groups for c in self.columns])

    def with_start(self, start) -> Packing:
        """The same columns started at `start` (key units, (P,))."""
        return Packing(self.columns, jnp.asarray(start, jnp.float64))


# ---------------------------------------------------------------- what a study fits


def parse_fit(study, fit) -> list[str]:
    """Study keys to fit from `--fit` (aliases K_d, clearance) plus the strengths of the
    effects the study switches on."""
    items = fit.split(",") if isinstance(fit, str) else list(fit or [])
    items = [s.strip() for s in items if s.strip()] or ["K_d", "clearance"]
    specs = effect_parameter_specs()
    keys = []
    for it in items:
        key = ALIASES.get(it, it)
        if key not in PARAMETER_KEYS and key not in specs and key != "angle_offset_deg":
            raise InputError(f"<<fit_spec>>: unknown parameter {it!r}; expected K_d, clearance "
                             f"or a "
                             f"study key such as spring_N_per_m")
        keys.append(key)
    for eff in study.config.effects:
        for k in get_effect(eff).parameters:
            if k not in keys:
                keys.append(k)
    return list(dict.fromkeys(keys))


def study_fit_keys(study, fit=None) -> list[str]:
    """The keys a verb fits: `fit` (a --fit string or list), else the study's `[fit]
    parameters`, else K_d and the clearances; plus the scans' registration where the study
    fits it (`[fit] angle_tolerance_deg` > 0)."""
    if fit is None:
        fit = list(study.fit) if study.fit else "K_d,clearance"
    return with_registration(study, parse_fit(study, fit))


def with_registration(study, keys: list[str]) -> list[str]:
    """`keys` plus the scans' angular registration (`angle_offset_deg`, one per profile
    experiment) when the study's `[fit] angle_tolerance_deg` is > 0."""
    if study.angle_tolerance_deg > 0 and "angle_offset_deg" not in keys:
        return [*keys, "angle_offset_deg"]
    return list(keys)


def clearance_bounds_mm(preset: str | None) -> tuple[float, float]:
    """Bounds on a fitted clearance [mm]: the plausible range a clearance is held to as an
    input (`_plausible.key_range`, docs/plausibility.md: 0.1 µm to 100 mm), else (0, inf).

    Why a bound and not only the tolerance prior: the prior row (c − c_nominal)/τ tends to
    the constant −c_nominal/τ as c → 0, and below ~0.1 µm the contact no longer sees the
    clearance either, so where the data pull a clearance down (a model that lacks the data's
    physics: a symmetric contact fitted to unsymmetric wear) nothing stops the walk in
    u = ln(c/c_nominal): a held-out study's fit stopped at 1.9e-6 mm, or at 1.3e-8 mm with a
    slightly different integrator, wherever the step test happened to stop it, and the
    candidates refitted from there failed (trials at e^1044 x nominal). At the bound the
    clearance is held, and `_outside.parameter_flags` says so (OUTSIDE THE MODEL)."""
    r = key_range("clearance_mm", preset)
    if r is None:
        return 0.0, math.inf
    return float(r.lo), float(r.hi)


def study_columns(study, keys: list[str], plist) -> list[tuple[Column, float]]:
    """Columns for the study keys `keys` with their study values (key units) as starts.

    `plist`: each experiment's `Params`. Clearances are one per experiment with the
    tolerance prior (τ = 0 holds them at nominal: no column; τ = inf: no prior row) and
    the plausible range as bounds (`clearance_bounds_mm`);
    registration offsets one per profile experiment with their prior; effect strengths
    start at `off` (nested: the fit starts from the model without them)."""
    specs = effect_parameter_specs()
    tol_mm = study.clearance_tolerance_um / 1e3
    c_lo, c_hi = clearance_bounds_mm(study.preset)
    out = []
    for key in keys:
        if key == "clearance_mm":
            if study.clearance_tolerance_um == 0:
                continue
            for i, e in enumerate(study.experiments):
                c = float(plist[i].clearance) * 1e3
                out.append((Column(f"clearance_mm/{e.name}", key, i, True, 1.0, 1e-3, c_lo,
                                   c_hi, prior_sd=tol_mm, prior_centre=c), c))
        elif key == "angle_offset_deg":
            if not study.angle_tolerance_deg > 0:
                continue
            for i, e in enumerate(study.experiments):
                if e.profile is not None:  # a history (maximum depth) has no angle
                    a = e.profile.angle_offset_deg
                    out.append((Column(f"angle_offset_deg/{e.name}", key, i, False, 1.0,
                                       math.pi / 180, -math.inf, math.inf,
                                       prior_sd=study.angle_tolerance_deg, prior_centre=a),
                                a))
        elif key in specs:
            s = specs[key]
            v = float(plist[0].get(key)) / s.to_si
            out.append((Column(key, key, None, s.log, s.scale, s.to_si, s.lower, s.upper,
                               strength=not s.log), v if s.log else s.off))
        else:
            k = PARAMETER_KEYS[key]
            out.append((Column(key, key, None, k.positive, 1.0, k.to_si,
                               0.0 if k.positive else -math.inf, math.inf),
                        float(plist[0].get(key)) / k.to_si))
    return out


def candidate_columns(name: str, p0) -> list[tuple[Column, float]]:
    """Columns of a diagnose candidate (an effect, or a structural choice's strength),
    started at `off` (strengths) or at the value `p0` carries (shape parameters)."""
    specs = (STRUCTURAL_CANDIDATES[name].parameters if name in STRUCTURAL_CANDIDATES
             else get_effect(name).parameters)
    out = []
    for key, s in specs.items():
        if s.log:
            v = float(np.asarray(p0.effect_params[key]).reshape(-1)[0]) / s.to_si
            start = v if v > 0 else s.default
        else:
            start = s.off
        out.append((Column(key, key, None, s.log, s.scale, s.to_si, s.lower, s.upper,
                           group=name, strength=not s.log), start))
    return out


def shape_columns(keys) -> list[tuple[Column, float]]:
    """The coefficients of the shape correction (`effects.shape`): 0 is the model as
    written; a deposit's coefficients are ≥ 0 (extra wear is never negative)."""
    return [(Column(k, k, None, False, 1.0, 1.0,
                    0.0 if k.startswith("deposit_") else -math.inf, math.inf, group="shape",
                    strength=k.startswith("deposit_")), 0.0)
            for k in keys]


def packing_of(columns: list[tuple[Column, float]], start: dict | None = None) -> Packing:
    """A `Packing` of (column, default start) pairs; `start` overrides by name (key units)."""
    start = dict(start or {})
    names = [c.name for c, _ in columns]
    unknown = sorted(set(start) - set(names))
    if unknown:
        raise InputError(f"start values for {unknown}, which are not fitted; fitted: {names}")
    s0 = []
    for c, v in columns:
        v = float(start.get(c.name, v))
        if c.log and not v > 0:
            raise InputError(f"start value of {c.name} must be > 0 to fit it, got {v}")
        s0.append(v)
    return Packing(tuple(c for c, _ in columns), to_device(s0, np.float64))
