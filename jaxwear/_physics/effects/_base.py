"""The effect interface: a candidate piece of physics the base model may be missing (§5).

An effect is a small stateless pytree (a `_core.pytree.Struct`) with a name, parameters
(study keys with units, defaults, bounds) and up to three hooks into the wear loop. Every
hook's default is the identity, and the wear loop never calls an effect that is switched
off, so a disabled effect leaves results bit-for-bit unchanged. Strength parameters at
their `off` value give the base model too (nesting), which is what makes score tests and
likelihood ratios valid.

Writing your own takes a subclass, its parameters and one hook (docs/effects.md has the
full walk-through, calibration/examples/custom_effect.py a runnable example):

    class Humidity(Effect):
        name = "humidity"
        parameters = {"humidity_gain": EffectParameter(1.0, 0.0, 0.0, -0.5, 5.0, "...",
                                                       scale=0.1, realistic=0.2)}
        signature = "uniform extra wear, proportional to sliding"

        def local_rate(self, p, rate, ctx):
            return rate * (1 + p.effect_params["humidity_gain"])

    register_effect(Humidity())

Register effects before building parameters (`preset`, `load_study`): `Params` carries a
strength for every effect registered at the time it is built.
"""

from __future__ import annotations

import contextlib
import contextvars
from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree
from jaxwear._physics.effects.parameter import EffectParameter
from jaxwear._physics.effects.structural import STRUCTURAL_CANDIDATES


class RateContext(pytree.Struct):
    """What a local wear-rate hook may use, for one cycle (all SI).

    `pressure` (steps, nodes) [Pa]; `slide` dS_i (steps,) [m]; `dt` Δt_i (steps,) [s];
    `sliding_distance` S at the start of the block [m]; `load_angle` θ_W (steps,) [rad],
    the direction of the joint load in the bushing frame (its turn rate marks impacts at
    force reversals; `effects.shape.state_variables` computes it and the others); `load`
    |W_i| (steps,) [N]; `worn_depth` h_j (nodes,) [m], the profile this cycle wears on
    (the depth already worn at each node: the surface's own state, `worn_depth_um` of
    `state_variables`). Extra wear not tied to sliding (a deposit where the pin presses)
    is added to the rate with `effects.shape.swept_kernel(load_angle, nodes)`; `swept`
    (steps, nodes) [1/rad] is that kernel computed once per run, where the effect sets
    `uses_swept_kernel = True` (else None): it depends on the load history only, and
    computed in the hook it is recomputed at every stage of every step (the law search's
    deposit evaluations: 5.7 s against 0.6 s for a factor at 48 x 72). `memory`
    (states, nodes) [-]: the effect's own hidden per-node states (`Effect.memory_states`
    of them) at this cycle, None for an effect without.
    """

    pressure: object
    slide: object
    dt: object
    sliding_distance: object
    load_angle: object = None
    load: object = None
    worn_depth: object = None
    swept: object = None
    memory: object = None


