"""The files a robot model reads: an MJCF or URDF file, the files it includes, and the meshes, textures and
height fields it names, found by reading the XML (nothing is compiled).

MJCF: ``<include file=...>`` (recursively, relative to the including file's
directory), and ``file=`` of ``mesh``, ``texture``, ``hfield`` and ``skin``
assets, relative to ``<compiler meshdir/texturedir/assetdir>`` of the main
file. URDF: ``<mesh filename=...>`` (``package://`` and ``file://`` prefixes are
stripped; a path that does not exist is still listed, so its appearance changes
the fingerprint). Used to fingerprint the inputs of a run.
"""

from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET
from pathlib import Path

__all__ = ["file_sha256", "model_files"]

_ASSET_DIR = {"mesh": "meshdir", "skin": "meshdir", "texture": "texturedir", "hfield": "assetdir"}


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex); ``"missing"`` if it cannot be read."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError:
        return "missing"
    return h.hexdigest()


def model_files(path: str | Path) -> list[Path]:
    """Every file the model at ``path`` reads, ``path`` first, each once, as absolute paths."""
    path = Path(path).resolve()
    seen: list[Path] = []
    if path.suffix.lower() == ".urdf":
        seen.append(path)
        try:
            root = ET.parse(path).getroot()
        except (OSError, ET.ParseError):
            return seen
        for mesh in root.iter("mesh"):
            name = mesh.get("filename")
            if name:
                name = name.removeprefix("file://").split("package://", 1)[-1]
                p = (path.parent / name).resolve()
                if p not in seen:
                    seen.append(p)
        return seen
    dirs: dict[str, Path] = {}
    _mjcf(path, path.parent, dirs, seen)
    return seen


def _mjcf(path: Path, main_dir: Path, dirs: dict[str, Path], seen: list[Path]) -> None:
    if path in seen:
        return
    seen.append(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError):
        return
    for compiler in root.iter("compiler"):
        for key in ("meshdir", "texturedir", "assetdir"):
            if compiler.get(key) is not None:
                dirs[key] = (main_dir / compiler.get(key, "")).resolve()
    for el in root.iter():
        name = el.get("file")
        if not name:
            continue
        if el.tag == "include":
            _mjcf((path.parent / name).resolve(), main_dir, dirs, seen)
        elif el.tag in _ASSET_DIR:
            base = dirs.get(_ASSET_DIR[el.tag], dirs.get("assetdir", main_dir))
            p = (base / name).resolve()
            if p not in seen:
                seen.append(p)
