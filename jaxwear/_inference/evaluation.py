"""One evaluation of the residual model: rows, prior rows and Jacobian at u (or a forward run
without it), with the integration's error estimate; an unusable value where the model cannot
run there."""

from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree
from jaxwear._core.background import Background
from jaxwear._core.host import to_device
from jaxwear._core.jit import jit
from jaxwear._inference import lsq
from jaxwear._inference.attempts import (
    MAX_ATTEMPTS,
    _dynamic,
    attempts_needed,
    enough_attempts,
    too_stiff,
    work_failure,
)
from jaxwear._inference.residual import TRACES, ResidualModel


@dataclass(frozen=True)
class Evaluation:
    """The model at u (numpy).

    `pred`, `r` (rows,) [µm] (model, model − measured); `J` (rows, P) = d r/d u;
    `r_prior` (m,), `J_prior` (m, P): prior rows in SD units; `snaps` (E, S, N) [µm] and
    `J_snaps` (E, S, N, P); `max_residual`: largest relative contact residual; `worn`:
    largest worn-through cycle (−1: none); `sliding_m` (E,); `error_um`: integration
    error estimate of the worst experiment (inf: the adaptive loop ran out of attempts);
    `steps`: accepted integration steps of the longest experiment; `failure`: why the model
    was not run at u (`unusable_evaluation`), "" where it ran.
    """

    u: np.ndarray
    pred: np.ndarray
    r: np.ndarray
    J: np.ndarray
    r_prior: np.ndarray
    J_prior: np.ndarray
    snaps: np.ndarray
    J_snaps: np.ndarray | None
    max_residual: float
    worn: float
    sliding_m: np.ndarray
    error_um: float
    steps: int
    adaptive: bool = True
    failure: str = ""

    @property
    def usable(self) -> bool:
        return bool(np.all(np.isfinite(self.r)) and np.all(np.isfinite(self.J))
                    and self.worn < 0 and np.isfinite(self.error_um) and not self.failure)

    @property
    def why(self) -> str:
        """The cause where not usable ("" where usable), for progress lines and messages."""
        if self.failure:
            return self.failure
        if self.worn >= 0:
            return f"the layer wore through at cycle {self.worn:.0f}"
        if not np.isfinite(self.error_um) and self.steps == 0:
            return ("no wear step could be taken: the model is not finite at these values "
                    f"(its contact residual is {self.max_residual:.3g})")
        if not np.isfinite(self.error_um):
            return ("the integration did not reach its end (the adaptive loop ran out of "
                    "attempts)")
        for what, a in (("rows", self.r), ("Jacobian", self.J)):
            bad = ~np.isfinite(a)
            if bad.any():
                return f"{int(bad.sum())} of {bad.size} model {what} not finite"
        return ""

    @property
    def rms_um(self) -> float:
        return float(np.sqrt(np.mean(self.r ** 2))) if self.r.size else 0.0

    def shifted(self, shift) -> Evaluation:
        """The evaluation with every row moved by `shift` (rows,) [µm] (a change of the
        rows' correction: the Jacobian is unchanged, the correction being fixed)."""
        shift = np.asarray(shift, np.float64)
        return dataclasses.replace(self, pred=self.pred + shift, r=self.r + shift)

    def point(self) -> lsq.Point:
        """The least-squares core's view: the integrator's error sets the floor of a
        meaningful decrease only where its steps adapt (their choice makes the error jump
        between nearby parameters; eq 23's fixed steps give a smooth bias instead)."""
        err = float(self.error_um) if self.adaptive and math.isfinite(self.error_um) else 0.0
        return lsq.Point(u=self.u, r=self.r, predicted=self.pred, J=self.J,
                         r_prior=self.r_prior, J_prior=self.J_prior, usable=self.usable,
                         error_um=err, extra=self, why=self.why)


def _rows_and_aux(model: ResidualModel, v):
    """((rows, snapshots), aux) at v: what both Jacobian programs differentiate, with the
    run's checks (max residual, worn-through cycle, sliding distance, error [µm], steps,
    attempts: the most accepted plus rejected steps of an experiment)."""
    snaps, res = model.snapshots(v)
    rows = model.predict_from(snaps, v)
    aux = (rows, snaps, jnp.max(res.max_residual), jnp.max(res.worn_through_cycle),
           res.sliding_distance, jnp.max(res.error_estimate) * 1e6, jnp.max(res.steps),
           jnp.max(res.steps + res.rejected_steps))
    return (rows, snaps), aux


