"""Fingerprints of what a run depends on: its resolved config, the files it reads, the package's own source.

:func:`package_source` hashes every source file of the installed ``selfid_jax``
(``.py``, model assets, following the link to the experiments), so a run
resumed after a code change is refused instead of mixing rows from two
versions. :func:`changes` says, one phrase each, what differs between two
fingerprints.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["PACKAGE_ROOT", "changes", "config_sha256", "fingerprint", "package_source"]

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


def changes(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """What differs between two fingerprints, one phrase each (empty if they are equal)."""
    out: list[str] = []
    if old.get("config_sha256") != new.get("config_sha256"):
        out.append("the resolved config")
    oi, ni = old.get("inputs", {}) or {}, new.get("inputs", {}) or {}
    for name in sorted(set(oi) | set(ni)):
        if name not in oi:
            out.append(f"{name} (not read before)")
        elif name not in ni:
            out.append(f"{name} (no longer read)")
        elif oi[name] != ni[name]:
            out.append(f"{name} (sha256 {_short(oi[name])} -> {_short(ni[name])})")
    op, np_ = old.get("package", {}) or {}, new.get("package", {}) or {}
    if op.get("source_sha256") != np_.get("source_sha256") or op.get("version") != np_.get("version"):
        out.append(f"the selfid_jax source (version {op.get('version')} -> {np_.get('version')}, "
                   f"sha256 {_short(op.get('source_sha256'))} -> {_short(np_.get('source_sha256'))})")
    return out