class Effect(pytree.Struct):
    """Base of all effects. Subclasses set `name`, `parameters`, `signature` and override
    any of the hooks below. They hold no state: their strengths live in
    `Params.effect_params` under the study keys of `parameters`.

    Hooks (each optional; the base model is the identity of all three):
    - `friction(p, sense)`: Coulomb coefficient times sliding sense per step (steps,), or
      None. Friction coefficients of several effects add.
    - `local_rate(p, rate, ctx)`: wear per step and node [m] (steps, nodes); receives the
      base Archard rate K_d p_ij dS_i (or the previous effect's output) and returns it
      modified.
    - `block_factor(p, sliding_start, sliding_per_cycle, cycles)`: multiplier of a block of
      `cycles` cycles' wear, for effects that depend on the history (S at the block start
      [m], sliding per cycle [m]).
    - `cycles_at(p, sliding_start, sliding_per_cycle, clock)`: optional inverse of the
      block factor's clock τ(n) = n · block_factor(p, S₀, s, n) (the factor integrated over
      n cycles): the n with τ(n) = `clock`, or None (the default). An effect that gives it
      is the adaptive wear loop's clock: the loop steps in τ, where dh/dτ has no factor, so
      a large, fast-decaying factor (running-in) costs no steps (`_wear._adaptive_trace`).
      Only one such effect at a time is a clock.
    - `memory_rate(p, ctx)`: for an effect with `memory_states` = m > 0 hidden per-node
      states s (a damage, a film: docs/effects.md, "Laws with memory"), ds/dN per cycle
      (m, nodes) at the states `ctx.memory` (m, nodes) and this cycle's contact. The wear
      loop integrates them with the depth (the same steps; states 0 on a new bore), and
      `local_rate` reads them in `ctx.memory`. `memory_stiffness(p)` bounds |∂(ds/dN)/∂s|
      [1/cycle] (the explicit integrator's stability limit counts it).
    """

    name: ClassVar[str] = ""
    parameters: ClassVar[dict[str, EffectParameter]] = {}
    signature: ClassVar[str] = ""
    structural: ClassVar[bool] = False
    memory_states: ClassVar[int] = 0

    def friction(self, p, sense):
        """Coulomb coefficient times sliding sense per step, or None (no friction)."""
        return None

    def local_rate(self, p, rate, ctx: RateContext):
        """Wear per step and node [m], (steps, nodes). Base model: K_d p_ij dS_i."""
        return rate

    def block_factor(self, p, sliding_start, sliding_per_cycle, cycles):
        """Multiplier of a block of `cycles` cycles' wear (profile frozen within the block)."""
        return jnp.ones(())

    def cycles_at(self, p, sliding_start, sliding_per_cycle, clock):
        """Cycles n whose clock n · block_factor(p, S₀, s, n) is `clock`, or None (no clock)."""
        return None

    def memory_rate(self, p, ctx: RateContext):
        """ds/dN (memory_states, nodes) [1/cycle] of the hidden states (none by default)."""
        return jnp.zeros((0, ctx.pressure.shape[1]))

    def memory_stiffness(self, p):
        """Bound on |∂(ds/dN)/∂s| [1/cycle] (0: the states do not feed back on themselves)."""
        return jnp.zeros(())

    @classmethod
    def strength_keys(cls) -> tuple[str, ...]:
        """Keys of the nested strength parameters (linear, `off` gives the base model)."""
        return tuple(k for k, s in cls.parameters.items() if not s.log)

    @classmethod
    def shape_keys(cls) -> tuple[str, ...]:
        """Keys of the shape parameters (log-fitted, identifiable only with the strength on)."""
        return tuple(k for k, s in cls.parameters.items() if s.log)


_REGISTRY: dict[str, Effect] = {}
# effects registered for one context only (`scoped_effects`), after the registry's own
_SCOPED: contextvars.ContextVar[tuple] = contextvars.ContextVar("jaxwear_scoped_effects",
                                                                default=())


def _effects() -> dict[str, Effect]:
    """The registry as this context sees it: every effect registered, then its scoped ones."""
    scoped = _SCOPED.get()
    if not scoped:
        return _REGISTRY
    out = dict(_REGISTRY)
    out.update((e.name, e) for e in scoped)
    return out


def _checked(effect: Effect, known: dict[str, Effect]) -> None:
    """Raise `ValueError` naming what `effect` lacks that the fitting machinery relies on, or
    a parameter it shares with another of the `known` effects."""
    name = effect.name
    if not name or not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"an effect needs a `name` that is an identifier, got {name!r}")

    if name in STRUCTURAL_CANDIDATES:
        raise ValueError(f"effect name {name!r} is taken by a structural candidate")
    if not effect.strength_keys():
        raise ValueError(f"effect {name}: needs a strength parameter (log=False) whose `off` "
                         f"value gives the base model")
    taken = {k: e.name for e in known.values() if e.name != name for k in e.parameters}
    for key, spec in effect.parameters.items():
        if key in taken:
            raise ValueError(f"effect {name}: parameter {key!r} already belongs to effect "
                             f"{taken[key]!r}")
        if not (spec.lower <= spec.default <= spec.upper):
            raise ValueError(f"effect {name}: default of {key} outside its bounds")
        if not (spec.lower <= spec.off <= spec.upper):
            raise ValueError(f"effect {name}: off value of {key} outside its bounds")
        if not spec.scale > 0 or not spec.to_si > 0:
            raise ValueError(f"effect {name}: {key} needs scale > 0 and to_si > 0")
        if spec.log and not (spec.lower > 0 and spec.default > 0):
            raise ValueError(f"effect {name}: log-fitted {key} needs lower > 0 and default > 0")
        if spec.realistic is not None and not (spec.lower <= spec.realistic <= spec.upper):
            raise ValueError(f"effect {name}: realistic value of {key} outside its bounds")