ALL = -1  # `seeds`' owner of a column every row depends on
NONE = -2  # its owner for a column whose Jacobian is not computed (0)


def seeds(columns, wanted=None, width: int | None = None):
    """Forward-mode seeds of a Jacobian (Curtis-Powell-Reid compression): (S (P, K) float,
    color (P,) int, owner (P,) int). A per-experiment column (an experiment's clearance,
    its registration offset: `Column.experiment`) moves that experiment's rows and
    snapshots only, so those of distinct experiments share one tangent (the sum of their
    unit vectors), and each is read back from the rows of its own experiment (`owner`);
    every other column has a tangent of its own (owner `ALL`). `columns`: the packing's
    `Column`s (P); `wanted` (K,) indices: the columns computed (repeats allowed; the
    others `NONE`, 0 in the Jacobian); None: every column. `width`: K at least (zero
    tangents pad it: one program for every set of `wanted` of one length).

    Why: the experiments run one after another (`ResidualModel.snapshots`'s `lax.map`),
    and a dense tangent of one experiment's clearance carries zeros through every other
    experiment's wear loop at the full cost of a tangent. On the generator's fatigue study
    (5 experiments) the fits' K_d + 5 clearances take 2 tangents instead of 6, the law
    search's 11 columns 7."""
    P = len(columns)
    idx = list(range(P)) if wanted is None else list(dict.fromkeys(int(i) for i in wanted))
    color = np.zeros(P, np.int32)
    owner = np.full(P, NONE, np.int32)
    groups: list[list[int]] = []  # columns per tangent
    # per tangent: the experiments of its columns (None: one column every row depends on)
    shared: list[set] = []
    for j in idx:
        e = columns[j].experiment
        if e is None:
            owner[j] = ALL
            groups.append([j])
            shared.append(None)
            continue
        owner[j] = int(e)
        k = next((k for k, s in enumerate(shared) if s is not None and int(e) not in s), None)
        if k is None:
            groups.append([])
            shared.append(set())
            k = len(groups) - 1
        groups[k].append(j)
        shared[k].add(int(e))
    K = max(len(groups), width or 0, 1)
    S = np.zeros((P, K))
    for k, js in enumerate(groups):
        for j in js:
            S[j, k] = 1.0
            color[j] = k
    return S, color, owner


def width_of(columns, wanted) -> int:
    """The tangents `seeds` needs for `wanted` (K,) padded as its caller padded it: the
    length of `wanted` less what sharing saves among its distinct columns (the same for
    every law of the law search, whose padded sets share their per-experiment columns)."""
    distinct = list(dict.fromkeys(int(i) for i in wanted))
    used = seeds(columns, distinct)[0].shape[1]
    return len(wanted) - (len(distinct) - used)


def _seeded(model: ResidualModel, u, S, color, owner):
    """The Jacobian (rows, P) and that of the snapshots (E, S, N, P) at u by forward mode
    along the seeds `S` (P, K) (`seeds`), with the rows and the run's checks (aux)."""
    def g(v):
        return _rows_and_aux(model, v)

    _, (Jk, Jk_snaps), aux = jax.vmap(lambda t: jax.jvp(g, (u,), (t,), has_aux=True),
                                      in_axes=1, out_axes=(None, -1, None))(S)
    exp = model.data.exp  # (rows,) each row's experiment
    own = (owner[None, :] == ALL) | (owner[None, :] == exp[:, None])  # (rows, P)
    J = jnp.where(own, Jk[:, color], 0.0)
    E = Jk_snaps.shape[0]
    own_s = (owner[None, :] == ALL) | (owner[None, :] == jnp.arange(E)[:, None])  # (E, P)
    J_snaps = jnp.where(own_s[:, None, None, :], Jk_snaps[..., color], 0.0)
    return J, J_snaps, aux


@jit
def _evaluate_jit(model: ResidualModel, u):
    """Rows, snapshots and their Jacobians in every column of u (`seeds`: the columns of
    distinct experiments share a tangent)."""
    TRACES["jacobian"] += 1  # runs when traced only
    S, color, owner = seeds(model.packing.columns)  # the packing is static: constants
    return _seeded(model, u, jnp.asarray(S, u.dtype), jnp.asarray(color), jnp.asarray(owner))


