"""An effect from a file, tried once on a small cycle before it is registered (issue 41).

A hook that is wrong failed only deep inside a run, and never named its file: a
`local_rate` of the wrong shape as `TypeError: dot_general requires contracting dimensions
...`, one that raised as its bare message, one that returned NaN as "the contact solve did
not converge ... please report" (or, NaN even when off and loaded as a diagnose candidate,
as K_d halved 8 times at ~40 s an evaluation), one that returned negative wear as exit 0
with negative depths.

`check_effect` calls each hook once, compiled as the wear loop runs it, at each strength
setting the effect will be run at first: `off` (the base model: diagnose's score test
differentiates there), `default`, `realistic` (what `synth` hides) and, where those all
coincide, `off` plus one `scale` (an effect switched on). The cycle is 6 steps x 8 nodes
of a plausible joint (a pressure bump of 2 MPa that turns with the load, 0.1 mm of sliding
and 10 ms a step, at the start of a run and after 5 m of sliding); the answers must be:

- `local_rate`: shape (steps, nodes), finite, and >= 0 (wear per step [m]: a hook may lower
  the Archard rate, never below zero; below zero is material added);
- `friction`: None, or finite of shape () or (steps,);
- `block_factor`: a finite scalar >= 0 (a multiplier of wear);
- `cycles_at`: None, or a finite scalar;
- for an effect with hidden states (`memory_states` = m > 0, tried at s = 0.5 on every
  node), `memory_rate`: finite, of shape (m, nodes); `memory_stiffness`: a finite scalar
  >= 0.

A failure is an `InputError` naming the file, the line (in the file where the hook raised,
else the class's), the class and hook, the strengths and what was wrong. Each hook is
traced by `jax.jit` once for all settings, as the wear loop runs it (Python control flow on
a traced strength fails here, at load); about as long as eager calls, whose every primitive
compiles on its own (0.4-2.6 s for each of the two effects of tests/test_effect_files.py on
a loaded 2-core host, mostly compilation).
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree
from jaxwear._core.errors import InputError
from jaxwear._physics.cycle import archard_rate
from jaxwear._physics.effects._base import Effect, RateContext
from jaxwear._physics.effects.shape import swept_kernel
from jaxwear._physics.params import preset

STEPS, NODES = 6, 8
PEAK_PA = 2e6  # peak contact pressure of the test cycle [Pa]
SLIDE_M, DT_S = 1e-4, 0.01  # sliding [m] and time [s] per step
SLID_M = (0.0, 5.0)  # sliding distance at the block's start [m]
CYCLES = 100.0  # cycles of a block


def _cycle():
    """(pressure, slide, dt, load angle, load) of the test cycle (module docstring)."""
    theta = 2 * np.pi * np.arange(NODES) / NODES
    angle = np.linspace(0.3, 1.2, STEPS)
    pressure = PEAK_PA * np.maximum(np.cos(theta[None, :] - angle[:, None]), 0.0) ** 2
    return (jnp.asarray(pressure), jnp.full(STEPS, SLIDE_M), jnp.full(STEPS, DT_S),
            jnp.asarray(angle), jnp.full(STEPS, 1000.0))


def strength_settings(eff: Effect) -> list[tuple[str, dict[str, float]]]:
    """(label, {key: value in the key's unit}) of the settings `check_effect` tries."""
    specs = eff.parameters
    shapes = {k: s.default for k, s in specs.items() if s.log}

    def setting(pick):
        return {**{k: float(pick(s)) for k, s in specs.items() if not s.log}, **shapes}

    out = [("off", setting(lambda s: s.off)), ("default", setting(lambda s: s.default))]
    if all(s.realistic is not None for k, s in specs.items() if not s.log):
        out.append(("realistic", setting(lambda s: s.realistic)))
    if all(v == out[0][1] for _, v in out[1:]):  # never on: one scale up from off
        out.append(("on (off + scale)", setting(
            lambda s: min(max(s.off + s.scale, s.lower), s.upper))))
    seen, unique = [], []
    for label, values in out:
        if values not in seen:
            seen.append(values)
            unique.append((label, values))
    return unique


def check_effect(path, eff: Effect, class_line: int) -> None:
    """Call every hook of `eff` on the test cycle at each of `strength_settings`; raise
    `InputError` (file, line, class, hook, what was wrong) at the first bad answer."""
    base = preset("rig")
    params = dict(base.effect_params)
    for k, s in eff.parameters.items():
        params[k] = jnp.asarray(s.default * s.to_si, jnp.float64)
    base = pytree.replace(base, effect_params=params)
    pressure, slide, dt, angle, load = _cycle()
    # as the wear loop gives them: the kernel where the effect asks for it (else None)
    swept = swept_kernel(angle, NODES) if getattr(eff, "uses_swept_kernel", False) else None
    rate = archard_rate(base, pressure, slide)
    sense = jnp.where(jnp.arange(STEPS) % 2 == 0, 1.0, -1.0)
    name = type(eff).__name__
    # each hook compiled once (the settings share its shapes) and run as the wear loop runs
    # it, traced: Python control flow on a strength fails here, not an hour into a fit
    jitted = {hook: jax.jit(lambda p, *a, hook=hook: getattr(eff, hook)(p, *a))
              for hook in ("friction", "local_rate", "block_factor", "cycles_at",
                           "memory_rate", "memory_stiffness")}
    m = int(getattr(eff, "memory_states", 0))
    memory = jnp.full((m, NODES), 0.5) if m else None
    for label, values in strength_settings(eff):
        p = base.with_values({k: v * eff.parameters[k].to_si for k, v in values.items()})
        at = f"at {label} ({', '.join(f'{k} = {v:g}' for k, v in values.items())})"

        def fail(hook, what, line=class_line):
            raise InputError(f"{path}: line {line}: {name}.{hook} {at} {what} (each hook is "
                             f"tried on a small cycle when the file is loaded, "
                             f"docs/effects.md)")

        def call(hook, *args):
            try:
                return jitted[hook](p, *args)
            except Exception as e:
                msg = " ".join(str(e).split()) or "(no message)"
                if isinstance(e, jax.errors.ConcretizationTypeError):  # JAX's text names ours
                    msg = ("Python control flow (if, while, float(), int()) on a traced "
                           "value; the hooks run inside jax.jit: write it with jnp.where")
                fail(hook, f"raised {type(e).__name__}: {msg}",
                     _line_in(e, Path(path).resolve(), class_line))

        mu = call("friction", sense)
        if mu is not None:
            mu = _array(mu)
            if mu is None or mu.shape not in ((), (STEPS,)):
                fail("friction", f"returned {_shape(mu)}; expected None or the Coulomb "
                                 f"coefficient times the sliding sense per step, shape () or "
                                 f"(steps,) = ({STEPS},)")
            _finite(fail, "friction", mu, "coefficient")
        for slid in SLID_M:
            ctx = RateContext(pressure, slide, dt, jnp.asarray(slid), angle, load,
                              jnp.zeros(NODES), swept, memory)
            if m:
                ds = _array(call("memory_rate", ctx))
                if ds is None or ds.shape != (m, NODES):
                    fail("memory_rate", f"returned {_shape(ds)}; expected ds/dN of its "
                                        f"states, shape (memory_states, nodes) = ({m}, "
                                        f"{NODES})")
                _finite(fail, "memory_rate", ds, "rate [1/cycle]")
                st = _array(call("memory_stiffness"))
                if st is None or st.size != 1 or not float(st.reshape(())) >= 0:
                    fail("memory_stiffness", "expected a finite scalar >= 0 [1/cycle]")
                _finite(fail, "memory_stiffness", st, "rate [1/cycle]")
            out = _array(call("local_rate", rate, ctx))
            if out is None or out.shape != (STEPS, NODES):
                fail("local_rate", f"returned {_shape(out)}; expected the wear per step and "
                                   f"node, shape (steps, nodes) = ({STEPS}, {NODES}), like its "
                                   f"`rate` argument")
            _finite(fail, "local_rate", out, "wear [m]")
            if np.min(out) < 0:
                fail("local_rate", f"returned negative wear (down to {np.min(out):.3g} m in a "
                                   f"step where the Archard rate is >= 0); expected wear >= 0 "
                                   f"(a hook may lower the rate, never below 0: that is "
                                   f"material added)")
            bf = _array(call("block_factor", jnp.asarray(slid), jnp.asarray(STEPS * SLIDE_M),
                             jnp.asarray(CYCLES)))
            if bf is None or bf.size != 1:
                fail("block_factor", f"returned {_shape(bf)}; expected a scalar multiplier")
            _finite(fail, "block_factor", bf, "factor")
            if float(bf.reshape(())) < 0:
                fail("block_factor", f"returned {float(bf.reshape(())):.3g}; expected a "
                                     f"multiplier of wear >= 0")
            n = call("cycles_at", jnp.asarray(slid), jnp.asarray(STEPS * SLIDE_M),
                     jnp.asarray(CYCLES))
            if n is not None:
                n = _array(n)
                if n is None or n.size != 1:
                    fail("cycles_at", f"returned {_shape(n)}; expected None or a scalar")
                _finite(fail, "cycles_at", n, "cycle count")


def _array(x):
    """`x` as a NumPy float array, or None if it is not numbers."""
    try:
        return np.asarray(x, np.float64)
    except (TypeError, ValueError):
        return None


def _shape(x) -> str:
    return "something that is not an array of numbers" if x is None else f"shape {x.shape}"


def _finite(fail, hook, x, what) -> None:
    bad = ~np.isfinite(x)
    if np.any(bad):
        kinds = "/".join(k for k, m in (("NaN", np.isnan(x)), ("inf", np.isinf(x))) if m.any())
        fail(hook, f"returned {kinds} at {int(bad.sum())} of {x.size} entries; expected a "
                   f"finite {what}")


def _line_in(exc: BaseException, filename: Path, default: int) -> int:
    """Line of the innermost traceback frame in `filename`, else `default`."""
    line, tb = default, exc.__traceback__
    while tb is not None:
        if Path(tb.tb_frame.f_code.co_filename) == filename:
            line = tb.tb_lineno
        tb = tb.tb_next
    return line


