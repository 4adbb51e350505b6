"""The law search's candidates fitted ahead on a second core (`law.ahead`): the jobs'
semantics: taken in the search's order, cancelled where the search reaches one that has not
started, discarded where it skips. (The search's answer with and without them:
`test_shape_refit.py`.)"""

import threading
import time

import pytest

from jaxwear._analyses.diagnose._model import stop_if_asked
from jaxwear._analyses.diagnose.law.ahead import Ahead
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
