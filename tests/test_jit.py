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
heavy = sorted(m for m in sys.modules if m == "scipy.stats"
               or m.startswith(("jaxwear._analyses.diagnose", "jaxwear._report.diagnosis")))
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
                  "diagnose": jw.diagnose.__module__, "xla_flags": __import__("os").environ.get(
                      "XLA_FLAGS", "")}))
"""


def _plain_process(*args, **env_extra):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAXWEAR_XLA_DEFAULTS")}
    env.update(PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu", **env_extra)
    out = subprocess.run([sys.executable, "-c", _PLAIN, *args], env=env, capture_output=True,
                         text=True, timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


PROGRAM = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1}
ONCE = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 0}


def test_plain_import_is_light_and_runs_the_wear_loop_with_legacy_emitters():
    got = _plain_process("run")
    # neither scipy.stats nor the diagnose package at import, the command line's included
    # (a verb imports what it needs)
    assert got["heavy"] == []
    assert got["diagnose"].startswith("jaxwear._analyses.diagnose")  # the name resolves
    # the process's flags untouched, the wear loop's program compiled with the legacy
    # emitters at LLVM's O1, a program that runs once at O0 (docs/performance.md)
    assert "xla_cpu_use_fusion_emitters" not in got["xla_flags"]
    assert got["options"] == PROGRAM
    assert got["variants"] == [PROGRAM]
    assert got["once"] == [ONCE]


def test_the_command_lines_process_flag_keeps_the_per_program_options():
    # `configure_xla`'s own flag is the same choice, not the user's: the options stay
    got = _plain_process("cli", "run")
    assert "xla_cpu_use_fusion_emitters=false" in got["xla_flags"]
    assert got["variants"] == [PROGRAM]
    assert got["once"] == [ONCE]


def test_user_choice_turns_the_per_program_options_off():
    got = _plain_process(XLA_FLAGS="--xla_cpu_use_fusion_emitters=true")
    assert got["options"] == {"xla_backend_optimization_level": 1}
    got = _plain_process(XLA_FLAGS="--xla_backend_optimization_level=2")
    assert got["options"] == {"xla_cpu_use_fusion_emitters": False}
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
            assert "does not accept the compiler options" in caplog.text
            assert J.current_options() is None  # once refused, not asked for again
            caplog.clear()
            f(x + 1.0)
            assert caplog.text == ""
    finally:
        J._rejected.discard(J._key(bogus))


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
        assert (("xla_cpu_use_fusion_emitters", False),) in _wear_loop_jit._variants
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
