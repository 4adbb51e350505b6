"""jaxwear's own programs (`jaxwear._core.jit`): compiled with per-program XLA options in a
plain `import jaxwear` (the user's process flags untouched), the same answers through
`jax.grad` / `jax.vmap` / a user's `jax.jit`, a logged fallback where the compiler refuses
an option; and `import jaxwear` does not import what only some verbs need."""

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._core import jit as J
from jaxwear._physics.wear import _wear_loop_jit, build_schedule

ROOT = Path(__file__).resolve().parents[1]

# In a fresh process: what `import jaxwear` imported, then one small run through the wear
# loop's wrapper and which of its programs that compiled.
_PLAIN = """
import json, sys
import jaxwear as jw
import jaxwear.cli  # the command line imports a verb's module when that verb runs
heavy = sorted(m for m in sys.modules if m in ("scipy.stats", "optimistix", "lineax",
                                                 "equinox")
               or m.startswith(("jaxwear._analyses.diagnose", "jaxwear._report.diagnosis",
                                "jaxwear._inference", "jaxwear._analyses.predict")))
from jaxwear._core import jit as J
from jaxwear._core import xla_flags
from jaxwear._physics import adaptive, wear
if "cli" in sys.argv[1:]:
    xla_flags.apply()  # as the command line does first
if "run" in sys.argv[1:]:
    p, cfg = jw.preset("rig"), jw.ModelConfig(nodes=16, steps_per_rev=16)
    jw.simulate(p, cfg, revolutions=50, M=25)
    adaptive._regime_rates_jit(p, cfg)
print(json.dumps({"heavy": heavy, "options": J.current_options(),
                  "variants": [dict(k) for k in wear._wear_loop_jit._variants],
                  "once": [dict(k) for k in adaptive._regime_rates_jit._variants],
                  "diagnose": jw.diagnose.__module__, "calibrate": jw.calibrate.__module__,
                  "xla_flags": __import__("os").environ.get("XLA_FLAGS", "")}))
"""


def _plain_process(*args, **env_extra):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAXWEAR_XLA_DEFAULTS")}
    env.update(PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu", **env_extra)
    out = subprocess.run([sys.executable, "-c", _PLAIN, *args], env=env, capture_output=True,
                         text=True, timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


ASKED = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1,
         "xla_cpu_experimental_ynn_fusion_type": ""}
ASKED_ONCE = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 0,
              "xla_cpu_experimental_ynn_fusion_type": ""}
REASSOC = {"xla_cpu_enable_fast_math": True, "xla_cpu_fast_math_honor_nans": True,
           "xla_cpu_fast_math_honor_infs": True, "xla_cpu_fast_math_honor_division": True,
           "xla_cpu_fast_math_honor_functions": True}


def _knows(name, value) -> bool:
    """Whether this jaxlib accepts compile option `name` (asked of a plain `jax.jit`, not of
    jaxwear's wrapper): jaxlib 0.11 no longer knows `xla_cpu_use_fusion_emitters`."""
    try:
        jax.jit(lambda x: x + 1.0, compiler_options={name: value})(jnp.zeros(()))
        return True
    except Exception as e:
        if "option" not in str(e):
            raise
        return False


LEGACY = _knows("xla_cpu_use_fusion_emitters", False)


def _expected(asked: dict) -> dict:
    """The options a program asked for with `asked` compiles with on this jaxlib: those it
    knows, and where the legacy emitters are gone the reassociation in their place."""
    out = {k: v for k, v in asked.items() if _knows(k, v)}
    if asked.get("xla_cpu_use_fusion_emitters") is False and not LEGACY:
        out.update({k: v for k, v in REASSOC.items() if _knows(k, v)})
    return out


PROGRAM, ONCE = _expected(ASKED), _expected(ASKED_ONCE)
NO_YNN = {"xla_cpu_experimental_ynn_fusion_type": ""}
YNN = {k: v for k, v in NO_YNN.items() if _knows(k, v)}  # where this jaxlib knows it


def test_no_ynnpack_fusion_in_the_jacobians_program():
    """The per-program option reaches XLA: a Jacobian of a sum over a row (the contact
    tangent's form, a multiply reduced over an axis) is compiled with no YNNPACK fusion
    where it is asked for, and with one where it is not (this jaxlib rewrites such a sum
    into a dot and hands it to YNNPACK)."""
    if not YNN:
        pytest.skip("this jaxlib has no YNNPACK fusions")
    n = jnp.linspace(0.1, 1.0, 48)

    def f(x):
        return jnp.sum(jnp.where(x > 0.2, x, 0.0) * n, axis=1)

    def hlo(opts):
        jac = jax.jit(jax.jacfwd(f), compiler_options=opts)
        return jac.lower(jnp.ones((72, 48))).compile().as_text()

    assert "ynn_fusion" not in hlo(J.current_options())
    assert "ynn_fusion" in hlo(None)


