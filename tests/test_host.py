"""Fewer programs per cold answer (issue 50, item 3): host data onto the device without a
compilation (`jaxwear._core.host`), one rate program for every resolution of a study
(`adaptive.rate_config`), and the resolution check's forward program compiled in the
background (`evaluation.compile_forward`) and then found compiled by the check."""

from pathlib import Path

import jax
import jax.monitoring as mon
import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._core.host import stack, to_device
from jaxwear._physics import adaptive

ROOT = Path(__file__).resolve().parents[1]

_compiles = [0]


def _listen(event, duration, **kw):
    if event == "/jax/core/compile/backend_compile_duration":
        _compiles[0] += 1


mon.register_event_duration_secs_listener(_listen)


def compilations(fn):
    """(XLA compilations while `fn()` ran, its value)."""
    n = _compiles[0]
    out = fn()
    return _compiles[0] - n, out


@pytest.mark.parametrize("value, dtype", [
    ([1.5, 2.5, 3.25], np.float64), ([1, 2, 3], np.int32), ([True, False], bool),
    (np.arange(7, dtype=np.int64), np.int32), (2.5e-9, np.float64),
    (np.linspace(0.0, 1.0, 11), None)])
def test_to_device_is_jnp_asarray_without_a_compilation(value, dtype):
    want = jnp.asarray(value, dtype)
    # a shape and dtype no program of this process has seen (jnp.asarray compiles one)
    fresh = np.concatenate([np.atleast_1d(np.asarray(value, dtype))] * 13)
    n, got = compilations(lambda: to_device(fresh, dtype))
    assert n == 0
    assert got.dtype == jnp.asarray(fresh, dtype).dtype and not got.weak_type
    np.testing.assert_array_equal(np.asarray(got), np.asarray(jnp.asarray(fresh, dtype)))
    one = to_device(value, dtype)
    assert one.dtype == want.dtype and one.shape == want.shape
    assert one.weak_type == want.weak_type
    np.testing.assert_array_equal(np.asarray(one), np.asarray(want))


def test_stack_on_the_host_keeps_values_and_types():
    xs = [jax.device_put(np.full(17, i, np.float64) + 0.1) for i in range(3)]
    n, got = compilations(lambda: stack(xs))
    assert n == 0
    want = jnp.stack(xs)
    assert got.dtype == want.dtype and got.weak_type == want.weak_type
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    # weakly typed leaves keep jnp.stack's type (a weak value must stay weak: a program's
    # cache key holds it)
    weak = [jnp.asarray(1.0), jnp.asarray(2.0)]
    assert stack(weak).weak_type == jnp.stack(weak).weak_type


def test_one_rate_program_for_every_resolution():
    """The work estimate's rate bound at 90 x 72, 180 x 144 and 360 x 360 (the levels of
    `_study.resolution`): one compilation, not one per level; the bound is the one at 72
    steps per cycle, within 0.1 % of the finer levels' own (the cycle's sliding, a sum
    over the steps, is what moves)."""
    p = jw.preset("rig", K_d_per_Pa=3.3e-13)
    # a configuration no other test compiles (the SCLA's passes and start angle)
    cfgs = [jw.ModelConfig(nodes=n, steps_per_rev=s, scla_passes=3, gamma0_rad=0.0123)
            for n, s in ((90, 72), (180, 144), (360, 360))]
    sched = jw.build_schedule(p, cfgs[0], revolutions=5000, snapshots=[5000], M=100)
    n, counts = compilations(lambda: [adaptive.adaptive_attempts(p, c, sched) for c in cfgs])
    assert n == 1, n
    assert len(set(counts)) == 1
    own = [float(np.max(adaptive._regime_rates(p, c))) for c in cfgs]
    shared = float(np.max(adaptive._regime_rates(p, adaptive.rate_config(cfgs[0]))))
    assert max(abs(shared / o - 1) for o in own) < 1e-3
    # below RATE_STEPS the configuration's own steps are kept
    low = jw.ModelConfig(nodes=16, steps_per_rev=24)
    assert adaptive.rate_config(low).steps_per_rev == 24


def test_background_compile_is_the_checks_program(tmp_path):
    """The forward program compiled in the background (a loop bound of 0 attempts) is the
    one the resolution check then runs: no new trace, and the run is the model's."""
    from jaxwear._inference.calibrate import build_problem, parse_fit
    from jaxwear._inference.evaluation import compile_forward, forward_run
    from jaxwear._inference.residual import traces, traces_since
    from jaxwear._study.study import load_study

    (tmp_path / "boom.csv").write_text((ROOT / "calibration" / "boom" / "boom.csv").read_text())
    (tmp_path / "s.toml").write_text(
        '[model]\npreset = "boom"\nduty_cycle = [{amplitude_deg = 20, duration_h = 1}, '
        '{amplitude_deg = 1, duration_h = 4}]\n[model.parameters]\nK_d_per_Pa = 3e-13\n'
        '[numerics]\nnodes = 40\nsteps_per_rev = 44\n[[experiment]]\nname = "boom"\n'
        'history = "boom.csv"\n')
    study = load_study(tmp_path / "s.toml")
    keys = parse_fit(study, "K_d")
    before = traces()
    compile_forward(lambda: build_problem(study, keys)).wait()
    assert traces_since(before)["forward"] == 1
    before = traces()
    f = forward_run(build_problem(study, keys), np.zeros(1))
    assert traces_since(before) == {"jacobian": 0, "forward": 0}
    # a real run: the measured history's scale (tens to hundreds of µm over 25 h)
    assert f.usable and np.isfinite(f.error_um) and f.steps > 0
    assert 10 < np.max(f.rows) < 1000
