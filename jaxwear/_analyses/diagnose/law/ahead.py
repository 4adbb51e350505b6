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
"""

from __future__ import annotations

import threading
from concurrent.futures import CancelledError, ThreadPoolExecutor

from jaxwear._analyses.diagnose._model import Model, Stopped, stopping
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

        self._jobs[key] = self._pool.submit(run)
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

