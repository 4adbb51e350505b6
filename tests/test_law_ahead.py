"""The law search's candidates fitted ahead on a second core (`law.ahead`): the jobs'
semantics: taken in the search's order, cancelled where the search reaches one that has not
started, discarded where it skips. (The search's answer with and without them:
`test_shape_refit.py`.)"""

import threading
import time

import numpy as np
import pytest

from jaxwear._analyses.diagnose._model import stop_if_asked
from jaxwear._analyses.diagnose.law.ahead import Ahead, Shared
from jaxwear._core.log import log


def test_a_job_not_started_is_run_by_the_caller_and_one_running_is_waited_for():
    gate = threading.Event()
    ahead = Ahead()

    def slow():
        log(True, "slow ran")
        gate.wait(10)
        return "slow"

    ahead.submit("a", slow)
    ahead.submit("b", lambda: "b")  # queued behind "a" (one worker)
    # "b" has not started: the caller is told to run it itself
    assert ahead.take("b") is None
    gate.set()
    out, lines = ahead.take("a")
    assert out == "slow" and lines == ["slow ran"]  # its progress lines held for the caller
    assert ahead.take("a") is None and ahead.take("never") is None
    ahead.close()
    assert ahead.used["jobs"] == 1 and ahead.discarded["jobs"] == 0


def test_an_error_is_raised_where_the_job_is_taken_and_what_is_skipped_is_discarded():
    ahead = Ahead()
    ahead.submit("bad", lambda: 1 / 0)
    ahead.submit("skipped", lambda: 7)
    with pytest.raises(ZeroDivisionError):
        ahead.take("bad")
    ahead.close()  # "skipped" ran (or was cancelled) but was not taken
    assert ahead.used["jobs"] == 1
    assert ahead.discarded["jobs"] in (0, 1)
    off = Ahead(enabled=False)
    off.submit("x", lambda: 1)
    assert off.take("x") is None
    off.close()


@pytest.mark.parametrize("how", ["close", "drop"])
def test_a_running_job_the_search_will_not_take_stops_at_its_next_evaluation(how):
    """A job running when the search skips it (`drop`) or ends (`close`) stops at its next
    model evaluation (here a chain of 500 of them, each `stop_if_asked` as
    `Model.evaluate` calls it), counted as discarded with the evaluations it made, where
    it ran to its end before: a fit of a candidate the search had already passed over."""
    started, ended, made = threading.Event(), [], []

    def job():
        started.set()
        for i in range(500):
            stop_if_asked()
            made.append(i)
            time.sleep(0.01)
        ended.append(True)
        return "fitted"

    ahead = Ahead()
    ahead.submit("j", job)
    assert started.wait(30)
    if how == "drop":
        ahead.drop("j")
    ahead.close()
    assert ended == [] and 0 < len(made) < 500
    assert ahead.discarded["jobs"] == 1 and ahead.used["jobs"] == 0


def _shared_job(shared, tasks, ran, gate):
    """A job as the search's laws with memory: its tasks known after a first part, then
    each claimed and run in order (the first held at `gate`)."""
    def job():
        shared.publish("starts", tasks)
        for i, t in enumerate(shared.items):
            if shared.claim(i):
                if i == 0:
                    gate.wait(10)
                ran[i] = threading.current_thread().name
                shared.put(i, t * 10)
        return "done"
    return job


def test_the_search_runs_the_shared_tasks_the_job_has_not_begun_meanwhile():
    """Reached while the job runs its first task, the search takes the others and runs
    them itself (on its own thread, while the job's runs), then the job's result: every
    task once, results in the tasks' order, whoever ran them. Why: on the fatigue study
    the search waited 11-12 s for the job's laws with memory with its core idle."""
    gate, ran = threading.Event(), {}
    ahead, shared = Ahead(), Shared()
    ahead.submit("m", _shared_job(shared, [1, 2, 3], ran, gate))
    assert ahead.started("m") and shared.wait_ready(lambda: ahead.finished("m"))
    while 0 not in shared._owner:  # the job has claimed its first task
        time.sleep(0.01)
    mine = shared.claim_rest()
    assert mine == [1, 2]  # the job is busy: every task it has not claimed
    for i in mine:
        ran[i] = threading.current_thread().name
    assert not ahead.finished("m")  # still on its first task while the search ran these
    gate.set()
    assert ahead.take("m")[0] == "done"
    assert shared.result(0) == 10 and set(ran) == {0, 1, 2}
    assert ran[0].startswith("jaxwear-law") and ran[1] == ran[2] == threading.current_thread().name
    ahead.close()


def test_a_job_between_tasks_keeps_its_next_and_one_not_started_is_the_callers():
    """Where the job has claimed nothing yet, the search leaves it the first task (it
    claims it next) and takes the rest; a job that has not started is the caller's whole
    (`started` cancels it, as `take`)."""
    shared = Shared()
    shared.publish("starts", ["a", "b", "c"])
    assert shared.claim_rest() == [1, 2]
    assert shared.claim(0) and not shared.claim(1)
    gate = threading.Event()
    ahead = Ahead()
    ahead.submit("busy", lambda: gate.wait(10))
    ahead.submit("queued", lambda: "never")
    assert not ahead.started("queued") and ahead.take("queued") is None
    gate.set()
    ahead.close()


def test_nothing_runs_ahead_where_the_shape_leaves_the_data_at_the_noise():
    """`law.ahead`'s jobs are discarded once a law reaches the noise; where the shape's
    correction refitted through the loop already leaves residuals at the noise (white, of
    the noise's size), the law that matches it is expected there and nothing is run ahead.
    Residuals of the noise pass; the same noise plus a smooth misfit of half its size along
    the series (the autocorrelation test's signature) and noise 20 % too large (the
    chi-square test's) do not; no residuals (the refit gave none) do not either."""
    from types import SimpleNamespace

    from jaxwear._analyses.diagnose._verdict import shape_at_noise

    rng = np.random.default_rng(7)
    n, sigma = 2000, 0.3
    pairs = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    base = SimpleNamespace(k=6)

    def at_noise(r):
        return shape_at_noise(None, base, SimpleNamespace(residual_um=r), sigma, 1500.0,
                              pairs)

    white = sigma * rng.standard_normal(n)
    assert at_noise(white)
    assert not at_noise(white + 0.5 * sigma * np.sin(np.linspace(0, 6 * np.pi, n)))
    assert not at_noise(1.2 * white)
    assert not at_noise(None)
