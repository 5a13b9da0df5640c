"""The online session's append-only log: one JSON object per line, flushed and fsynced as each event happens.

A line is written with one ``write`` of ``json + "\\n"``, then ``flush`` and
``os.fsync``, so a crash (``kill -9``, power loss after the fsync returns)
loses at most the line in flight. :func:`read_journal` therefore tolerates a
last line that is cut short or is not JSON (dropped and counted in
:attr:`JournalContents.truncated`); a bad line anywhere else is corruption and
raises :class:`JournalError` naming the file and line. :class:`Journal` opened
on an existing log first cuts such a tail off, so new lines never follow a
half-written one.

Every record is a mapping with an ``"e"`` (event) key; the first line is the
``"header"``. Numbers are written by ``json`` (``repr``: float64 round-trips
exactly); a non-finite number is written as ``null`` and read back as NaN
(:func:`floats`). What the events mean is the online runner's business
(:mod:`selfid_jax.robot.live`); this module only writes and reads lines.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from selfid_jax.strict_json import jsonable

__all__ = ["Journal", "JournalContents", "JournalError", "floats", "read_journal"]


class JournalError(ValueError):
    """A session log that cannot be read or resumed; the message names the file and line (or field)."""


class JournalContents(NamedTuple):
    """A session log as read back."""

    header: dict[str, Any]  # the first record (its "e" is "header")
    records: list[dict[str, Any]]  # every later record, in order
    truncated: int  # 0 or 1: a cut-short last line that was dropped
    good_bytes: int  # length of the file up to the end of its last complete line


def floats(values: Any) -> np.ndarray:
    """A logged list of numbers as float64, ``None`` (a non-finite number) as NaN."""
    return np.array([np.nan if v is None else v for v in values], np.float64)


def read_journal(path: str | Path) -> JournalContents:
    """Read a session log; a cut-short last line is dropped and counted.

    Raises:
      JournalError: the file is missing or empty, its first line is not a
        header, or a line other than the last is not a JSON object.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise JournalError(f"{path}: cannot read the session log: {err.strerror or err}") from None
    lines = data.split(b"\n")
    # data ending in "\n" splits into [..., b""]: the last element is the unterminated tail (possibly empty)
    tail = lines.pop()
    records: list[dict[str, Any]] = []
    truncated = 1 if tail.strip() else 0
    good = len(data) - len(tail)
    offset = 0
    for i, raw in enumerate(lines):
        last = i == len(lines) - 1 and not tail.strip()
        try:
            rec = json.loads(raw)
            if not isinstance(rec, dict) or "e" not in rec:
                raise ValueError("not an event record")
        except ValueError:
            if last:  # a complete-looking last line that is not JSON: lost in flight all the same
                truncated, good = 1, offset
                break
            raise JournalError(f"{path}: line {i + 1} is not a JSON event record; the log is corrupt "
                               "(only its last line may be cut short)") from None
        records.append(rec)
        offset += len(raw) + 1
    if not records or records[0].get("e") != "header":
        raise JournalError(f"{path}: the first line is not a session header; not a session log")
    return JournalContents(header=records[0], records=records[1:], truncated=truncated, good_bytes=good)


class Journal:
    """An append-only log file: :meth:`append` writes one record as one line and fsyncs it.

    Opening an existing file with ``good_bytes`` (from :func:`read_journal`)
    cuts the file to that length first, dropping a half-written last line.
    """

    def __init__(self, path: str | Path, *, good_bytes: int | None = None):
        self.path = Path(path)
        self.lines = 0
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o666)
        if good_bytes is not None:
            os.ftruncate(fd, good_bytes)
        self._f = os.fdopen(fd, "ab", buffering=0)

    def append(self, record: dict[str, Any]) -> None:
        """Write ``record`` (a mapping with an ``"e"`` key) as one JSON line, then fsync."""
        line = json.dumps(jsonable(record), separators=(",", ":"), allow_nan=False) + "\n"
        self._f.write(line.encode("utf-8"))
        os.fsync(self._f.fileno())
        self.lines += 1

    def close(self) -> None:
        """Close the file (idempotent)."""
        if not self._f.closed:
            self._f.close()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
