"""The run-directory lock: one process at a time in a run directory, re-entrant within a process.

The lock. ``hold(RUN)`` takes ``fcntl.flock(LOCK_EX | LOCK_NB)`` on
``RUN/.lock`` and writes this process's id into it. The kernel drops the lock
when the process exits, however it exits (``kill -9`` included), so a stale
``.lock`` file never blocks a later run; the file itself stays (removing it
would let two processes lock two different files of the same name). A second
process asking for the lock is refused at once with :class:`RunDirBusy`.
The lock is re-entrant within a process: a process-level registry counts the
holds, so ``selfid-jax sweep`` holding ``RUN`` does not block its own
:func:`selfid_jax.runner.sweep.run_chunked` into ``RUN/parts/<name>``, which locks
``RUN`` too. Threads of one process share the hold. ``flock`` is advisory and
local to one machine: on NFS a process on another host may not see it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import threading
from collections.abc import Iterator
from pathlib import Path

from selfid_jax.runner.errors import RunDirBusy, RunDirError
from selfid_jax.runner.layout import LOCK_FILE

__all__ = ["LOCK_FILE", "RunDirBusy", "RunDirError", "check_free", "hold", "is_held", "make_run_dir"]

_HELD: dict[Path, list[int]] = {}  # resolved run dir -> [fd, depth]
_GUARD = threading.Lock()


def is_held(run_dir: str | Path) -> bool:
    """Whether this process holds the lock of ``run_dir`` (inside a :func:`hold` block)."""
    with _GUARD:
        return Path(run_dir).resolve() in _HELD


def check_run_dir(run_dir: str | Path) -> Path:
    """``Path(run_dir)`` if it is a directory or can be made one; else :class:`RunDirError` saying why (a file in
    the way, a nearest existing folder that cannot be written). Creates nothing."""
    run_dir = Path(run_dir)
    for p in (run_dir, *run_dir.parents):
        if p.exists():
            if not p.is_dir():
                what = "exists and is a file" if p == run_dir else f"has a file, {p}, as a parent"
                raise RunDirError(f"{run_dir}: {what}, not a directory; choose another --out")
            if not os.access(p, os.W_OK | os.X_OK):
                raise RunDirError(f"{p}: not writable; make it writable, or choose another --out")
            break
        if p.is_symlink():
            raise RunDirError(f"{p}: a dangling symbolic link in the way of {run_dir}; remove it or choose another "
                              "--out")
    return run_dir


def check_free(run_dir: str | Path) -> None:
    """Raise :class:`RunDirBusy` at once if another process holds the lock of ``run_dir``; nothing otherwise.

    For the command line, before it builds an experiment (a start search can take a minute): a busy directory
    is refused before any compute. It creates and writes nothing (no lock file where there is none) and
    holds nothing; :func:`hold` still decides, since another process may take the lock after this check.
    """
    run_dir = Path(run_dir)
    path = run_dir / LOCK_FILE
    if not path.is_file() or is_held(run_dir):
        return
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return  # unreadable: hold() will say why
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise _busy(run_dir) from None
    finally:
        os.close(fd)  # drops the probe's own lock, if it got it


def make_run_dir(run_dir: str | Path) -> Path:
    """Create ``run_dir`` (and its parents) or raise :class:`RunDirError` saying why it cannot be one."""
    run_dir = check_run_dir(run_dir)
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
