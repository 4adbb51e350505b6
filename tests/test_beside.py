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
    monkeypatch.setattr(_model, "evaluate", lambda e, u, columns=None, width=None: (None, e))
    monkeypatch.setattr(_model, "forward", lambda e, u, doublings=3: (None, None, 0.0, e))
    monkeypatch.setattr(_model, "_compiled_count", lambda: 0)
    monkeypatch.setattr(_model.Model, "evaluations", 0)
    m = object.__new__(_model.Model)  # no study: the counters only
    m.ext, m.jacobian_columns, m.jacobian_width = ext, None, None
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
