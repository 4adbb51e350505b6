"""Where a jaxwear command's time goes, per program and per phase (issue 48, the 2-minute
bar of `diagnose --shape`): every progress line on stderr stamped with the wall time and
the process's CPU time (user + sys, every thread) since the start, so that a phase's CPU
is the difference of two lines' stamps (on a shared machine the wall time depends on the
others' load, the CPU time much less); and a JSON of each compiled program's compilations
(count; trace, lowering and XLA seconds by `jax.monitoring`, wall, summed over threads)
and each jaxwear program's runs (`jaxwear._core.jit.Jit` calls timed to their result, the
caller's own compilation taken out, as `benchmarks/time_to_answer.py`'s `_RUNNER`).

    JAXWEAR_NO_CACHE=1 python benchmarks/profile_phases.py OUT.json -- diagnose STUDY.toml \\
        --shape --out DIR 2> stamped.log

Not a test: figures depend on the machine and its load.
"""

from __future__ import annotations

import collections
import json
import resource
import sys
import threading
import time

T0 = time.perf_counter()
COMPILE_EVENTS = {"/jax/core/compile/jaxpr_trace_duration": 1,
                  "/jax/core/compile/jaxpr_to_mlir_module_duration": 2,
                  "/jax/core/compile/backend_compile_duration": 3}


def cpu() -> float:
    """CPU seconds (user + sys) of this process so far, every thread."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class Stamped:
    """A text stream whose every line is prefixed with [wall w, CPU c] since the start."""

    def __init__(self, f):
        self.f, self.buf = f, ""

    def write(self, s):
        self.buf += s
        while "\n" in self.buf:
            line, self.buf = self.buf.split("\n", 1)
            self.f.write(f"[{time.perf_counter() - T0:7.1f} w {cpu():7.1f} c] {line}\n")
        self.f.flush()
        return len(s)

    def flush(self):
        self.f.flush()

    def __getattr__(self, k):
        return getattr(self.f, k)


def main(argv) -> int:
    out_json, args = argv[0], argv[2:] if argv[1:2] == ["--"] else argv[1:]
    sys.stderr = Stamped(sys.stderr)
    import jax
    import jax.monitoring as mon

    comp = collections.defaultdict(lambda: [0, 0.0, 0.0, 0.0])  # n, trace, lower, xla
    mine: dict[int, float] = {}  # thread: its own compile seconds
    events = []

    def listen(event, duration, **kw):
        k = COMPILE_EVENTS.get(event)
        if k is None:
            return
        name = kw.get("fun_name", "?")
        comp[name][k] += duration
        if k == 3:
            comp[name][0] += 1
            events.append((round(time.perf_counter() - T0, 1), name, round(duration, 2)))
        t = threading.get_ident()
        mine[t] = mine.get(t, 0.0) + duration

    mon.register_event_duration_secs_listener(listen)
    from jaxwear import cli
    from jaxwear._core import jit as J

    runs = collections.defaultdict(lambda: [0, 0.0])
    plain_call = J.Jit.__call__

    def timed_call(self, *a, **k):
        if J._traced(a, k):
            return plain_call(self, *a, **k)
        t = threading.get_ident()
        c0, s0 = mine.get(t, 0.0), time.perf_counter()
        out = jax.block_until_ready(plain_call(self, *a, **k))
        r = runs[getattr(self.fun, "__qualname__", str(self.fun))]
        r[1] += time.perf_counter() - s0 - (mine.get(t, 0.0) - c0)
        r[0] += 1
        return out

    J.Jit.__call__ = timed_call
    try:
        return cli.main(args)
    finally:
        r = resource.getrusage(resource.RUSAGE_SELF)
        with open(out_json, "w") as f:
            json.dump({"wall": time.perf_counter() - T0, "cpu": r.ru_utime + r.ru_stime,
                       "user": r.ru_utime, "sys": r.ru_stime, "compile": dict(comp),
                       "compile_total": sum(v[1] + v[2] + v[3] for v in comp.values()),
                       "runs": dict(runs), "runs_total": sum(v[1] for v in runs.values()),
                       "events": events}, f, indent=1)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