@jit
def _evaluate_columns_jit(model: ResidualModel, u, S, color, owner):
    """`_evaluate_jit` with the Jacobian's columns chosen by `seeds` (its `wanted`, the
    others 0): forward mode costs one tangent per seed, and a fit that holds most columns
    (the law search's one model for every law, 10 law constants of which a law fits 1-5)
    pays for its free ones only. The seeds are data: one program for every set of the
    same width."""
    TRACES["jacobian"] += 1  # runs when traced only
    return _seeded(model, u, S, color, owner)


# The first run of an evaluation is given this many times its model's attempt count as
# the loop's (traced) bound. Why: the count is an estimate, and a run that did not reach
# the end was repeated whole at twice the count, its Jacobian (1 + tangents runs)
# included: on the generator's fatigue study (48 x 72) a diagnosis ran 3 of its 95
# Jacobian evaluations twice (one of the shape's refit: 6.6 s against ~2.7 s). Attempts
# after the end cost nothing (the loop stops), so a run that needs up to this many times
# the count now ends in one go, with the same steps, the same answer to the bit, and the
# model's count raised as the repeats would have raised it (`_raised`): what later
# comparisons read of it (`attempts.needs_more_attempts`) is unchanged. A run that cannot
# reach the end (a stiff trial) spends up to this many times the count before the
# doublings it would have taken: they are counted as taken. Never more than the caller's
# doublings allow (2^doublings: a fit's trial, allowed one, gets twice the count), so a
# run is usable exactly where the repeats would have made it so.
HEADROOM = 4


def _headroom(model: ResidualModel, factor: int) -> ResidualModel:
    """`_dynamic(model)` whose loop bound is `factor` times its attempt count (at most
    `MAX_ATTEMPTS`)."""
    dyn = _dynamic(model)
    if not model.schedule.adaptive or factor <= 1:
        return dyn
    bound = min(factor * model.schedule.attempts, MAX_ATTEMPTS)
    return dyn.with_schedule(dataclasses.replace(dyn.schedule, attempt_limit=to_device(
        np.full(np.shape(dyn.schedule.attempt_limit), bound, np.int32))))


def _raised(model: ResidualModel, used) -> ResidualModel:
    """`model` with its attempt count doubled until it holds `used` attempts (a finished
    run's most accepted plus rejected steps of an experiment): the count the repeated runs
    at twice the count would have left it with."""
    while model.schedule.adaptive and model.schedule.attempts < int(used):
        model = model.with_schedule(model.schedule.more_attempts())
    return model


def _jacobian_run(model: ResidualModel, u, cols):
    if cols is None:
        return _evaluate_jit(model, u)
    return _evaluate_columns_jit(model, u, *cols)


# a thread lowering the next level's program ahead (`Compiling`): a compilation is counted
# when that program is compiled, not when it is traced and perhaps never needed
_ahead = threading.local()


@jit
def _forward_jit(model: ResidualModel, u):
    """Rows [µm], snapshots [µm], worn-through cycle, error estimate [µm], steps: no
    Jacobian (a check of a linearised answer costs one plain run)."""
    if not getattr(_ahead, "lowering", False):
        TRACES["forward"] += 1  # runs when traced only (lowered ahead: when compiled)
    snaps, res = model.snapshots(u)
    return (model.predict_from(snaps, u), snaps, jnp.max(res.worn_through_cycle),
            jnp.max(res.error_estimate) * 1e6, jnp.max(res.steps))


def unusable_evaluation(model: ResidualModel, u, why: str) -> Evaluation:
    """An `Evaluation` of a model that was not run at u (`why`): rows, Jacobian and
    snapshots NaN (shapes from a trace, no compilation), not usable."""
    uj = jnp.asarray(u, jnp.float64)
    shape = pytree.filter_eval_shape(lambda m, v: m.snapshots(v)[0], _dynamic(model), uj).shape
    n, P = model.n_data, model.packing.size
    r_prior, J_prior = model.prior_rows(np.asarray(u, np.float64))
    return Evaluation(u=np.asarray(u, np.float64), pred=np.full(n, np.nan),
                      r=np.full(n, np.nan), J=np.full((n, P), np.nan), r_prior=r_prior,
                      J_prior=J_prior, snaps=np.full(shape, np.nan),
                      J_snaps=np.full(shape + (P,), np.nan), max_residual=math.nan,
                      worn=-1.0, sliding_m=np.full(shape[0], np.nan), error_um=math.inf,
                      steps=0, adaptive=model.schedule.adaptive, failure=why)


