"""Ctrl-C at any moment of the command line is one line and exit 1 (issue 29).

`cli.main` turns a `KeyboardInterrupt` into `jaxwear: interrupted` and exit 1 (design.md §7:
0 done, 2 bad input, 1 anything else; not the shell's 130, so that scripts see only the
three documented codes). Before `main` runs, the package itself is being imported (JAX takes
seconds), and an interrupt there printed Python's traceback. `guard_import` is called first
thing in `jaxwear/__init__.py`: when this process is the command line (`jaxwear ...` or
`python -m jaxwear ...`, never a user's own program importing jaxwear), an interrupt before
`main` prints the same one line and exits 1. It does so from the signal handler itself, not
by raising: a `KeyboardInterrupt` raised while a compiled extension is initialising (jaxlib's
MLIR bindings call back into Python) cannot unwind through C++ and aborted the process with
exit -6 and a C++ trace (seen once in CI). `main` hands SIGINT back to Python
(`release`) once it can catch the exception itself. Outputs are written atomically (`_io`),
so an interrupted run leaves the previous file or none.
"""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

MESSAGE = "jaxwear: interrupted"
EXIT_CODE = 1


def launched_as_cli() -> bool:
    """True when this process runs the command line: the `jaxwear` script or `python -m
    jaxwear` (`sys.orig_argv`: while -m locates the module, `sys.argv[0]` is only '-m')."""
    if Path(sys.argv[0] if sys.argv else "").name in ("jaxwear", "jaxwear.exe"):
        return True
    orig = list(getattr(sys, "orig_argv", ()))
    return any(a == "-m" and orig[i + 1:i + 2] == ["jaxwear"] for i, a in enumerate(orig))


def guard_import() -> None:
    """In the command line's process, an uncaught `KeyboardInterrupt` (during `import
    jaxwear`, before `main` catches it) becomes `MESSAGE` and exit `EXIT_CODE`."""
    if not launched_as_cli():
        return
    previous = sys.excepthook

    def hook(kind, value, tb):
        if issubclass(kind, KeyboardInterrupt):
            try:
                print(MESSAGE, file=sys.stderr, flush=True)
            finally:
                os._exit(EXIT_CODE)  # nothing to clean up: no output is open yet
        previous(kind, value, tb)

    sys.excepthook = hook

    def on_sigint(signum, frame):
        os.write(2, (MESSAGE + "\n").encode())
        os._exit(EXIT_CODE)  # nothing to clean up: no output is open yet

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not if ignored
        signal.signal(signal.SIGINT, on_sigint)
        _GUARD.append(on_sigint)


_GUARD: list = []

# While `cli.main` runs (`release` .. `restore`): whether a Ctrl-C came. Python raises the
# `KeyboardInterrupt` at whatever bytecode runs when the signal is handled, and one that
# lands in a garbage-collector callback (JAX's `_xla_gc_callback`) or a `__del__` is
# printed as "Exception ignored" and dropped: a Ctrl-C just after a fit then ran on to exit
# 0 with every output written (issue 41). The flag outlives the exception: outputs are not
# written once it is set (`_io`, `raise_if_interrupted`) and `main` exits `EXIT_CODE`.
_STATE = {"armed": False, "interrupted": False}


def _on_sigint(signum, frame):
    if _STATE["armed"]:
        _STATE["interrupted"] = True
    raise KeyboardInterrupt


def _unraisable(previous):
    def hook(info):
        # the dropped `KeyboardInterrupt` is remembered (`_on_sigint`); its "Exception
        # ignored in ..." traceback would be the run's last words otherwise
        if not (_STATE["armed"] and isinstance(info.exc_value, KeyboardInterrupt)):
            previous(info)

    return hook


def release() -> None:
    """From here on Ctrl-C raises `KeyboardInterrupt` again (caught by `cli.main`), and is
    remembered even where the exception is dropped (`interrupted`), silently."""
    _STATE.update(armed=True, interrupted=False, unraisable=sys.unraisablehook)
    sys.unraisablehook = _unraisable(sys.unraisablehook)
    current = signal.getsignal(signal.SIGINT)
    if (_GUARD and current is _GUARD[0]) or current is signal.default_int_handler:
        signal.signal(signal.SIGINT, _on_sigint)


def restore() -> None:
    """The end of `cli.main`: Python's own Ctrl-C handling again, the flag cleared (a
    process that calls `main` and goes on, a notebook or a test, is not left flagged)."""
    _STATE.update(armed=False, interrupted=False)
    if _STATE.get("unraisable") is not None:
        sys.unraisablehook = _STATE.pop("unraisable")
    if signal.getsignal(signal.SIGINT) is _on_sigint:
        signal.signal(signal.SIGINT, signal.default_int_handler)


SHUTDOWN_MESSAGE = f"{MESSAGE} while shutting down (the outputs were written)"


def shutting_down(rc: int) -> None:
    """After `cli.main` returns `rc` in the command line's process: a Ctrl-C while the
    process shuts down (JAX's exit hook waits for its backends: half a second after a
    calibrate, issue 49) prints one line and exits at once with `rc`, not a traceback from
    the hook: the run had ended, so its exit status stands (0: the outputs are complete,
    and the line says so)."""

    line = (SHUTDOWN_MESSAGE if rc == 0 else f"{MESSAGE} while shutting down") + "\n"

    def on_sigint(signum, frame):
        os.write(2, line.encode())
        os._exit(rc)

    if signal.getsignal(signal.SIGINT) in (signal.default_int_handler, _on_sigint):
        signal.signal(signal.SIGINT, on_sigint)


def end_process(rc: int) -> None:
    """End the command line's process with `rc` once `cli.main` has returned: the exit
    hooks run (`atexit`: JAX's backends cleared, logging flushed, `weakref.finalize`'s
    clean-ups), the standard streams are flushed, and the process ends without the
    interpreter's teardown of modules and XLA's executables, which took 0.2-0.5 s after
    every command and did nothing a user sees (measured 2026-11-29 after the rig study's
    `calibrate`: 0.07 s in the exit hooks, 0.11 s in a garbage collection, ~0.4 s in all;
    interleaved, cold: `calibrate` 8.01, 8.33 -> 7.74, 8.15 s, `simulate` of the README
    4.52-5.09 -> 4.40-4.56 s). Every output is written and closed by then (atomically,
    `_core.io`). Only where `main` returned: an exit on its way (argparse's `--help`)
    is Python's. A background compilation nobody waits for any more (a finer level's
    forward program the check did not need, `_core.background`) is left to the end, not
    joined."""
    import atexit

    from jaxwear._core import background

    background.abandon()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can be said on it
            pass
    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(rc)


def interrupted() -> bool:
    """Whether a Ctrl-C came while `cli.main` runs (even one whose exception was dropped)."""
    return bool(_STATE["armed"] and _STATE["interrupted"])


def raise_if_interrupted() -> None:
    """`KeyboardInterrupt` if `interrupted()`: called before an output replaces its file."""
    if interrupted():
        raise KeyboardInterrupt