def test_the_expected_options_on_this_jaxlib():
    # 0.10: the legacy emitters at O1; 0.11 (no legacy emitters): O1 and the reassociation
    # (its options known to both)
    assert all(_knows(k, v) for k, v in REASSOC.items())
    # (the YNNPACK option where this jaxlib knows it: `YNN`)
    legacy = {**{k: v for k, v in ASKED.items() if k not in NO_YNN}, **YNN}
    assert PROGRAM == (legacy if LEGACY else {"xla_backend_optimization_level": 1,
                                              **REASSOC, **YNN})


def test_plain_import_is_light_and_runs_the_wear_loop_with_legacy_emitters():
    got = _plain_process("run")
    # neither scipy.stats nor the diagnose package at import, nor the fits (optimistix,
    # lineax, the least-squares core) and the analyses on them, the command line's included
    # (a verb imports what it needs), nor equinox (the pytrees are `_core.pytree`'s)
    assert got["heavy"] == []
    assert got["diagnose"].startswith("jaxwear._analyses.diagnose")  # the names resolve
    assert got["calibrate"] == "jaxwear._inference.calibrate"
    # the process's flags untouched, the wear loop's program compiled with the legacy
    # emitters at LLVM's O1, a program that runs once at O0 (docs/performance.md)
    assert "xla_cpu_use_fusion_emitters" not in got["xla_flags"]
    assert got["options"] == PROGRAM
    assert got["variants"] == [PROGRAM]
    assert got["once"] == [ONCE]


def test_the_command_lines_process_flag_keeps_the_per_program_options():
    # `configure_xla`'s own flag is the same choice, not the user's: the options stay
    got = _plain_process("cli", "run")
    # the process flag only where the jaxlib knows it (an unknown flag aborts XLA)
    assert ("xla_cpu_use_fusion_emitters=false" in got["xla_flags"]) == LEGACY
    assert got["variants"] == [PROGRAM]
    assert got["once"] == [ONCE]


def test_user_choice_turns_the_per_program_options_off():
    if LEGACY:  # the flag exists (elsewhere it aborts XLA): the user's fusion emitters
        # keep the reassociation that makes them fast on jaxwear's sums
        got = _plain_process(XLA_FLAGS="--xla_cpu_use_fusion_emitters=true")
        assert got["options"] == {"xla_backend_optimization_level": 1, **REASSOC, **YNN}
        got = _plain_process(XLA_FLAGS="--xla_cpu_use_fusion_emitters=true "
                             "--xla_cpu_enable_fast_math=false")
        assert got["options"] == {"xla_backend_optimization_level": 1, **YNN}
    got = _plain_process(XLA_FLAGS="--xla_backend_optimization_level=2")
    assert got["options"] == {"xla_cpu_use_fusion_emitters": False, **YNN}
    # the user's own YNNPACK choice keeps them (any value: theirs)
    got = _plain_process(XLA_FLAGS="--xla_cpu_experimental_ynn_fusion_type=")
    assert got["options"] == {k: v for k, v in PROGRAM.items() if k not in NO_YNN}
    assert _plain_process(JAXWEAR_XLA_DEFAULTS="0")["options"] is None


def test_options_reach_the_compiler_and_a_refused_one_falls_back_logged(caplog):
    # an option the compiler does not know fails the compilation: so it was passed there
    bogus = {"xla_cpu_jaxwear_no_such_option": True}
    f = J.jit(lambda x: jnp.sin(x) * x)
    x = jnp.linspace(0.0, 1.0, 5)
    try:
        with J.options(bogus), caplog.at_level(logging.WARNING, logger="jaxwear"):
            assert J.current_options() == bogus
            np.testing.assert_allclose(f(x), np.sin(np.linspace(0, 1, 5)) * np.linspace(0, 1, 5))
            assert "does not accept the compiler option xla_cpu_jaxwear_no_such_option" \
                in caplog.text
            assert J.current_options() is None  # once refused, not asked for again
            caplog.clear()
            f(x + 1.0)
            assert caplog.text == ""
    finally:
        J._unknown.discard("xla_cpu_jaxwear_no_such_option")