def chunks(columns, wanted, width: int) -> list[list[int]]:
    """`wanted`'s distinct columns (indices) in consecutive parts that need at most `width`
    tangents each (`seeds`: the columns of distinct experiments share one); a column that
    alone needs more is a part of its own."""
    parts: list[list[int]] = []
    for j in dict.fromkeys(int(i) for i in wanted):
        if parts and seeds(columns, parts[-1] + [j])[0].shape[1] <= width:
            parts[-1].append(j)
        else:
            parts.append([j])
    return parts


def evaluate(model: ResidualModel, u, *, doublings: int = 3, columns=None,
             width: int | None = None) -> tuple[Evaluation, ResidualModel]:
    """The model at u with its Jacobian, and the model it ran (its attempt count raised
    where u needed more: a fit keeps it, so later trials neither repeat a short run nor
    recompile). Where the work estimate at u is not finite the model is not run: an
    unusable `Evaluation` saying why (a fit rejects it as a trial). `columns`: the
    Jacobian's columns computed (indices (K,), one repeated to pad), the others 0
    (`_evaluate_columns_jit`); None: every column. `width`: the program's tangents (with
    `columns`): columns that need more are computed in parts of that width (`chunks`),
    one run each of the same program at the same u, their Jacobians added (each part's
    other columns are 0). Why: two uses of one model with different column sets (the
    shape's surface columns and its refit, `shape.analysis`) then share one compilation
    instead of two (~6 s of CPU each on 2 cores)."""
    if columns is not None and width is not None:
        parts = chunks(model.packing.columns, columns, width)
        if len(parts) > 1:
            ev, model = _evaluate(model, u, doublings, parts[0], width)
            for part in parts[1:]:
                if not ev.usable:
                    break
                more, model = _evaluate(model, u, doublings, part, width)
                # the same run again (same u, same program): only its tangents are new
                ev = dataclasses.replace(more, J=ev.J + more.J,
                                         J_snaps=ev.J_snaps + more.J_snaps)
            return ev, model
    return _evaluate(model, u, doublings, columns, width)


def _evaluate(model: ResidualModel, u, doublings: int, columns, width: int | None
              ) -> tuple[Evaluation, ResidualModel]:
    need = attempts_needed(model, u)
    if not math.isfinite(need):
        return unusable_evaluation(model, u, work_failure(model, u)), model
    model = enough_attempts(model, u, need=need)
    uj = jnp.asarray(u, jnp.float64)
    cols = None
    if columns is not None:
        S, color, owner = seeds(model.packing.columns, columns,
                                width if width is not None
                                else width_of(model.packing.columns, columns))
        cols = (to_device(S), to_device(color), to_device(owner))  # no compilation
    a0, room = model.schedule.attempts, min(HEADROOM, 2 ** max(doublings, 0))
    out = _jacobian_run(_headroom(model, room), uj, cols)
    # The attempt count is an estimate: where the loop did not reach the end (a stiff
    # layer's rejections), double it (a traced bound: no recompilation) rather than use a
    # truncated history. Not where no experiment took a single step: a model that is not
    # finite at u (a parameter, an effect's hook) rejects every step whatever the count
    # (measured: three doublings to 512 attempts 3.4 s, where one run takes 0.03 s).
    # Where one doubling is not enough, the count that reaches the end is found by forward
    # runs and the Jacobian run once more at it: a run that does not reach the end uses
    # every attempt, and the Jacobian's costs 1 + P tangents. Measured (issue 48): the
    # shape's refit on the fatigue study (51 columns) never reached the end; its three
    # doubled Jacobian runs (2 + 4 + 8 x the first's length) were ~60 s of CPU per refit
    # of a cold `diagnose --shape`. The first doublings are the first run's own headroom
    # (`HEADROOM`): most raises end there, and forward runs first would compile the model's
    # forward program (3 more compilations on the g_step_p_power_v study, each longer than
    # the run saved).
    left = doublings
    if np.isfinite(float(out[2][5])):
        model = _raised(model, out[2][7])
    elif _unfinished(model, out[2][5], out[2][6]):
        # the doublings the headroom stood for, counted as taken (`HEADROOM`)
        while left > 0 and 2 * model.schedule.attempts <= min(room * a0, MAX_ATTEMPTS):
            model = model.with_schedule(model.schedule.more_attempts())
            left -= 1
    while left > 0 and _unfinished(model, out[2][5], out[2][6]):
        reached = False
        while left > 0:
            model = model.with_schedule(model.schedule.more_attempts())
            left -= 1
            f = _forward_jit(_dynamic(model), uj)
            if np.isfinite(float(f[3])):
                reached = True
                break
            if int(f[4]) == 0:  # no step at all: no count reaches the end (above)
                left = 0
        if not reached:
            break
        out = _jacobian_run(_dynamic(model), uj, cols)
    J, J_snaps, (rows, snaps, mres, worn, sliding, err, steps, _) = jax.tree.map(np.asarray,
                                                                                 out)
    u = np.asarray(u, np.float64)
    meas = model.measured
    r = rows - meas
    if not np.isfinite(float(err)):
        r = np.full_like(r, np.nan)  # a truncated history is not a model evaluation
    r_prior, J_prior = model.prior_rows(u)
    return Evaluation(u=u, pred=rows, r=r, J=J, r_prior=r_prior, J_prior=J_prior, snaps=snaps,
                      J_snaps=J_snaps, max_residual=float(mres), worn=float(worn),
                      sliding_m=sliding, error_um=float(err), steps=int(steps),
                      adaptive=model.schedule.adaptive), model


