"""Progress lines: the one way every layer speaks to the user while it works (stderr, flushed,
so that a long run shows where it is; stdout stays for the verbs' results)."""

from __future__ import annotations

import sys
import threading
from contextlib import contextmanager

_held = threading.local()


def log(verbose: bool, msg: str) -> None:
    """Print `msg` as one progress line on stderr when `verbose` (kept instead where this
    thread holds its lines: `held`)."""
    if verbose:
        lines = getattr(_held, "lines", None)
        if lines is not None:
            lines.append(msg)
            return
        print(msg, file=sys.stderr, flush=True)


@contextmanager
def held():
    """The lines this thread logs inside the block are kept in the list it yields, not
    printed: for work that runs beside other work's progress (`diagnose`'s refit on top
    of the effect found, beside the law search), whose caller prints them once it is
    done, so that the two's lines do not interleave."""
    prev = getattr(_held, "lines", None)
    lines: list[str] = []
    _held.lines = lines
    try:
        yield lines
    finally:
        _held.lines = prev


def progress(msg: str) -> None:
    """Print `msg` as one progress line on stderr."""
    log(True, msg)
