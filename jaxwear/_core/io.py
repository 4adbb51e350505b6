"""Outputs of the command line: never over an input, never half written.

Every verb opens its outputs with one call before any work,

    out = open_outputs(study, args.out, planned=[...], json_file=args.json)

which refuses (`InputError`, exit 2) an output folder that is a file, and any planned output
(a file under `--out`, or `--json FILE`) that would replace an input file: the study, its
effect files, its load files and its profile/history CSVs (for `synth`, the conditions
study and its data). Names not planned are checked again when written. Every file is
written to a temporary name in its folder and renamed over the final name (`os.replace`,
atomic on POSIX and Windows), so an interrupted run leaves the previous file or none, never
half a file; a full device is a `NoSpaceError` naming the file (exit 1, one line), and the
temporaries a killed run left are swept by the next run (`sweep_parts`). Each output
folder is created and probed with a real file (removed at once) before any work, so that an
output that cannot be written is refused (exit 2) before the computation, not after it.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import os
import re
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

from jaxwear._core.errors import InputError, NoSpaceError
from jaxwear._core.interrupt import raise_if_interrupted
from jaxwear._core.jsonfmt import _fmt, _json_default


def _key(p: Path):
    """(device, inode) of an existing file (catches hard links), else its resolved path."""
    try:
        st = p.stat()
        return ("inode", st.st_dev, st.st_ino)
    except OSError:
        return ("path", p.resolve())


FIGURE_DPI = 110  # of every figure a verb writes


class OutputDir:
    """An output folder whose writes never replace an input file and are atomic.

    - `root`: the folder (created; an existing file there is bad input).
    - `inputs`: files that must not be replaced.
    - `planned`: file names under `root` the verb will write; checked now, before any work.
    - `json_file`: the `--json FILE` path, if any; checked now too.
    """

    def __init__(self, root, inputs: Iterable = (), *, planned: Iterable[str] = (),
                 json_file=None):
        # An empty name is no folder: Path("") is ".", so `--out ""` (an unset shell
        # variable) wrote every output into the current folder without a word.
        for flag, value in (("<<out>>", root), ("<<json_file>>", json_file)):
            if value is not None and not str(value).strip():
                raise InputError(f"{flag} {str(value)!r}: an empty name; give a "
                                 + ("folder (`.` for the current one)" if flag == "<<out>>"
                                    else "file name") + " or leave the option out")
        self.root = Path(root)
        self._inputs = {_key(Path(p)) for p in inputs}
        self.json_file = Path(json_file) if json_file is not None else None
        _no_link_loop(self.root, "<<out>>")
        if self.root.exists() and not self.root.is_dir():
            raise InputError(f"{self.root}: <<out>> must be a folder, and this is a file"
                             + (" (an input of this run)" if self._is_input(self.root) else ""))
        for name in planned:
            self._check(self.root / name, "<<out>>")
        if self.json_file is not None:
            self._check(self.json_file, "<<json_file>>")
        # Each folder is created and written to now (a probe file, removed at once): an
        # unwritable output (permissions, a read-only mount, /proc, a path under a file)
        # was found only when the results were written, after the whole computation.
        _writable_folder(self.root, "<<out>>")
        sweep_parts(self.root)
        if self.json_file is not None:
            _writable_folder(self.json_file.parent, "<<json_file>>")

    def _is_input(self, p: Path) -> bool:
        return _key(p) in self._inputs or ("path", p.resolve()) in self._inputs

    def _check(self, p: Path, option: str) -> Path:
        _no_link_loop(p, option)
        if self._is_input(p):
            raise InputError(f"{p}: refusing to replace an input file of this run; choose "
                             f"another {option}")
        if p.is_dir():  # a file cannot be renamed over a folder
            raise InputError(f"{p}: is a folder, and {option} writes a file by this name; "
                             f"move it away or choose another {option}")
        return p

    def path(self, name: str) -> Path:
        """`root/name`, refused if it is an input file."""
        return self._check(self.root / name, "<<out>>")

    def _target(self, name_or_path) -> Path:
        p = Path(name_or_path)
        if p.is_absolute() or p.parent != Path("."):
            return self._check(p, "<<json_file>>")
        return self.path(str(p))

    def write_text(self, name: str, text: str) -> Path:
        p = self._target(name)
        atomic_write(p, text)
        return p

    def write_bytes(self, name: str, data: bytes) -> Path:
        """`root/name` with `data` (e.g. a PNG drawn beforehand)."""
        p = self.path(name)
        atomic_write(p, data)
        return p

    def write_csv(self, name: str, header: list[str], rows) -> Path:

        p = self.path(name)
        with atomic_open(p, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(header)
            for r in rows:
                w.writerow([_fmt(x) for x in r])
        return p

    def write_json(self, name_or_path, obj) -> Path:
        """JSON to `root/name`, or to a path with a folder (`--json FILE`; folders made)."""

        p = self._target(name_or_path)
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(p, json.dumps(obj, indent=2, default=_json_default) + "\n")
        return p

    def write_json_file(self, obj) -> Path | None:
        """The `--json FILE` given at construction (None when there was none)."""
        if self.json_file is None:
            return None
        # relative to the working folder, not to --out
        return self.write_json(self.json_file.resolve(), obj)

    def write_with(self, name: str, writer) -> Path:
        """`writer(path)` writes `root/name` through a library that wants a file name
        (e.g. netCDF): it gets a temporary name in the folder, renamed over `name` after."""
        p = self.path(name)
        with atomic_path(p) as tmp:
            writer(tmp)
        return p

    def savefig(self, fig, name: str, dpi: int = FIGURE_DPI) -> Path:
        p = self.path(name)
        save_figure(fig, p, dpi)
        return p


# `.NAME.PID.XXXXXXXX.part` (`_temporary`), and the older `.NAME.XXXXXXXX.part`
_PART = re.compile(r"^\..+?(?:\.(\d+))?\.[A-Za-z0-9_]{8}\.part$")
LEGACY_PART_AGE_S = 3600.0  # a temporary without a process id: swept once this old


def sweep_parts(folder: Path) -> list[Path]:
    """Remove the temporary files (`atomic_open`'s `.part`) that killed runs left in
    `folder`: those whose process is gone (its id is in the name), and those of older
    versions (no id) not touched for `LEGACY_PART_AGE_S`; a live run's are left alone
    (two runs may share a folder). Returns the paths removed. Issue 49: a kill -9 during
    a run left `out/.fit_a.png.*.part` behind."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        m = _PART.match(entry.name)
        if m is None or not entry.is_file(follow_symlinks=False):
            continue
        try:
            if m.group(1) is not None:
                if _alive(int(m.group(1))):
                    continue
            elif now - entry.stat(follow_symlinks=False).st_mtime < LEGACY_PART_AGE_S:
                continue
            os.unlink(entry.path)
            removed.append(Path(entry.path))
        except OSError:
            continue
    return removed


def _alive(pid: int) -> bool:
    """Whether a process with this id exists (this one included)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True  # another user's, or not ours to judge: left alone
    return True


def _no_link_loop(p: Path, option: str) -> None:
    """Refuse a path that is (or runs through) a symbolic link loop, named as such."""
    try:
        p.stat()
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise InputError(f"{p}: symbolic link loop (the link leads back to itself); "
                             f"fix the link or choose another {option}") from None


def _writable_folder(folder: Path, option: str) -> None:
    """Create `folder` (with its parents) and write and remove a probe file in it; an
    `InputError` (exit 2) naming the folder and the reason when that fails."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{folder}: cannot create the output folder ({e.strerror or e}); "
                         f"choose another {option}") from None
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".jaxwear-probe-", suffix=".part")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise InputError(f"{folder}: cannot write to the output folder ({e.strerror or e}); "
                         f"choose another {option}") from None


