"""The one reader of the CSV files a study names (profiles, histories, load files)."""

from __future__ import annotations

import csv
import errno
import math
import os
import sys
from pathlib import Path

import numpy as np

from jaxwear._core.errors import InputError


def _read_csv(path: Path, columns: list[str], optional: list[str] = (),
              alternatives: dict | None = None):
    """Rows of a CSV file whose header starts with `columns` (each may be replaced by one of
    `alternatives[column]`), then any of `optional`; other columns are ignored with a note.

    Returns (the header names used, in the order `columns + present optional`, and an array
    with those columns)."""
    _exists(path, "data file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a data file")
    text = read_text(path, "data file")
    rows = list(csv.reader(line for line in text.splitlines() if line.strip()))
    if not rows:
        raise InputError(f"{path}: empty file; expected a header {','.join(columns)}")
    header = [h.strip() for h in rows[0]]
    alternatives = alternatives or {}
    used = []
    for c in columns:
        names = [c, *alternatives.get(c, ())]
        found = [n for n in names if n in header]
        if len(found) != 1:
            expected = ",".join(columns) + (f"[,{','.join(optional)}]" if optional else "")
            what = "missing" if not found else "given twice as " + " and ".join(found)
            raise InputError(f"{path}: line 1: columns {header}; expected {expected} "
                             f"(column {c!r} {what})")
        used.append(found[0])
    used += [o for o in optional if o in header]
    if len(set(header)) != len(header):
        raise InputError(f"{path}: line 1: a column name is repeated in {header}")
    extra = [h for h in header if h not in used]
    if extra:
        print(f"note: {path}: ignoring column(s) {', '.join(map(repr, extra))}",
              file=sys.stderr)
    idx = [header.index(u) for u in used]
    if len(rows) == 1:
        raise InputError(f"{path}: no data rows after the header")
    data = []
    for i, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputError(f"{path}: line {i}: {len(row)} values, expected {len(header)}")
        try:
            vals = [float(row[j]) for j in idx]
        except ValueError:
            j = next(j for j in idx if not _is_float(row[j]))
            raise InputError(f"{path}: line {i}, column {j + 1} ({header[j]}): "
                             f"{row[j].strip()!r} is not a number") from None
        for name, v in zip(used, vals):
            if not math.isfinite(v):
                raise InputError(f"{path}: line {i}: {name} is {v} (NaN/inf are not allowed; "
                                 f"leave the row out instead)")
        data.append(vals)
    return used, np.array(data)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _exists(path: Path, what: str) -> None:
    """`InputError` unless `path` exists: a symbolic link loop or a link to nothing is
    named as such (a loop once read "not found")."""
    try:
        path.stat()
        return
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise InputError(f"{path}: symbolic link loop (the link leads back to itself); "
                             f"point it at the {what}") from None
    if path.is_symlink():
        raise InputError(f"{path}: symbolic link to {os.readlink(path)!r}, which does not "
                         f"exist; point it at the {what}")
    raise InputError(f"{path}: {what} not found")


def read_text(path: Path, what: str) -> str:
    """The file as UTF-8 text (a byte-order mark is not data). A byte that is not UTF-8
    (Latin-1 or Windows-1252 from a spreadsheet) is reported with its line and column,
    not its byte offset."""
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise InputError(f"{path}: cannot read the {what} ({e.strerror or e})") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        col = e.start - (raw.rfind(b"\n", 0, e.start) + 1) + 1
        raise InputError(f"{path}: line {line}: byte 0x{raw[e.start]:02x} at column {col} "
                         f"is not UTF-8 (Latin-1 or Windows-1252?); save the file as UTF-8"
                         ) from None