def _unfinished(model: ResidualModel, err, steps) -> bool:
    """A run of an adaptive model that took steps but did not reach the end (its error
    estimate `err` not finite): more attempts may reach it."""
    return bool(model.schedule.adaptive and not np.isfinite(float(err)) and int(steps) > 0)


@dataclass(frozen=True)
class Forward:
    """A forward run (no Jacobian): `rows` (rows,) and `snaps` (E, S, N) [µm], NaN where the
    model wore through or its integration did not reach the end; `error_um` the worst
    experiment's integration error estimate, `steps` the longest one's accepted steps,
    `model` the model it ran (its attempt count raised where needed)."""

    rows: np.ndarray
    snaps: np.ndarray
    error_um: float
    steps: int
    model: ResidualModel

    @property
    def usable(self) -> bool:
        return bool(np.all(np.isfinite(self.rows)))


def forward_run(model: ResidualModel, u, *, doublings: int = 3, worn_ok: bool = False
                ) -> Forward:
    """The model at u without the Jacobian (`Forward`); `worn_ok`: keep the rows and
    snapshots of a run that wore through (a forecast past the layer). Where the work
    estimate at u is not finite the model is not run: NaN rows and snapshots, error inf."""
    need = attempts_needed(model, u)
    if not math.isfinite(need) or need > MAX_ATTEMPTS:
        ev = unusable_evaluation(model, u, work_failure(model, u) if not math.isfinite(need)
                                 else too_stiff(need))
        return Forward(ev.pred, ev.snaps, math.inf, 0, model)
    model = enough_attempts(model, u, need=need)
    uj = jnp.asarray(u, jnp.float64)
    out = _forward_jit(_dynamic(model), uj)
    for _ in range(doublings):
        if not (model.schedule.adaptive and not np.isfinite(float(out[3]))):
            break
        model = model.with_schedule(model.schedule.more_attempts())
        out = _forward_jit(_dynamic(model), uj)
    rows, snaps, worn, err, steps = (np.asarray(x) for x in out)
    if (float(worn) >= 0 and not worn_ok) or not np.isfinite(float(err)):
        rows, snaps = np.full(rows.shape, np.nan), np.full(snaps.shape, np.nan)
    return Forward(rows, snaps, float(err), int(steps), model)


