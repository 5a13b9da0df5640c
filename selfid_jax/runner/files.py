"""Whole files only: atomic writes (temporary file, fsync, rename) and strict JSON (:mod:`selfid_jax.strict_json`).

:func:`atomic_write_bytes` writes a temporary file in the same directory,
fsyncs it and renames it over the target, so a kill or a full disk never
leaves a half-written file under its final name (nor a temporary one), and
gives it the permissions the user's umask gives a new file.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from selfid_jax.strict_json import jsonable

__all__ = ["atomic_write_bytes", "atomic_write_text", "write_json"]


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


def write_json(path: str | Path, obj: Any) -> None:
    """Atomically write ``obj`` as indented strict JSON (:func:`selfid_jax.strict_json.jsonable`: NaN/inf become null,
    floats exact)."""
    atomic_write_text(path, json.dumps(jsonable(obj), indent=2, allow_nan=False) + "\n")
