"""What lets `diagnose` run the shape's refit on top of the effect found beside the law
search: progress lines a thread holds (`_core.log.held`) and each thread's own count of
model evaluations (`Model.own_evaluations`)."""

from __future__ import annotations

import threading

from jaxwear._analyses.diagnose import _model
from jaxwear._core.log import held, log


def test_held_lines_are_kept_not_printed_and_only_in_their_thread(capsys):
    seen = {}

    def other():
        log(True, "printed by the other thread")

    with held() as lines:
        log(True, "kept")
        log(False, "not verbose: neither kept nor printed")
        t = threading.Thread(target=other)
        t.start()
        t.join()
        with held() as inner:
            log(True, "inner")
        seen["inner"] = list(inner)
        log(True, "kept again")
    log(True, "printed after")
    err = capsys.readouterr().err.splitlines()
    assert lines == ["kept", "kept again"] and seen["inner"] == ["inner"]
    assert err == ["printed by the other thread", "printed after"]


def test_each_thread_counts_its_own_evaluations(monkeypatch):
    """Two threads evaluate one model (Jacobian runs and forward runs, the compiled calls
    stubbed): each thread's own count is its own, the process-wide one their sum."""
    from types import SimpleNamespace

    ext = SimpleNamespace(schedule=SimpleNamespace(attempts=1))
    monkeypatch.setattr(_model, "evaluate", lambda e, u, columns=None: (None, e))
    monkeypatch.setattr(_model, "forward", lambda e, u, doublings=3: (None, None, 0.0, e))
    monkeypatch.setattr(_model, "_compiled_count", lambda: 0)
    monkeypatch.setattr(_model.Model, "evaluations", 0)
    m = object.__new__(_model.Model)  # no study: the counters only
    m.ext, m.jacobian_columns = ext, None
    go = threading.Barrier(2)
    out = {}

    def run(k):
        go.wait()
        start = _model.Model.own_evaluations()
        for _ in range(k):
            m.evaluate(None)
            m.predict(None)
        out[k] = _model.Model.own_evaluations() - start

    ts = [threading.Thread(target=run, args=(k,)) for k in (3, 5)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert out == {3: 6, 5: 10} and _model.Model.evaluations == 16


def _counting_model(monkeypatch):
    """A model whose compiled calls are stubbed: the counters only."""
    from types import SimpleNamespace

    ext = SimpleNamespace(schedule=SimpleNamespace(attempts=1))
    monkeypatch.setattr(_model, "forward", lambda e, u, doublings=3: (None, None, 0.0, e))
    m = object.__new__(_model.Model)
    m.ext, m.jacobian_columns = ext, None
    return m


def test_two_threads_give_the_items_results_in_order_and_count_as_the_callers(monkeypatch):
    """`in_two_threads` (the left-out checks' two halves): the results in the items'
    order whichever thread made each, both threads used, and the helper's forward runs
    counted as the caller's own."""
    monkeypatch.setattr(_model.os, "cpu_count", lambda: 2)
    m = _counting_model(monkeypatch)
    met = set()
    both = threading.Barrier(2, timeout=10)  # each thread waits once for the other

    def fn(x):
        if threading.current_thread().name not in met:
            met.add(threading.current_thread().name)
            both.wait()
        for _ in range(x):
            m.predict(None)
        return x * x

    start = _model.Model.own_evaluations()
    assert _model.in_two_threads(fn, range(1, 8)) == [x * x for x in range(1, 8)]
    assert len(met) == 2
    assert _model.Model.own_evaluations() - start == sum(range(1, 8))


def test_two_threads_stop_with_the_caller(monkeypatch):
    """A stop asked of the caller (`stopping`) stops the helper at its next evaluation,
    and the caller's error ends the call: no item is taken after it."""
    monkeypatch.setattr(_model.os, "cpu_count", lambda: 2)
    m = _counting_model(monkeypatch)
    ev = threading.Event()
    taken = []

    def fn(x):
        taken.append(x)
        if x == 2:
            ev.set()
        m.predict(None)  # raises `Stopped` once the event is set, in either thread
        return x

    with _model.stopping(ev):
        try:
            _model.in_two_threads(fn, range(50))
        except _model.Stopped:
            pass
        else:
            raise AssertionError("not stopped")
    assert len(taken) < 50 and 2 in taken
