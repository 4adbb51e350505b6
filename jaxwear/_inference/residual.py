"""The study as a residual model: u ↦ model − measured depth at every row [µm].

One definition for every fit: calibrate, each diagnose fit (the base model, every candidate,
the shape of the missing wear), predict's Laplace fit and its NUTS posterior all pose their
problem as a `ResidualModel`; `jaxwear._inference.lsq` solves it. A model holds

- the parameter vector's packing (`_packing.Packing`: columns, starts, bounds, priors),
- every experiment's parameters and wear schedule, batched (schedules padded to a common
  length, so all experiments run in one compiled function),
- the measured rows (`Data`): where each row lives in the model's snapshots,

and one compiled evaluation returns the rows, their exact forward-mode Jacobian through the
whole wear loop (forward mode: a handful of tangents pushed alongside the primal, the
columns of distinct experiments sharing one: `evaluation.seeds`), the
snapshots and their Jacobian. Prior rows are computed on the host from the packing (they
are analytic in u), so changing a prior never recompiles.

Diagnose's candidates are columns of a group (`Column.group`) in the same model, switched
off by masks; the configuration then carries every candidate effect, held at `off`.

One compile per answer: a fit compiles its Jacobian once, at the coarsest resolution, and
consults finer resolutions by forward runs only. The residual difference between a finer
level and this one at the answer is held as a fixed correction of the rows (`defect_um`, a
traced array: changing it never recompiles) while the coarse Jacobian steps (defect
correction, `_calibrate.fit_study`). A `Layout` pads every schedule to shared capacities
(pieces, snapshots, attempts, the early-stop arrays), so that a forecast over other points
runs in the fit's own compiled function. `TRACES` counts the compilations.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree
from jaxwear._core.errors import InputError
from jaxwear._core.host import stack, to_device
from jaxwear._inference.packing import (
    Packing,
    candidate_columns,
    packing_of,
    shape_columns,
    study_columns,
)
from jaxwear._physics.config import ModelConfig
from jaxwear._physics.effects import STRUCTURAL_CANDIDATES
from jaxwear._physics.effects.shape import PACKED, TERMS_ON
from jaxwear._physics.effects.shape import pack as pack_shape
from jaxwear._physics.params import Params
from jaxwear._physics.schedule import Schedule, pad_schedule
from jaxwear._physics.wear import build_schedule, schedule_numerics, wear_loop
from jaxwear._study.study import Study

# Compilations of the residual model's functions, by kind ("jacobian", "forward"), counted
# when JAX traces them (a trace is a compilation, or a load from the persistent cache):
# a fit reports the difference over its run as its `compiles`.
TRACES: collections.Counter = collections.Counter()


def traces() -> dict:
    """A copy of `TRACES` (to difference around an answer)."""
    return dict(TRACES)


def traces_since(before: dict) -> dict:
    """Compilations by kind since `before` (`traces()`): "jacobian" and "forward" always,
    other kinds ("density": a sampler's log density) where any."""
    kinds = dict.fromkeys(["jacobian", "forward", *TRACES])
    out = {k: TRACES.get(k, 0) - before.get(k, 0) for k in kinds}
    return {k: v for k, v in out.items() if v or k in ("jacobian", "forward")}


@dataclass(frozen=True)
class Layout:
    """Shared capacities of a model's batched schedule, so that problems over other points
    (a forecast, its refinements) share one compiled function with the fit: `updates`
    pieces, `snapshots` snapshot slots, at least `attempts` attempted steps (adaptive), and
    the early-stop arrays present (`stop`: a fit never stops early, its arrays are +inf;
    a forecast sets them, `_predict.stop_past_layer`). Unused capacity costs little: a
    padded piece or attempt skips all work (measured on the boom at 90 x 72: 8x the
    attempts, 0.35 s against 0.21 s a forward run)."""

    updates: int
    snapshots: int
    attempts: int = 0
    stop: bool = True

    def holds(self, sched: Schedule) -> bool:
        """Whether a batched schedule fits in these capacities."""
        return (sched.cycles.shape[-1] <= self.updates
                and sched.n_snapshots <= self.snapshots)


class Data(pytree.Struct):
    """Measured rows, flattened over experiments: where each lives in the model output."""

    exp: jax.Array  # experiment index (rows,)
    snap: jax.Array  # snapshot index
    i0: jax.Array  # interpolation nodes and weight (profiles)
    i1: jax.Array
    w: jax.Array
    is_max: jax.Array  # True: maximum depth (history rows)
    depth_um: jax.Array  # measured [µm]
    x: jax.Array  # angle [deg] (profiles) or hours (history), for reports only
    angle: jax.Array  # bushing-frame angle at the given registration [rad] (0: history)
    offset_col: jax.Array  # column of the row's fitted angle offset, or -1

    @property
    def n(self) -> int:
        return int(self.depth_um.shape[0])


def _stack(trees):
    # on the host where the leaves are host data (`_core.host.stack`: no compilation)
    return jax.tree.map(lambda *xs: stack(xs), *trees)


def _run_length(e) -> dict:
    """`build_schedule`'s run length of an experiment's residuals: up to its last measured
    point, not past it (nothing after it enters a residual: a forecast's training study
    keeps the experiment's duration, and its fits ran 25 h of the boom for data to 15 h)."""
    pts = e.snapshot_points
    end = max(pts) if pts else None
    if e.hours is not None:
        return {"revolutions": None, "hours": e.hours if end is None else min(e.hours, end)}
    return {"revolutions": e.revolutions if end is None or e.revolutions is None
            else min(e.revolutions, end), "hours": None}


def experiment_schedules(study: Study, plist: list[Params], layout: Layout | None = None
                         ) -> Schedule:
    """Every experiment's schedule (to its data's snapshot points), padded and batched;
    with a `layout`, padded to its capacities (which must hold it) with the early-stop
    arrays at +inf (never stops)."""
    scheds = [build_schedule(p, study.config, **_run_length(e),
                             snapshots=e.snapshot_points or [e.hours or e.revolutions],
                             pad=False, **schedule_numerics(study))
              for p, e in zip(plist, study.experiments)]
    U = max(s.updates for s in scheds)
    S = max(s.n_snapshots for s in scheds)
    A = max(s.attempts for s in scheds)
    if layout is not None:
        if U > layout.updates or S > layout.snapshots:
            raise ValueError(f"schedule of {U} pieces and {S} snapshots exceeds the layout "
                             f"{layout}")
        U, S = layout.updates, layout.snapshots
        A = max(A, layout.attempts) if A else 0
    batched = _stack([pad_schedule(s, U, S, A) for s in scheds])
    if layout is not None and layout.stop and batched.adaptive:
        batched = batched.stopping_at(math.inf, math.inf)
    return batched


def measured_data(study: Study, packing: Packing) -> Data:
    """The study's measured rows (profiles and histories) as a `Data`."""
    n = study.config.nodes
    offset_col = {c.experiment: i for i, c in enumerate(packing.columns)
                  if c.key == "angle_offset_deg"}
    rows = {k: [] for k in ("exp", "snap", "i0", "i1", "w", "is_max", "depth_um", "x",
                            "angle", "offset_col")}
    for ei, e in enumerate(study.experiments):
        points = e.snapshot_points
        if e.profile is not None:
            # periodic linear interpolation between the two nodes around each measured angle
            x = np.mod(e.profile.angle / (2 * np.pi) * n, n)
            i0 = np.floor(x).astype(int) % n
            rows["exp"] += [ei] * len(x)
            rows["snap"] += [points.index(float(r)) for r in e.profile.revolutions]
            rows["i0"] += list(i0)
            rows["i1"] += list((i0 + 1) % n)
            rows["w"] += list(x - np.floor(x))
            rows["is_max"] += [False] * len(x)
            rows["depth_um"] += list(np.asarray(e.profile.depth) * 1e6)
            rows["x"] += list(np.degrees(e.profile.angle))
            rows["angle"] += list(np.asarray(e.profile.angle, float))
            rows["offset_col"] += [offset_col.get(ei, -1)] * len(x)
        if e.history is not None:
            k = len(e.history.hours)
            rows["exp"] += [ei] * k
            rows["snap"] += [points.index(float(t)) for t in e.history.hours]
            rows["i0"] += [0] * k
            rows["i1"] += [0] * k
            rows["w"] += [0.0] * k
            rows["is_max"] += [True] * k
            rows["depth_um"] += list(np.asarray(e.history.depth) * 1e6)
            rows["x"] += list(np.asarray(e.history.hours, float))
            rows["angle"] += [0.0] * k
            rows["offset_col"] += [-1] * k
    if not rows["exp"]:
        raise InputError(f"{study.path}: no measured data (profile or history) to fit")
    f, i = np.float64, np.int32
    return Data(exp=to_device(rows["exp"], i), snap=to_device(rows["snap"], i),
                i0=to_device(rows["i0"], i), i1=to_device(rows["i1"], i),
                w=to_device(rows["w"], f), is_max=to_device(rows["is_max"], bool),
                depth_um=to_device(rows["depth_um"], f), x=to_device(rows["x"], f),
                angle=to_device(rows["angle"], f), offset_col=to_device(rows["offset_col"], i))


def _packed_coefficients(p, shape, coefs, vals, columns, n_exp: int):
    """`p` with the shape correction's coefficients at `vals` (its columns `coefs`: (index
    in u, position in `shape.keys()`)) as the one packed array the wear loop reads
    (`effects.shape.pack`: `PACKED`, (n_exp, keys)), made in one operation.

    Why not a parameter per key, packed by the loop: the shape's design has ~170
    coefficient columns, and a scalar per column, broadcast, set and stacked (with its
    tangents) was ~40 % of the operations of its Jacobian's program, traced, lowered and
    compiled at its first evaluation. The values are the same products element by
    element."""
    eff = dict(p.effect_params)
    keys = shape.keys()
    # per key: gone once packed (each present where they are not packed yet)
    held = ([eff.pop(k, None) for k in keys] if PACKED in eff
            else [eff.pop(k) for k in keys])
    idx = np.array([i for i, _ in coefs])
    pos = np.array([k for _, k in coefs])
    si = vals[idx] * np.array([columns[i].to_si for i in idx], np.float64)
    if len(pos) == len(keys) and np.array_equal(pos, np.arange(len(keys))):
        packed = jnp.broadcast_to(si, (n_exp, len(keys)))  # every key a column
    else:
        packed = (jnp.asarray(eff[PACKED], jnp.float64) if PACKED in eff else jnp.stack(
            [jnp.broadcast_to(jnp.asarray(v, jnp.float64), (n_exp,)) for v in held], axis=-1))
        packed = packed.at[:, pos].set(jnp.broadcast_to(si, (n_exp, len(pos))))
    eff[PACKED] = packed
    return pytree.replace(p, effect_params=eff)


class ResidualModel(pytree.Struct):
    """A study's model and data: u (P,) ↦ rows [µm] (see the module docstring)."""

    cfg: ModelConfig = pytree.field(static=True)
    exp_names: tuple = pytree.field(static=True)
    packing: Packing
    params: Params  # batched over experiments (leading axis), candidates at `off`
    schedule: Schedule  # batched
    data: Data
    nominal_angle_deg: jax.Array  # the given registration offsets (experiments,)
    noise_um: float | None = pytree.field(static=True, default=None)  # the study's, if given
    # a fixed correction of every row [µm] (rows,): the residual difference between a
    # finer resolution and this one at the answer (defect correction); zeros: none
    defect_um: jax.Array | None = None

    # ------------------------------------------------------------ the parameter vector
    @property
    def columns(self) -> tuple:
        return self.packing.columns

    @property
    def names(self) -> tuple[str, ...]:
        return self.packing.names

    @property
    def start(self):
        """Start values (P,) in key units: u = 0."""
        return self.packing.start

    @property
    def n_data(self) -> int:
        return self.data.n

    @property
    def measured(self) -> np.ndarray:
        return np.asarray(self.data.depth_um)

    def values(self, u):
        return self.packing.values(u)

    def with_packing(self, packing: Packing) -> ResidualModel:
        return dataclasses.replace(self, packing=packing)

    def with_schedule(self, schedule: Schedule) -> ResidualModel:
        return dataclasses.replace(self, schedule=schedule)

    def with_defect(self, defect_um) -> ResidualModel:
        """The same model with its rows corrected by `defect_um` (rows,) [µm]."""
        return dataclasses.replace(self, defect_um=to_device(defect_um, np.float64))

    def with_terms_on(self, on) -> ResidualModel:
        """The same model (the same compiled programs) with the switched terms of its shape
        basis on or off: `on` (terms,) bool in `ShapeBasis.terms()` order; a term without
        a switch (`ShapeBasis.gated`) cannot be off."""
        shape = self.cfg.shape
        terms = () if shape is None else shape.terms()
        on = [bool(x) for x in on]
        if len(on) != len(terms):
            raise ValueError(f"{len(terms)} switches expected, got {len(on)}")
        if any(not x and i not in shape.gated for i, x in enumerate(on)):
            raise ValueError("a term without a switch cannot be off (ShapeBasis.gated)")
        if not terms or not shape.gated:
            return self
        flags = np.array([on[i] for i in shape.gated], np.float64)
        n_exp = len(self.exp_names)
        eff = {**self.params.effect_params,
               TERMS_ON: to_device(np.broadcast_to(flags, (n_exp, len(flags))), np.float64)}
        return dataclasses.replace(self, params=pytree.replace(self.params, effect_params=eff))

    @property
    def defect(self) -> np.ndarray:
        """The rows' correction (rows,) [µm] (zeros: none)."""
        return (np.zeros(self.n_data) if self.defect_um is None
                else np.asarray(self.defect_um, np.float64))

    # ------------------------------------------------------------ the model
    def batched_params(self, u) -> Params:
        """Every experiment's parameters (SI, batched) at u."""
        vals = self.values(u)
        p = self.params
        n_exp = len(self.exp_names)
        updates: dict = {}
        structural: dict = {}
        shape = self.cfg.shape
        at = {k: n for n, k in enumerate(shape.keys())} if shape is not None else {}
        coefs = []  # the shape correction's columns (index, position in its keys)
        for i, c in enumerate(self.columns):
            if c.key == "angle_offset_deg":
                continue  # a property of the measurement, not of the joint
            if (c.key in at and c.experiment is None
                    and c.group not in STRUCTURAL_CANDIDATES):
                coefs.append((i, at[c.key]))
                continue
            si = vals[i] * c.to_si
            if c.group in STRUCTURAL_CANDIDATES:
                structural.setdefault(c.group, {})[c.key] = jnp.broadcast_to(si, (n_exp,))
            elif c.experiment is None:
                updates[c.key] = jnp.broadcast_to(si, (n_exp,))
            else:
                cur = updates.get(c.key, p.get(c.key))
                updates[c.key] = jnp.asarray(cur).at[c.experiment].set(si)
        p = p.with_values(updates) if updates else p
        for name, vals_si in structural.items():
            p = STRUCTURAL_CANDIDATES[name].set_strength(p, vals_si)
        if coefs:
            p = _packed_coefficients(p, shape, coefs, vals, self.columns, n_exp)
        return p

    def snapshots(self, u):
        """Snapshots (experiments, snapshots, nodes) [µm] and the batched `WearResult`."""
        # lax.map, not vmap: on CPU the experiments gain nothing from batching, and mapping
        # keeps the contact solver's data-dependent branches and loop counts per experiment.
        # the shape correction's coefficients packed before the map: `batched_params`
        # packs the fitted ones; `pack` those of a correction held as study parameters
        res = jax.lax.map(lambda ps: wear_loop(ps[0], self.cfg, ps[1]),
                          (pack_shape(self.batched_params(u), self.cfg.shape),
                           self.schedule))
        return res.snapshots * 1e6, res

    def predict_from(self, snaps_um, u=None):
        """Model depth at every row [µm] from snapshots (experiments, snapshots, nodes).

        With fitted registration offsets (and u given), each profile row is read at its
        angle shifted by (fitted − given) offset, by a periodic linear interpolation that is
        differentiable in the offset: the weight is smooth in the angle and the node indices
        (floor) are locally constant, so d depth/d offset is the profile's slope there."""
        d = self.data
        # Each row reads its two nodes (and a history row its snapshot's maximum) straight
        # from the snapshots: gathering each row's whole profile first, (rows, nodes), was
        # under the shape analysis's ~150 forward-mode tangents 58 KB a row at 48 nodes
        # (17 GB for a 300 000-row scan; issue 41).
        n = snaps_um.shape[-1]
        flat = snaps_um.reshape(-1)
        start = (d.exp * snaps_um.shape[1] + d.snap) * n  # (rows,) each row's profile
        fits_angles = any(c.key == "angle_offset_deg" for c in self.columns)
        if fits_angles and u is not None:
            vals = self.values(u)
            k = jnp.clip(d.offset_col, 0, None)
            shift = jnp.where(d.offset_col >= 0, vals[k] - self.nominal_angle_deg[d.exp], 0.0)
            x = jnp.mod((d.angle + jnp.deg2rad(shift)) / (2 * jnp.pi) * n, n)
            fl = jnp.floor(x)
            i0 = fl.astype(jnp.int32) % n
            i1 = (i0 + 1) % n
            w = x - fl
        else:
            i0, i1, w = d.i0, d.i1, d.w
        at = flat[start + i0] * (1 - w) + flat[start + i1] * w
        rows = jnp.where(d.is_max, jnp.max(snaps_um, axis=-1)[d.exp, d.snap], at)
        return rows if self.defect_um is None else rows + self.defect_um

    def predict(self, u):
        """Model depth at every row [µm] at u (traceable)."""
        return self.predict_from(self.snapshots(u)[0], u)

    def prior_rows(self, u):
        """The packing's Gaussian prior rows (SD units) and their Jacobian, numpy."""
        return self.packing.prior_rows(u)


def build_model(study: Study, keys: list[str], start: dict | None = None, *,
                candidates=(), contact: str | None = None, shape=None,
                layout: Layout | None = None) -> ResidualModel:
    """The residual model of `study` fitting the study keys `keys` (`_packing.parse_fit`).

    - `start`: start values by output name (key units), else the study's values.
    - `candidates`: diagnose candidates added as columns of their own group (at `off`),
      the configuration extended with them; `contact`: another contact model; `shape`: the
      shape correction's basis (`effects.shape.ShapeBasis`), its coefficients at 0.
    - `layout`: the schedule's capacities (`Layout`), shared with other problems.
    The rows' correction (`defect_um`) starts at zero.
    """
    plist = [study.params(e) for e in study.experiments]
    cols = study_columns(study, keys, plist)
    cfg = study.config
    parametric = [c for c in candidates if c not in STRUCTURAL_CANDIDATES]
    if candidates:
        cfg = cfg.replace(effects=tuple(cfg.effects) + tuple(parametric))
    if "double_layer" in candidates:
        cfg = STRUCTURAL_CANDIDATES["double_layer"].configure(cfg)
    if contact is not None:
        cfg = cfg.replace(contact=contact)
    params = _stack(plist)
    for cand in candidates:
        if cand != "unsymmetric":
            cols += candidate_columns(cand, params)
    if shape is not None:
        cfg = cfg.replace(shape=shape)
        params = pytree.replace(params, effect_params={
            **params.effect_params, **{k: jnp.zeros(len(plist)) for k in shape.keys()}})
        if shape.gated:  # every term on (`with_terms_on`)
            params = pytree.replace(params, effect_params={
                **params.effect_params,
                TERMS_ON: to_device(np.ones((len(plist), len(shape.gated))), np.float64)})
        cols += shape_columns(shape.keys())
    packing = packing_of(cols, start)
    nominal_angle = [e.profile.angle_offset_deg if e.profile is not None else 0.0
                     for e in study.experiments]
    model = ResidualModel(cfg=cfg, exp_names=tuple(e.name for e in study.experiments),
                          packing=packing, params=params,
                          schedule=experiment_schedules(study, plist, layout),
                          data=measured_data(study, packing),
                          nominal_angle_deg=to_device(nominal_angle, np.float64),
                          noise_um=study.noise_um)
    model = model.with_defect(np.zeros(model.n_data))
    if candidates or shape is not None:
        # candidate strengths at `off` in the batched parameters too (a study may set a
        # value for an effect it does not switch on; the structural strength maps to the
        # backing, which is absent in the single-layer base model)
        model = dataclasses.replace(model, params=model.batched_params(
            jnp.zeros(packing.size)))
    return model


# ---------------------------------------------------------------- evaluation


