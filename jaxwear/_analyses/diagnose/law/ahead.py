"""Candidates of the law search fitted ahead on a second core, the search's answer unchanged.

Why (issue 48's 2-minute bar, measured on the generator's fatigue study, 48 x 72, 2 cores,
2026-11-29): the search fitted its candidates one after the other on one core, each a
chain of single-threaded wear-loop runs (its start's forward runs, its fit, its left-out
checks): 65 s of the 140 s of `diagnose --shape`, while the other core had only the shape's
refit on top of the effect found to run.

What runs ahead is what the search itself would run, with the same inputs: a screen's pick
whose start does not depend on a law fitted before it (`law.search.from_fitted` returns
it as it is), and the laws with memory (their starts' forward runs and fits, which depend
on no law fitted before them; only whether they are tried does). The search still walks
its candidates in order and makes every decision itself; where it reaches a candidate
that runs ahead it takes that result (waiting for it if it is running), where it has not
started, it cancels it and runs it itself, and what it does not reach or skips is
discarded (`close`), its model evaluations counted apart (`discarded`). So the answer,
the candidates fitted and their order are those of the sequential search; the cost in
CPU is higher where a candidate run ahead is then skipped (a law at the noise: the rest
are not fitted); a job the search will not take is stopped at its next model evaluation
(`_model.stopping`), not run to its end.

Each job's progress lines are held (`_core.log.held`) and printed by the search when it
takes the result, so that they read in the search's order.

A job of several independent tasks (the laws with memory: one fit per form, after their
starts) shares them with the search (`Shared`): once the search reaches the job, it fits
the tasks the job has not begun while the job fits its own, rather than wait for the
whole job with its own core idle.
"""

from __future__ import annotations

import threading
from concurrent.futures import CancelledError, ThreadPoolExecutor

from jaxwear._analyses.diagnose._model import Model, Stopped, stopping
from jaxwear._core.background import in_context
from jaxwear._core.log import held

# one thread beside the search's own: the machine of the 2-minute bar has two cores, and
# diagnose runs the shape's refit on top of the effect found beside the search too
WORKERS = 1


class Ahead:
    """Jobs run in a thread pool of `WORKERS` (none where not `enabled`: every `take`
    answers None and the caller runs the job itself)."""

    def __init__(self, enabled: bool = True):
        self._pool = (ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="jaxwear-law")
                      if enabled else None)
        self._jobs: dict = {}
        self._stops: dict = {}  # key -> the event that stops its job at its next evaluation
        # the jobs whose result the search took, and the model evaluations they ran
        self.used = {"jobs": 0, "model_evaluations": 0}
        # those it did not take (skipped, or run by itself once it reached them)
        self.discarded = {"jobs": 0, "model_evaluations": 0}

    def submit(self, key, fn, *args, **kw) -> None:
        """Run `fn(*args, **kw)` ahead, under `key` (in the order submitted)."""
        if self._pool is None:
            return

        stop = threading.Event()

        def run():
            e0 = Model.own_evaluations()
            with held() as lines, stopping(stop):
                try:
                    out = fn(*args, **kw)
                except Stopped:  # the search will not take it (`drop`, `close`)
                    return None, lines, Model.own_evaluations() - e0
                except Exception as err:  # noqa: BLE001 (re-raised where it is taken)
                    return err, lines, Model.own_evaluations() - e0
            return out, lines, Model.own_evaluations() - e0

        self._jobs[key] = self._pool.submit(in_context(run))
        self._stops[key] = stop

    def take(self, key):
        """(the job's result, its progress lines) where it ran or runs (waiting for it),
        else None: none was submitted, or it had not started (it is cancelled, and the
        caller runs it itself). An exception the job raised is raised here, where the
        search would have met it."""
        fut = self._jobs.pop(key, None)
        if fut is None or fut.cancel():
            return None
        out, lines, evals = fut.result()
        self.used["jobs"] += 1
        self.used["model_evaluations"] += evals
        if isinstance(out, Exception):
            raise out
        return out, lines

    def started(self, key) -> bool:
        """Whether the job `key` runs or ran; one that has not started is cancelled (the
        caller runs it itself), as `take` would."""
        fut = self._jobs.get(key)
        if fut is None:
            return False
        if fut.cancel():
            del self._jobs[key]
            return False
        return True

    def finished(self, key) -> bool:
        """Whether the job `key` has ended (or none is held under it)."""
        fut = self._jobs.get(key)
        return fut is None or fut.done()

    def drop(self, key) -> None:
        """The job will not be taken: cancelled where it has not started, stopped at its
        next model evaluation where it runs (and counted at `close`)."""
        fut = self._jobs.get(key)
        if fut is None:
            return
        self._stops[key].set()
        if fut.cancel():
            del self._jobs[key]

    def close(self) -> None:
        """Every job not taken cancelled or waited for (they run inside the search's
        `effects.law.searching()`, which must outlast them), and counted as discarded."""
        if self._pool is None:
            return
        for key in self._jobs:  # what runs stops at its next evaluation
            self._stops[key].set()
        for fut in self._jobs.values():
            if fut.cancel():
                continue
            try:
                _, _, evals = fut.result()
            except CancelledError:
                continue
            self.discarded["jobs"] += 1
            self.discarded["model_evaluations"] += evals
        self._jobs.clear()
        self._pool.shutdown(wait=True)


class Shared:
    """A job's tasks (independent of each other, each decided before the job starts them),
    claimed one at a time: by the job in their order, and by the search once it reaches
    the job, from the end, so that the search runs what the job has not begun while the
    job runs its own, instead of waiting for the whole job. Why: on the generator's
    fatigue study the laws with memory (their starts' forward runs, then a damage's fit
    and a film's, each with its left-out checks) ran as one job on the second core, and
    the search, done with the memoryless laws, waited 11-12 s for it with its own core
    idle. The tasks' results are those of the same calls wherever they run."""

    def __init__(self):
        self._lock = threading.Lock()
        self._ready = threading.Event()
        self.head = None  # what the job computed before its tasks
        self.items: list = []
        self._owner: dict = {}
        self._done: dict = {}
        self._out: dict = {}

    def publish(self, head, items) -> None:
        """The job's tasks are known (`head`: what it computed to know them)."""
        self.head, self.items = head, list(items)
        self._done = {i: threading.Event() for i in range(len(self.items))}
        self._ready.set()

    def wait_ready(self, ended) -> bool:
        """Wait until the tasks are published (True) or `ended()` says that the job ended
        without publishing them (False: it raised, or was stopped)."""
        while not self._ready.wait(0.05):
            if ended():
                return self._ready.is_set()
        return True

    def claim(self, i: int) -> bool:
        """The job's claim of task `i` (False: the search runs it)."""
        with self._lock:
            if i in self._owner:
                return False
            self._owner[i] = "job"
            return True

    def put(self, i: int, out) -> None:
        """The job's result of task `i`."""
        self._out[i] = out
        self._done[i].set()

    def claim_rest(self) -> list[int]:
        """The tasks the search takes: every one the job has not claimed, but the first
        of them where the job is between tasks (it claims that one next)."""
        with self._lock:
            rest = [i for i in range(len(self.items)) if i not in self._owner]
            busy = any(who == "job" and not self._done[i].is_set()
                       for i, who in self._owner.items())
            mine = rest if busy else rest[1:]
            for i in mine:
                self._owner[i] = "search"
            return mine

    def result(self, i: int):
        """The job's result of task `i` (waiting for it)."""
        self._done[i].wait()
        return self._out[i]