class Compiling:
    """`_forward_jit` of a model compiled in a daemon thread (`compile_forward`); `wait()`
    joins it. Why: a fit at the coarsest resolution then checks its answer by one forward
    run at the next finer level (design.md §6), a program of its own (~1.3-1.8 s of a cold
    answer on 2 cores, most of it XLA's compile, which releases the interpreter): compiled
    while the coarse fit compiles and runs, it is ready when the check comes. The same CPU
    time, less wall time where a core is free. A failure here is left to the real call to
    meet and report.

    When (measured on the rig study's and the boom's calibrations, 2 cores):
    - `trace_after`: the tracing and lowering wait for these events. They hold the
      interpreter: beside the fit's own tracing of its Jacobian program they only slow it
      down (0.66 s alone, 1.16 s beside the check's); during its XLA compilation they
      cost it nothing.
    - `compile_after`: XLA's compilation waits for these. XLA:CPU's compilations in two
      threads partly wait for each other: a program of the fit's least-squares core
      (compiled in ~0.05 s) took 0.6 s beside a forward program's compilation, and the
      boom's first step 1.5 s instead of 0.9 s. Compiled while the fit only runs its
      model, the program costs the fit nothing.
    `cancel()`: a program not needed any more is not started (one whose compilation is
    under way finishes in the background)."""

    def __init__(self, build, trace_after=(), compile_after=(), core=None, ahead=None,
                 prev: Compiling | None = None):
        self._cancelled = False
        self.next = None  # `ahead`'s program, lowered: (lowered, model, u)
        self.ready = threading.Event()  # this program compiled (or given up)

        def lower(make):
            model = _dynamic(make())
            if not model.schedule.adaptive:
                return None  # eq 23's loop has no bound to set to 0: it would run in full
            # a loop bound of 0 attempts: the program as the check runs it (the bound is
            # traced), run for nothing where it is not compiled ahead
            limit = to_device(np.zeros(np.shape(model.schedule.attempt_limit), np.int32))
            model = model.with_schedule(dataclasses.replace(model.schedule,
                                                            attempt_limit=limit))
            u = to_device(np.zeros(model.packing.size), np.float64)
            return _forward_jit.lower(model, u), model, u

        def run():
            for ev in trace_after:
                ev.wait()
            if self._cancelled:
                return
            try:
                if prev is not None:
                    prev.join()
                program = prev.next if prev is not None and prev.next else lower(build)
                if program is None:
                    return
                # the core's programs: their tracing runs small programs, which wait for
                # the fit's compilation to end
                first = [] if core is None else lsq.lower_core(*core)
                for ev in compile_after:
                    ev.wait()
                if self._cancelled:
                    return
                for low in first:
                    low.compile()
                lowered, model, u = program
                try:
                    lowered.compile()
                except Exception:  # noqa: BLE001 (an option this jaxlib lacks: the call
                    jax.block_until_ready(_forward_jit(model, u))  # finds out and drops it)
                if prev is not None and program is prev.next:
                    TRACES["forward"] += 1  # lowered ahead, compiled now
                self.ready.set()
                if ahead is not None and not self._cancelled:
                    _ahead.lowering = True
                    try:
                        self.next = lower(ahead)
                    finally:
                        _ahead.lowering = False
            except Exception:  # noqa: BLE001 (the check's own call reports it)
                pass
            finally:
                self.ready.set()

        self._job = Background(run)

    def wait(self) -> None:
        """Until this program is compiled (not what it lowers ahead)."""
        self.ready.wait()

    def join(self) -> None:
        """Until the thread has ended (what it lowers ahead included)."""
        self._job.join()

    def cancel(self) -> None:
        self._cancelled = True

    def compile_next(self, build) -> Compiling:
        """The program `ahead` lowered, compiling in a daemon thread once this one is done
        (`build`'s, traced then, where it was not lowered)."""
        return Compiling(build, prev=self)


def compile_forward(build, trace_after=(), compile_after=(), core=None, ahead=None
                    ) -> Compiling:
    """Start compiling the forward run of the model `build()` returns (a `ResidualModel`
    with an adaptive schedule) in a daemon thread (`Compiling`): traced once every event
    of `trace_after` is set, compiled once every one of `compile_after` is; `core`: (rows,
    free) of a fit whose least-squares core's programs are compiled first
    (`lsq.lower_core`); `ahead`: a builder whose forward program is then traced and
    lowered, not compiled (`Compiling.compile_next` compiles it)."""
    return Compiling(build, tuple(trace_after), tuple(compile_after), core, ahead)


def forward(model: ResidualModel, u, *, doublings: int = 3):
    """Rows [µm] and snapshots [µm] at u without the Jacobian, NaN where the model wore
    through or its integration did not reach the end; and the model it ran."""
    f = forward_run(model, u, doublings=doublings)
    return f.rows, f.snaps, f.error_um, f.model


def unusable_point(model: ResidualModel, u, why: str = "") -> lsq.Point:
    """A trial a fit declines to evaluate (`why`): rejected as unusable."""
    n, P = model.n_data, model.packing.size
    r_prior, J_prior = model.prior_rows(u)
    return lsq.Point(u=np.asarray(u, np.float64), r=np.full(n, np.inf),
                     predicted=np.full(n, np.nan), J=np.zeros((n, P)), r_prior=r_prior,
                     J_prior=J_prior, usable=False, why=why)


def integration_report(model: ResidualModel, ev: Evaluation) -> dict:
    """The `"integration"` block of a fit's JSON (same keys as `simulate`'s)."""
    sched = model.schedule
    tol = sched.tolerance_um
    err = float(ev.error_um)
    return {"integrator": "adaptive" if sched.adaptive else "paper",
            "error_estimate_um": err if math.isfinite(err) else "inf",
            "steps": int(ev.steps), "tolerance_um": tol}
