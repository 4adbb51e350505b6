"""Figures drawn in a second process while this one goes on.

Why: a `simulate` of the rig study writes 15 PNG figures, and matplotlib took ~2.2 s of
the ~3.6 s a run on a filled compilation cache lasts (2-core AMD EPYC, 2026-11-30), all of
it in Python on one core. A helper process draws every other figure beside the one that
computes: it starts when the verb does (numpy and matplotlib only: the stub below keeps
`jaxwear/__init__.py`, and JAX with it, out of it; ~0.5 s on the second core, beside the
model's tracing and compilation) and sends back the PNG bytes.

The helper only draws. Every file is still written by this process, through the same
atomic writes as an inline figure (`_core.io`), so that an interrupted run writes nothing
after its line and a full disk names its file. A figure that failed in the helper, or
one left when the helper died, is drawn again here, where its error is raised as it would
have been without the helper; the helper is a speed-up and never changes an answer (its
PNG is byte for byte the one drawn here: `tests/test_painter.py`).

`JAXWEAR_FIGURE_PROCESS=0` draws every figure in this process.
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import queue
import struct
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

_HEADER = struct.Struct("<QBQ")  # job id, status (0 ok, 1 failed), payload length
_JOB = struct.Struct("<QQ")  # job id, payload length
_PACKAGE = str(Path(__file__).resolve().parents[1])

# The helper: a bare `jaxwear` package object (its folder, not its __init__) so that the
# figure modules import with numpy and matplotlib alone.
_BOOT = ("import sys, types\n"
         "m = types.ModuleType('jaxwear'); m.__path__ = [sys.argv[1]]\n"
         "sys.modules['jaxwear'] = m\n"
         "from jaxwear._report.painter import serve\n"
         "serve()\n")

PENDING = 2
"""Figures the helper may hold at once (the one it draws and the next); beyond, this
process draws the figure itself rather than wait."""


def enabled() -> bool:
    """Whether verbs draw in a helper process (`JAXWEAR_FIGURE_PROCESS`, default on)."""
    return os.environ.get("JAXWEAR_FIGURE_PROCESS", "1") != "0"


def _plain(x):
    """`x` with JAX arrays as NumPy ones (the helper does not import JAX)."""
    if isinstance(x, (list, tuple)):
        return type(x)(_plain(v) for v in x)
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if type(x).__module__.startswith(("jax", "jaxlib")):
        import numpy as np

        return np.asarray(x)
    return x


class Painter:
    """Draws figures `fn(path, *args, **kwargs)` (a module-level function of the report
    layer that saves its figure to `path` with `_core.io.save_figure`): in the helper
    process where one runs and holds fewer than `PENDING` figures, else here.

    Use as a context manager: on leaving the block normally every figure is written
    (`close`); on an exception the helper is stopped and nothing more is written."""

    def __init__(self, helper: bool | None = None):
        self._proc: subprocess.Popen | None = None
        self._replies: queue.Queue = queue.Queue()
        self._pending: collections.OrderedDict = collections.OrderedDict()
        self._next = 0
        self._reader: threading.Thread | None = None
        self.drawn_here = self.drawn_there = 0  # figures drawn in each process (tests)
        if enabled() if helper is None else helper:
            self._start()

    def _start(self) -> None:
        if not sys.executable:
            return
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-c", _BOOT, _PACKAGE], stdin=subprocess.PIPE,
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, bufsize=0)
        except OSError:  # no process can be started here: every figure is drawn here
            self._proc = None
            return
        self._reader = threading.Thread(target=self._read, args=(self._proc.stdout,),
                                        daemon=True, name="jaxwear-painter")
        self._reader.start()

    def _read(self, stream) -> None:
        # replies in a thread: `draw` looks at finished figures without blocking
        try:
            while True:
                head = _exactly(stream, _HEADER.size)
                if head is None:
                    break
                job, status, n = _HEADER.unpack(head)
                data = _exactly(stream, n)
                if data is None:
                    break
                self._replies.put((job, status, data))
        finally:
            self._replies.put(None)  # the helper is gone

    def __enter__(self) -> Painter:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()

    def draw(self, path, fn: Callable, *args, **kwargs) -> None:
        """Draw `fn(path, *args, **kwargs)`, here or in the helper; a figure drawn there is
        written to `path` by a later `draw` or by `close`."""
        self._collect(block=False)
        if self._proc is not None and len(self._pending) < PENDING:
            job = self._next
            self._next += 1
            try:
                payload = pickle.dumps((fn, _plain(args), _plain(kwargs)),
                                       protocol=pickle.HIGHEST_PROTOCOL)
                self._proc.stdin.write(_JOB.pack(job, len(payload)) + payload)
            except (OSError, ValueError, pickle.PicklingError, AttributeError, TypeError):
                self._lost()
            else:
                self._pending[job] = (path, fn, args, kwargs)
                return
        self.drawn_here += 1
        fn(path, *args, **kwargs)

    def _collect(self, block: bool) -> None:
        """Write the figures the helper has finished (all of them, where `block`)."""
        while self._pending:
            try:
                reply = self._replies.get(block=block, timeout=120 if block else None)
            except queue.Empty:
                if block:  # a figure takes a second at most: the helper hangs
                    self._lost()
                return
            if reply is None:
                self._lost()
                return
            job, status, data = reply
            path, fn, args, kwargs = self._pending.pop(job)
            if status == 0:
                from jaxwear._core.io import atomic_write

                self.drawn_there += 1
                atomic_write(path, data)
            else:  # drawn again here, where its error is raised as without the helper
                self.drawn_here += 1
                fn(path, *args, **kwargs)

    def _lost(self) -> None:
        """The helper is gone (or hangs): stop it and draw what it held here."""
        self._stop(kill=True)
        pending, self._pending = self._pending, collections.OrderedDict()
        for path, fn, args, kwargs in pending.values():
            self.drawn_here += 1
            fn(path, *args, **kwargs)

    def close(self) -> None:
        """Write every figure (waiting for the helper's) and end the helper."""
        try:
            self._collect(block=True)
        except BaseException:  # a figure failed here: the others are not written
            self.abort()
            raise
        self._stop(kill=False)

    def abort(self) -> None:
        """End the helper now; the figures it holds are not written."""
        self._pending.clear()
        self._stop(kill=True)

    def _stop(self, kill: bool) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()  # the helper ends at the end of its input
        except OSError:
            pass
        if kill:
            proc.kill()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        self._reader.join(timeout=10)  # at the pipe's end, now that the helper has ended
        proc.stdout.close()


def _exactly(stream, n: int) -> bytes | None:
    """`n` bytes from `stream`, or None at its end."""
    chunks, left = [], n
    while left:
        chunk = stream.read(left)
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def serve() -> None:
    """The helper's loop: jobs from stdin, PNG bytes (or a failure) to stdout, until stdin
    ends. Ctrl-C is the verb's to handle: the helper ignores it and ends with its input."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from jaxwear._report.figures import plt

    plt()  # matplotlib imported before the first job arrives
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    while True:
        head = _exactly(stdin, _JOB.size)
        if head is None:
            return
        job, n = _JOB.unpack(head)
        payload = _exactly(stdin, n)
        if payload is None:
            return
        try:
            fn, args, kwargs = pickle.loads(payload)
            buf = io.BytesIO()
            fn(buf, *args, **kwargs)
            status, data = 0, buf.getvalue()
        except Exception as e:  # the verb draws it again itself and raises the error
            status, data = 1, repr(e).encode()
        stdout.write(_HEADER.pack(job, status, len(data)) + data)
        stdout.flush()
