"""Keeping a run directory whole: one process at a time, whole files only.

The lock. ``hold(RUN)`` takes ``fcntl.flock(LOCK_EX | LOCK_NB)`` on
``RUN/.lock`` and writes this process's id into it. The kernel drops the lock
when the process exits, however it exits (``kill -9`` included), so a stale
``.lock`` file never blocks a later run; the file itself stays (removing it
would let two processes lock two different files of the same name). A second
process asking for the lock is refused at once with :class:`RunDirBusy`.
The lock is re-entrant within a process: a process-level registry counts the
holds, so ``selfid-jax sweep`` holding ``RUN`` does not block its own
:func:`selfid_jax.sweep.run_chunked` into ``RUN/parts/<name>``, which locks
``RUN`` too. Threads of one process share the hold. ``flock`` is advisory and
local to one machine: on NFS a process on another host may not see it.

Whole files. :func:`atomic_write_bytes` writes a temporary file in the same
directory, fsyncs it and renames it over the target, so a kill or a full disk
never leaves a half-written file under its final name (nor a temporary one),
and gives it the permissions the user's umask gives a new file.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import math
import os
import tempfile
import threading
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from selfid_jax.config import ConfigError

__all__ = ["LOCK_FILE", "RunDirBusy", "RunDirError", "atomic_write_bytes", "atomic_write_text", "hold", "make_run_dir",
           "write_json"]

LOCK_FILE = ".lock"

_HELD: dict[Path, list[int]] = {}  # resolved run dir -> [fd, depth]
_GUARD = threading.Lock()


class RunDirError(ConfigError):
    """A run directory that cannot be (re)used as asked; the message says why and what to do."""


# --------------------------------------------------------------------------- atomic files

def _umask() -> int:
    """The process's file-creation mask, read without changing it where Linux allows."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _naming(err: OSError, path: Path) -> OSError:
    """``err`` with ``path`` as its file name (a failed ``write`` names none)."""
    return OSError(err.errno, err.strerror, str(path)) if err.errno is not None else err


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same directory and ``os.replace``.

    The file gets mode ``0o666 & ~umask``, like a plainly created one. Raises
    ``OSError`` (e.g. ``ENOSPC``, ``EACCES``) naming ``path``; no temporary file is left.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        raise _naming(err, path) from err
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), 0o666 & ~_umask())
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise _naming(err, path) from err
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Text version of :func:`atomic_write_bytes` (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def _jsonable(x: Any) -> Any:
    """Numpy scalars/arrays -> Python; NaN/inf -> None (strict JSON); floats to 12 significant digits.

    The rounding drops binary noise such as ``2.0500000000000003`` (from a grid
    built by arithmetic) and keeps far more digits than any measured value has.
    """
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float):
        return float(f"{x:.12g}") if math.isfinite(x) else None
    if isinstance(x, Path):
        return str(x)
    return x


def write_json(path: str | Path, obj: Any) -> None:
    """Atomically write ``obj`` as indented strict JSON (NaN/inf become null)."""
    atomic_write_text(path, json.dumps(_jsonable(obj), indent=2, allow_nan=False) + "\n")


# --------------------------------------------------------------------------- lock

class RunDirBusy(RunDirError):
    """Another process holds the run directory's lock; the message names its process id."""


def make_run_dir(run_dir: str | Path) -> Path:
    """Create ``run_dir`` (and its parents) or raise :class:`RunDirError` saying why it cannot be one."""
    run_dir = Path(run_dir)
    for p in (run_dir, *run_dir.parents):
        if p.exists():
            if not p.is_dir():
                what = "exists and is a file" if p == run_dir else f"has a file, {p}, as a parent"
                raise RunDirError(f"{run_dir}: {what}, not a directory; choose another --out")
            break
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


def _busy(run_dir: Path) -> RunDirBusy:
    try:
        pid = (run_dir / LOCK_FILE).read_text().strip()
    except OSError:
        pid = ""
    who, stop = (f"process {pid}", f"stop it (kill {pid})") if pid.isdigit() else ("another process", "stop it")
    return RunDirBusy(f"run directory {run_dir} is in use by {who}; wait for it to finish, {stop}, "
                      "or choose another --out")


def _acquire(run_dir: Path) -> int:
    path = run_dir / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except PermissionError as err:  # a read-only directory may still hold a lock file from an earlier run
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            raise err from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        os.close(fd)
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise _busy(run_dir) from None
        raise
    with contextlib.suppress(OSError):  # the id is only for the message; a full disk must not stop the run here
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


@contextlib.contextmanager
def hold(run_dir: str | Path) -> Iterator[Path]:
    """Hold the exclusive lock of ``run_dir`` (created if missing) for the ``with`` block.

    Raises:
      RunDirBusy: another process holds it (one line naming that process's id).
      RunDirError: ``run_dir`` or one of its parents is a file.
      OSError: the lock file cannot be created (e.g. read-only directory).
    """
    run_dir = make_run_dir(run_dir)
    key = run_dir.resolve()
    with _GUARD:
        entry = _HELD.get(key)
        if entry is None:
            entry = _HELD[key] = [_acquire(run_dir), 0]
        entry[1] += 1
    try:
        yield run_dir
    finally:
        with _GUARD:
            entry[1] -= 1
            if entry[1] == 0:
                del _HELD[key]
                os.close(entry[0])  # releases the flock