def register_effect(effect: Effect) -> Effect:
    """Make an effect available by name to studies, `calibrate`, `diagnose` and `synth`.

    Checks what the fitting machinery relies on: a name, at least one strength parameter,
    defaults and `off` values within bounds, positive scales, and log parameters > 0.
    Raises `ValueError` naming the problem.
    """
    _checked(effect, _effects())
    _REGISTRY[effect.name] = effect
    return effect


@contextlib.contextmanager
def scoped_effects(*effects: Effect):
    """`effects` registered (checked as `register_effect` does) for the code this context
    runs, and for the threads it starts through `_core.background.in_context` and the
    helpers that use it, until the block ends; every other thread sees the registry
    without them.

    Why (issue 50): diagnose's law search registers its grammar's effects while other
    threads build models beside it (the shape's refit, programs compiled ahead). With the
    registry process-wide, a model built meanwhile carried their strengths (unused, at
    off) or not, by the threads' timing: another pytree, whose programs compiled again."""
    known = _effects()
    for eff in effects:
        if known.get(eff.name) is not eff:
            _checked(eff, known)
            known = {**known, eff.name: eff}
    token = _SCOPED.set(_SCOPED.get() + tuple(effects))
    try:
        yield
    finally:
        _SCOPED.reset(token)


def unregister_effect(name: str) -> None:
    """Remove an effect from the registry (tests, notebooks). Studies and `Params` built
    while it was registered keep its keys; build new ones after removing it."""
    _REGISTRY.pop(name, None)


def get_effect(name: str) -> Effect:
    return _effects()[name]


def registered_effects() -> dict[str, Effect]:
    return dict(_effects())


def effect_parameter_specs() -> dict[str, EffectParameter]:
    out = {}
    for eff in _effects().values():
        out.update(eff.parameters)
    return out


def product_pairs(keys) -> list[tuple[int, int]]:
    """(i, j) for every fitted key i whose `per` names another fitted key j (see
    `EffectParameter.per`): the fit then uses value_i = linear_i · exp(-u_j)."""
    specs = effect_parameter_specs()
    keys = list(keys)
    return [(i, keys.index(specs[k].per)) for i, k in enumerate(keys)
            if k in specs and specs[k].per is not None and specs[k].per in keys]


def project_products(keys, start, scale, u):
    """u with each product strength's value (linear·exp(-u_per), see `product_pairs`)
    clipped into its [lower, upper] by its linear coordinate (numpy)."""
    specs = effect_parameter_specs()
    u = np.array(u, np.float64)
    for i, j in product_pairs(keys):
        sp = specs[keys[i]]
        lin = (start[i] + scale[i] * u[i])
        val = np.clip(lin * np.exp(-u[j]), sp.lower, sp.upper)
        u[i] = (val * np.exp(u[j]) - start[i]) / scale[i]
    return u


def safe_power(x, exponent):
    """x**exponent for x ≥ 0 with finite gradients at x = 0 (where the result is 0)."""
    pos = x > 0
    return jnp.where(pos, jnp.where(pos, x, 1.0) ** exponent, 0.0)


# Where each effect registered from a file came from: name -> (path, effect). Filled by the
# study layer's effect-file loader; read here so that a failure deep in a run can name the file.
EFFECT_ORIGINS: dict = {}


def file_effects(names) -> list[str]:
    """"NAME (from FILE)" for each of the effect `names` registered from an effect file: a
    run that fails with them switched on names them (a NaN from a hook at a strength the
    load-time check did not try surfaces as a contact solve that does not converge)."""
    out = []
    for name in names:
        entry = EFFECT_ORIGINS.get(name)
        if entry is not None and registered_effects().get(name) is entry[1]:
            out.append(f"{name} (from {entry[0]})")
    return out
