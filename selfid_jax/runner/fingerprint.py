"""Fingerprints of what a run depends on: its resolved config, the files it reads, the package's own source.

:func:`package_source` hashes every source file of the installed ``selfid_jax``
(``.py``, model assets, following the link to the experiments), so a run
resumed after a code change is refused instead of mixing rows from two
versions. :func:`changes` says, one phrase each, what differs between two
fingerprints; :func:`key_changes` is its key-by-key comparison of two
mappings, which also names the differing keys of two resolved configs
(:func:`selfid_jax.runner.rundir.create_run_dir`).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

__all__ = ["PACKAGE_ROOT", "changes", "config_sha256", "fingerprint", "key_changes", "package_source"]

PACKAGE_ROOT = Path(__file__).resolve().parents[1]
_SOURCE_SUFFIXES = (".py", ".xml", ".urdf", ".stl", ".obj", ".msh", ".png", ".yaml", ".json")


@functools.cache
def package_source() -> dict[str, Any]:
    """``{"version", "source_sha256", "files"}`` of the ``selfid_jax`` package this process imports."""
    h = hashlib.sha256()
    n = 0
    for folder, dirs, files in os.walk(PACKAGE_ROOT, followlinks=True):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__" and not d.startswith("."))
        for name in sorted(files):
            if not name.endswith(_SOURCE_SUFFIXES):
                continue
            p = Path(folder, name)
            h.update(p.relative_to(PACKAGE_ROOT).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
            n += 1
    try:
        version = importlib.metadata.version("selfid_jax")
    except importlib.metadata.PackageNotFoundError:
        version = None
    return {"version": version, "source_sha256": h.hexdigest(), "files": n}


def config_sha256(resolved: Mapping[str, Any]) -> str:
    """SHA-256 of a resolved config (plain data), independent of key order."""
    return hashlib.sha256(json.dumps(resolved, sort_keys=True, default=str).encode()).hexdigest()


def fingerprint(resolved_config: Mapping[str, Any], inputs: Mapping[str, str]) -> dict[str, Any]:
    """The fingerprint stored in a part's manifest: config hash, ``inputs`` (file -> sha256), package source."""
    return {"config_sha256": config_sha256(resolved_config), "inputs": dict(sorted(inputs.items())),
            "package": package_source()}


def _short(sha: Any) -> str:
    return str(sha)[:12]


def key_changes(
    old: Mapping[str, Any],
    new: Mapping[str, Any],
    *,
    added: Callable[[Any], str],
    removed: Callable[[Any], str],
    changed: Callable[[Any, Any], str],
) -> list[str]:
    """``"KEY (what)"`` for each key whose value differs between ``old`` and ``new``, sorted by key.

    ``what`` is ``added(new_value)`` for a key only in ``new``, ``removed(old_value)`` for one only in
    ``old``, ``changed(old_value, new_value)`` for one in both with unequal values (``!=``).
    """
    out = []
    for key in sorted(set(old) | set(new)):
        if key not in old:
            out.append(f"{key} ({added(new[key])})")
        elif key not in new:
            out.append(f"{key} ({removed(old[key])})")
        elif old[key] != new[key]:
            out.append(f"{key} ({changed(old[key], new[key])})")
    return out


def changes(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """What differs between two fingerprints, one phrase each (empty if they are equal)."""
    out: list[str] = []
    if old.get("config_sha256") != new.get("config_sha256"):
        out.append("the resolved config")
    out += key_changes(old.get("inputs", {}) or {}, new.get("inputs", {}) or {},
                       added=lambda _: "not read before", removed=lambda _: "no longer read",
                       changed=lambda a, b: f"sha256 {_short(a)} -> {_short(b)}")
    op, np_ = old.get("package", {}) or {}, new.get("package", {}) or {}
    if op.get("source_sha256") != np_.get("source_sha256") or op.get("version") != np_.get("version"):
        out.append(f"the selfid_jax source (version {op.get('version')} -> {np_.get('version')}, "
                   f"sha256 {_short(op.get('source_sha256'))} -> {_short(np_.get('source_sha256'))})")
    return out