_UMASK = None


def _mode() -> int:
    # mkstemp makes 0600 files; a written output should get the usual 0666 & ~umask.
    global _UMASK
    if _UMASK is None:
        _UMASK = os.umask(0)
        os.umask(_UMASK)
    return 0o666 & ~_UMASK


# the errors of a full device: the disk (ENOSPC) or the user's quota (EDQUOT)
FULL = tuple(e for e in (errno.ENOSPC, getattr(errno, "EDQUOT", None)) if e is not None)


def _temporary(path: Path) -> tuple[int, str]:
    """A temporary file beside `path` (fd, name): `.NAME.PID.XXXXXXXX.part`, the process
    id in the name so that the next run sweeps what a killed one left (`sweep_parts`)."""
    try:
        return tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{os.getpid()}.",
                                suffix=".part")
    except OSError as e:
        if e.errno in FULL:
            raise NoSpaceError(path, e.errno) from None
        raise


@contextlib.contextmanager
def atomic_open(path, mode: str = "w", **kw):
    """Open a temporary file beside `path`; on success it replaces `path`, on any error
    (or interrupt) it is removed and `path` is left as it was. A full device is a
    `NoSpaceError` naming `path`."""
    path = Path(path)
    fd, tmp = _temporary(path)
    try:
        if "b" not in mode:
            kw.setdefault("encoding", "utf-8")
        with os.fdopen(fd, mode, **kw) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _mode())
        raise_if_interrupted()  # a Ctrl-C whose exception was dropped: no output
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError) and not isinstance(e, NoSpaceError) and e.errno in FULL:
            raise NoSpaceError(path, e.errno) from None
        raise


@contextlib.contextmanager
def atomic_path(path):
    """A temporary file name beside `path` for a writer that opens files itself; on
    success it replaces `path`, on any error it is removed and `path` is left as it was."""
    path = Path(path)
    fd, tmp = _temporary(path)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, _mode())
        raise_if_interrupted()
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError) and not isinstance(e, NoSpaceError) and e.errno in FULL:
            raise NoSpaceError(path, e.errno) from None
        raise


def atomic_write(path, data: str | bytes) -> None:
    """Write `data` (text as UTF-8) to `path` through a temporary file and a rename."""
    with atomic_open(path, "wb" if isinstance(data, bytes) else "w") as f:
        f.write(data)


def png_bytes(fig, dpi: int = FIGURE_DPI) -> bytes:
    """`fig` rendered as PNG in memory (drawn in one place, written or embedded later)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def save_figure(fig, path, dpi: int = FIGURE_DPI) -> None:
    """`fig.savefig` through a temporary file (format from the suffix); where `path` is a
    binary file object (a figure drawn for another process: `_report.painter`), a PNG
    written to it."""
    if hasattr(path, "write"):
        fig.savefig(path, format="png", dpi=dpi)
        return
    path = Path(path)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format=path.suffix.lstrip(".") or "png", dpi=dpi)
