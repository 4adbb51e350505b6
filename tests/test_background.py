"""Work done beside the caller's thread (`jaxwear._core.background`) and the programs a fit
compiles ahead (`evaluation.Compiling`, `lsq.lower_core`): when they start, that what
they compile is what the calls then use (nothing traced again), and that a thread is
joined at the interpreter's exit unless the command line abandoned it."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxwear._core import background
from jaxwear._core.background import Background
from jaxwear._inference import lsq

ROOT = Path(__file__).resolve().parents[1]

# programs traced while `_TRACED` is being recorded, by name (JAX's tracing event)
_TRACED: list[str] = []
_RECORDING = threading.Event()


def _on_event(event, duration, **kw):
    if _RECORDING.is_set() and event == "/jax/core/compile/jaxpr_trace_duration":
        _TRACED.append(str(kw.get("fun_name", "")))


jax.monitoring.register_event_duration_secs_listener(_on_event)


def test_lowered_is_set_by_the_named_program_only():
    mine = background.lowered("_probe_lowered_one")
    other = background.lowered("_probe_lowered_two")

    def _probe_lowered_one(x):
        return 2.0 * x

    assert not mine.is_set()
    jax.jit(_probe_lowered_one)(jnp.ones(3))
    assert mine.is_set() and not other.is_set()
    background.forget(other)  # whoever waits on it goes on
    assert other.is_set()


def test_background_returns_and_reraises():
    assert Background(lambda a, b=0: a + b, 1, b=2).result() == 3

    def fails():
        raise ValueError("inside")

    job = Background(fails)
    with pytest.raises(ValueError, match="inside"):
        job.result()
    assert job.done.is_set()


@pytest.mark.parametrize("abandon", [False, True])
def test_a_thread_is_joined_at_exit_unless_abandoned(tmp_path, abandon):
    """A thread still working when the program ends is waited for (a compilation torn
    down with the interpreter may crash it); the command line abandons it and ends the
    process itself (`_core.interrupt.end_process`)."""
    mark = tmp_path / "mark"
    code = textwrap.dedent(f"""
        import threading, time
        from jaxwear._core import background
        go = threading.Event()
        def work():
            go.wait()
            time.sleep(0.5)  # still working when the main thread has ended
            open({str(mark)!r}, "w").write("done")
        background.Background(work)
        if {abandon}:
            background.abandon()
        go.set()  # the thread may run only now; the main thread ends at once
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=120)
    if not abandon:
        assert mark.read_text() == "done"


def _linear(rows: int, k: int):
    rng = np.random.default_rng(3)
    A, y = rng.normal(size=(rows, k)), rng.normal(size=rows)

    def evaluate(u):
        m = A @ u
        return lsq.Point(u=np.array(u, float), r=m - y, predicted=m, J=A,
                         r_prior=np.zeros(0), J_prior=np.zeros((0, k)), usable=True)

    return evaluate, A, y


def test_the_core_lowered_ahead_is_what_the_fit_runs():
    """`lsq.lower_core` for a fit's shapes, compiled: the fit's own damped step and
    trust-region verdict are then not traced again, and the answer is least squares'."""
    rows, k = 13, 3  # shapes no other test fits
    for low in lsq.lower_core(rows, k):
        low.compile()
    evaluate, A, y = _linear(rows, k)
    _TRACED.clear()
    _RECORDING.set()
    try:
        out = lsq.solve(evaluate, np.zeros(k), noise_um=1.0, max_evaluations=20)
    finally:
        _RECORDING.clear()
    assert not [n for n in _TRACED if "_propose" in n or "_judge" in n], _TRACED
    np.testing.assert_allclose(out.u, np.linalg.lstsq(A, y, rcond=None)[0], atol=1e-8)


def _boom_study(tmp_path, nodes, steps):
    from jaxwear._study.study import load_study

    (tmp_path / "boom.csv").write_text((ROOT / "calibration" / "boom" / "boom.csv").read_text())
    path = tmp_path / f"s{nodes}.toml"
    path.write_text(
        '[model]\npreset = "boom"\nduty_cycle = [{amplitude_deg = 20, duration_h = 1}, '
        '{amplitude_deg = 1, duration_h = 4}]\n[model.parameters]\nK_d_per_Pa = 3e-13\n'
        f'[numerics]\nnodes = {nodes}\nsteps_per_rev = {steps}\n[[experiment]]\n'
        'name = "boom"\nhistory = "boom.csv"\n')
    return load_study(path)


def test_a_gated_compilation_waits_and_a_cancelled_one_never_traces(tmp_path):
    from jaxwear._inference.calibrate import build_problem, parse_fit
    from jaxwear._inference.evaluation import compile_forward
    from jaxwear._inference.residual import traces, traces_since

    study = _boom_study(tmp_path, 38, 44)
    keys = parse_fit(study, "K_d")
    gate = threading.Event()
    before = traces()
    job = compile_forward(lambda: build_problem(study, keys), trace_after=(gate,))
    assert not job.ready.is_set()  # it cannot start before its gate
    job.cancel()
    gate.set()
    job.join()
    assert traces_since(before)["forward"] == 0


def test_a_program_lowered_ahead_is_the_next_checks_program(tmp_path):
    """The next level's forward program, traced and lowered after this level's compiled
    (`ahead`) and compiled when asked for (`compile_next`): the check's run at that level
    traces nothing, and is the model's (the measured history's scale)."""
    from jaxwear._inference.calibrate import build_problem, parse_fit
    from jaxwear._inference.evaluation import compile_forward, forward_run
    from jaxwear._inference.residual import traces, traces_since

    coarse, fine = _boom_study(tmp_path, 36, 40), _boom_study(tmp_path, 42, 40)
    keys = parse_fit(coarse, "K_d")
    before = traces()
    first = compile_forward(lambda: build_problem(coarse, keys),
                            ahead=lambda: build_problem(fine, keys))
    first.wait()
    first.join()
    # both traced in the background; the one lowered ahead is counted once compiled
    assert traces_since(before)["forward"] == 1
    assert first.next is not None
    before = traces()
    first.compile_next(lambda: build_problem(fine, keys)).wait()
    assert traces_since(before)["forward"] == 1
    before = traces()
    f = forward_run(build_problem(fine, keys), np.zeros(1))
    assert traces_since(before) == {"jacobian": 0, "forward": 0}
    assert f.usable and 10 < np.max(f.rows) < 1000
