"""Progress lines: the one way every layer speaks to the user while it works (stderr, flushed,
so that a long run shows where it is; stdout stays for the verbs' results)."""

from __future__ import annotations

import sys


def log(verbose: bool, msg: str) -> None:
    """Print `msg` as one progress line on stderr when `verbose`."""
    if verbose:
        print(msg, file=sys.stderr, flush=True)


def progress(msg: str) -> None:
    """Print `msg` as one progress line on stderr."""
    log(True, msg)
