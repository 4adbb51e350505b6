"""Work done in a daemon thread while the caller's thread waits on XLA.

Why: XLA's compilation and the compiled programs' runs release the interpreter, and a cold
answer spends most of its time in them, on one core. What an answer will need next (a
finer level's forward program, the plotting library) can be made ready on the other core
meanwhile. What does not release the interpreter (JAX's tracing and lowering, importing a
module) only slows the caller's thread down if run beside its own tracing; `lowered`
tells a thread when the caller's program has been lowered and its XLA compilation begins.

- `Background`: `fn(*args, **kw)` in a daemon thread; `result()` joins it and re-raises
  what it raised.
- `lowered(pattern)`: an event set once JAX has lowered a program whose name contains
  `pattern` (a `jax.monitoring` listener on JAX's lowering event; where a later JAX renames
  that event the caller's own fallback sets it, see `Compiling` in `_inference.evaluation`).
- `in_context(fn)`: `fn` to run in another thread in a copy of the caller's context
  (`contextvars`), as `Background` does: what the caller's block registered for itself
  (the law search's effects, `effects._base.scoped_effects`) holds there too.
- Every thread started here is joined at the interpreter's exit (`atexit`): a compilation
  still running while the interpreter tears down its modules may crash it. The command
  line ends its process without that teardown and calls `abandon` first (`_core.interrupt`),
  so that a compilation nobody waits for does not hold up its exit.
"""

from __future__ import annotations

import atexit
import contextvars
import threading
from collections.abc import Callable

import jax

# JAX's event at the end of a program's lowering to MLIR (its XLA compilation follows)
LOWERED_EVENT = "/jax/core/compile/jaxpr_to_mlir_module_duration"

_lock = threading.Lock()
_threads: list[threading.Thread] = []  # started here and not yet abandoned
_watch: list[tuple[str, threading.Event]] = []  # `lowered` events not yet set
_listening = False


class Background:
    """`fn(*args, **kw)` in a daemon thread (named after `fn`); `result()` joins it and
    re-raises what it raised; `done` is set when it has ended."""

    def __init__(self, fn: Callable, *args, **kw):
        self._out = None
        self._err: BaseException | None = None
        self.done = threading.Event()

        def run():
            try:
                self._out = fn(*args, **kw)
            except BaseException as e:  # re-raised in the caller's thread
                self._err = e
            finally:
                self.done.set()

        self._thread = threading.Thread(target=in_context(run), daemon=True,
                                        name=f"jaxwear-{getattr(fn, '__name__', 'work')}")
        with _lock:
            _threads[:] = [t for t in _threads if t.is_alive()]
            _threads.append(self._thread)
        self._thread.start()

    def join(self) -> None:
        self._thread.join()

    def result(self):
        self._thread.join()
        if self._err is not None:
            raise self._err
        return self._out


def in_context(fn: Callable) -> Callable:
    """`fn` run in a copy of the calling thread's context (`contextvars`), wherever it is
    called: a thread (its own or a pool's) starts in an empty context otherwise."""
    ctx = contextvars.copy_context()
    return lambda *a, **kw: ctx.run(fn, *a, **kw)


def _on_duration(event: str, duration: float, **kw) -> None:
    if event != LOWERED_EVENT or not _watch:
        return
    name = str(kw.get("fun_name", ""))
    with _lock:
        hit = [w for w in _watch if w[0] in name]
        _watch[:] = [w for w in _watch if w not in hit]
    for _, ev in hit:
        ev.set()


def lowered(pattern: str) -> threading.Event:
    """An event set once JAX has lowered a program whose name contains `pattern` (in any
    thread; a program already compiled in this process is not lowered again: the caller
    sets the event itself where that can be)."""
    global _listening
    ev = threading.Event()
    with _lock:
        if not _listening:
            jax.monitoring.register_event_duration_secs_listener(_on_duration)
            _listening = True
        _watch.append((pattern, ev))
    return ev


def forget(ev: threading.Event) -> None:
    """Stop watching for `ev`'s lowering (and set it: whoever waits on it goes on)."""
    with _lock:
        _watch[:] = [w for w in _watch if w[1] is not ev]
    ev.set()


def abandon() -> None:
    """Leave the threads started so far to the process's end: not joined at exit (the
    command line ends its process with `os._exit` right after)."""
    with _lock:
        _threads.clear()


@atexit.register
def _join_at_exit() -> None:
    with _lock:
        threads = list(_threads)
        _threads.clear()
    for t in threads:
        t.join()