def test_an_unknown_option_drops_alone(caplog):
    # the others (here LLVM's level) stay: the program compiles with them, logged once
    asked = {"xla_cpu_jaxwear_no_such_option": True, "xla_backend_optimization_level": 1}
    f = J.jit(lambda x: jnp.cos(x) + x)
    x = jnp.linspace(0.0, 1.0, 3)
    try:
        with J.options(asked), caplog.at_level(logging.WARNING, logger="jaxwear"):
            np.testing.assert_allclose(f(x), np.cos(np.linspace(0, 1, 3)) + np.linspace(0, 1, 3))
            assert J.current_options() == {"xla_backend_optimization_level": 1}
            assert list(f._variants) == [J._key({"xla_backend_optimization_level": 1})]
            assert caplog.text.count("does not accept") == 1
            f(x + 1.0)
            g = J.jit(lambda x: x * 2.0)
            np.testing.assert_allclose(g(x), 2 * np.linspace(0, 1, 3))
            assert caplog.text.count("does not accept") == 1  # once per process
    finally:
        J._unknown.discard("xla_cpu_jaxwear_no_such_option")


def test_the_unknown_option_named_in_jaxlibs_errors():
    opts = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1}
    assert J._unknown_option("INVALID_ARGUMENT: No such compile option: "
                             "'xla_cpu_use_fusion_emitters'", opts) == \
        "xla_cpu_use_fusion_emitters"
    assert J._unknown_option("INVALID_ARGUMENT: While setting option "
                             "xla_backend_optimization_level, 'x' is not a valid enum value.",
                             opts) == "xla_backend_optimization_level"
    # a name not asked for, or none: not ours to drop
    assert J._unknown_option("No such compile option: 'xla_other'", opts) is None
    assert J._unknown_option("something else", opts) is None


def test_reassociation_changes_the_wear_loop_by_round_off_only():
    """The fusion emitters' reassociation (`FUSION_REASSOC`) against the same emitters
    without it: a run of eq 23 (no step control to amplify round-off) equal to 1e-12."""
    p = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=48, steps_per_rev=72)
    sched = build_schedule(p, cfg, revolutions=2000, M=100, pad=False)
    with J.options(None):
        plain = np.asarray(_wear_loop_jit(p, cfg, sched).depth)
    with J.options(J.FUSION_REASSOC):
        fast = np.asarray(_wear_loop_jit(p, cfg, sched).depth)
    assert np.max(plain) > 1e-7
    np.testing.assert_allclose(fast, plain, rtol=1e-12, atol=1e-12 * np.max(plain))


def test_grad_and_vmap_through_the_wear_loop_wrapper():
    """Under a caller's transformation the wrapper runs its function without options (JAX
    refuses them on a nested jit): the gradient matches central differences of top-level
    calls (compiled with the options), vmap matches single calls."""
    p = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=16, steps_per_rev=16)
    sched = build_schedule(p, cfg, revolutions=200, M=20, pad=False)
    k0 = float(p.get("K_d_per_Pa"))

    def peak(k):
        return jnp.max(_wear_loop_jit(p.with_values({"K_d_per_Pa": k}), cfg, sched).depth)

    with J.options(J.LEGACY_EMITTERS):
        top = lambda k: float(peak(jnp.asarray(k)))
        dk = 1e-3 * k0
        fd = (top(k0 + dk) - top(k0 - dk)) / (2 * dk)
        g = float(jax.grad(peak)(jnp.asarray(k0)))
        ks = jnp.asarray([0.5 * k0, 2.0 * k0])
        batched = np.asarray(jax.vmap(peak)(ks))
        assert J._key(_expected(J.LEGACY_EMITTERS)) in _wear_loop_jit._variants
    assert g > 0
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    np.testing.assert_allclose(batched, [top(float(k)) for k in ks], rtol=1e-12)


def test_a_users_jit_around_the_wrapper():
    f = J.jit(lambda x, n: jnp.sin(x) * n)  # n: static (not an array)
    x = jnp.linspace(0.0, 1.0, 4)
    with J.options(J.LEGACY_EMITTERS):
        want = np.sin(np.linspace(0.0, 1.0, 4)) * 3
        np.testing.assert_allclose(f(x, 3), want, rtol=1e-15)
        np.testing.assert_allclose(jax.jit(lambda y: f(y, 3))(x), want, rtol=1e-15)
        # no traced argument, inside the user's jit all the same
        np.testing.assert_allclose(jax.jit(lambda: f(jnp.linspace(0.0, 1.0, 4), 3))(), want,
                                   rtol=1e-15)
