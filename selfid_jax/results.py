"""Run directories: resolved config, versions, results table, summary, figures.

Layout of a run directory ``RUN``::

    RUN/config.yaml       resolved config (every default filled in)
    RUN/versions.json     package versions, git revision, devices, command
    RUN/parts/<part>/     per compiled part of an experiment (e.g. per system):
                          manifest.json (what its chunks hold) and chunks/, one
                          Parquet file per finished chunk (sweep.run_chunked)
    RUN/results.parquet   tidy table, one row per batch element (rollout)
    RUN/summary.json      per-system summaries (e.g. valid-region bounds)
    RUN/figures/          PNG and PDF figures, redrawn by ``selfid-jax plot RUN``

Files are written atomically (temporary file + ``os.replace``), so a killed run
never leaves a half-written file under its final name.
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from selfid_jax.config import ConfigError, dump_config, flatten_dict, yaml_load

__all__ = [
    "RESULTS_FILE",
    "write_results",
    "SUMMARY_FILE",
    "RunDirError",
    "atomic_write_bytes",
    "atomic_write_text",
    "clear_run_dir",
    "collect_versions",
    "create_run_dir",
    "load_results",
    "read_run_config",
    "read_summary",
    "write_summary",
]

CONFIG_FILE = "config.yaml"
VERSIONS_FILE = "versions.json"
MANIFEST_FILE = "manifest.json"
CHUNKS_DIR = "chunks"
PARTS_DIR = "parts"
RESULTS_FILE = "results.parquet"
SUMMARY_FILE = "summary.json"
FIGURES_DIR = "figures"

# Everything create_run_dir/run_chunked may write; --fresh removes exactly these.
_OWNED = (CONFIG_FILE, VERSIONS_FILE, MANIFEST_FILE, CHUNKS_DIR, PARTS_DIR, RESULTS_FILE, SUMMARY_FILE, FIGURES_DIR)


class RunDirError(ConfigError):
    """A run directory that cannot be (re)used as asked; the message says why and what to do."""


# --------------------------------------------------------------------------- atomic files

def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same directory and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Text version of :func:`atomic_write_bytes` (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def _jsonable(x: Any) -> Any:
    """Numpy scalars/arrays -> Python; NaN/inf -> None (strict JSON)."""
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def write_json(path: str | Path, obj: Any) -> None:
    """Atomically write ``obj`` as indented strict JSON (NaN/inf become null)."""
    atomic_write_text(path, json.dumps(_jsonable(obj), indent=2, allow_nan=False) + "\n")


# --------------------------------------------------------------------------- versions

def _pkg_version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def _git(*args: str, cwd: str | Path | None = None) -> str | None:
    try:
        res = subprocess.run(
            ["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return res.stdout.strip() if res.returncode == 0 else None


def collect_versions(cwd: str | Path | None = None) -> dict[str, Any]:
    """Package versions, git revision of ``cwd`` (None outside a repo or before a commit) and devices."""
    import jax  # local: keep `selfid_jax.results` cheap to import for plotting

    rev = _git("rev-parse", "HEAD", cwd=cwd)
    dirty = None
    if rev is not None:
        status = _git("status", "--porcelain", "--untracked-files=no", cwd=cwd)
        dirty = bool(status) if status is not None else None
    return {
        "selfid_jax": _pkg_version("selfid_jax"),
        "jax": jax.__version__,
        "jaxlib": _pkg_version("jaxlib"),
        "mujoco": _pkg_version("mujoco"),
        "mujoco_mjx": _pkg_version("mujoco-mjx"),
        "numpy": np.__version__,
        "python": platform.python_version(),
        "git_revision": rev,
        "git_dirty": dirty,
        "jax_backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "process_count": jax.process_count(),
        "x64": bool(jax.config.jax_enable_x64),
    }


# --------------------------------------------------------------------------- run dir

def read_run_config(run_dir: str | Path) -> dict:
    """The resolved config saved in ``run_dir/config.yaml`` as a plain dict."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise RunDirError(f"{path}: not found; is {run_dir} a run directory?")
    data = yaml_load(path.read_text())
    if not isinstance(data, dict):
        raise RunDirError(f"{path}: expected a mapping")
    return data


def clear_run_dir(run_dir: str | Path) -> None:
    """Remove everything a run writes in ``run_dir`` (and nothing else)."""
    run_dir = Path(run_dir)
    for name in _OWNED:
        p = run_dir / name
        if p.is_dir():
            shutil.rmtree(p)
        else:
            p.unlink(missing_ok=True)


def _diff_keys(old: Mapping, new: Mapping) -> list[str]:
    a, b = flatten_dict(old), flatten_dict(new)
    out = []
    for k in sorted(set(a) | set(b)):
        if k not in a:
            out.append(f"{k} (new: {b[k]!r})")
        elif k not in b:
            out.append(f"{k} (was {a[k]!r}, now absent)")
        elif a[k] != b[k]:
            out.append(f"{k} (was {a[k]!r}, now {b[k]!r})")
    return out


def create_run_dir(
    out: str | Path,
    cfg: Any,
    config_path: str | Path | None = None,
    *,
    overrides: Sequence[str] = (),
    fresh: bool = False,
) -> Path:
    """Create (or reopen for resuming) the run directory ``out`` for config ``cfg``.

    Writes ``config.yaml`` (the resolved config, from :func:`dump_config`) and
    ``versions.json`` (:func:`collect_versions`, plus the source config path,
    the overrides, the command line and a UTC timestamp).

    Reopening a directory whose ``config.yaml`` equals the resolved config keeps
    its results (so a sweep can resume); the versions of each resumption are
    appended to ``versions.json["resumed"]``. A directory holding a different
    config raises :class:`RunDirError` naming the differing keys, unless
    ``fresh``, which first removes everything a run writes there.

    Under ``jax.distributed`` only process 0 touches the directory.

    Returns:
      ``Path(out)``.
    """
    import jax

    run_dir = Path(out)
    if jax.process_index() != 0:
        return run_dir
    resolved = dump_config(cfg) if not isinstance(cfg, Mapping) else dict(cfg)
    cfg_file = run_dir / CONFIG_FILE
    if fresh:
        clear_run_dir(run_dir)
    elif cfg_file.exists():
        old = read_run_config(run_dir)
        diff = _diff_keys(old, resolved)
        if diff:
            raise RunDirError(
                f"{run_dir}: holds results of a different config; differing keys: "
                + "; ".join(diff)
                + ". Use --fresh (fresh=True) to discard them, or choose another --out."
            )
    elif any((run_dir / d).exists() for d in (CHUNKS_DIR, PARTS_DIR, RESULTS_FILE)):
        raise RunDirError(
            f"{run_dir}: holds results but no {CONFIG_FILE}; use --fresh to discard them or another --out."
        )
    run_dir.mkdir(parents=True, exist_ok=True)

    info = collect_versions()
    info.update(
        config_source=str(Path(config_path).resolve()) if config_path is not None else None,
        overrides=list(overrides),
        command=list(sys.argv),
        created_utc=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    )
    vfile = run_dir / VERSIONS_FILE
    if cfg_file.exists() and vfile.exists():
        first = json.loads(vfile.read_text())
        first.setdefault("resumed", []).append(info)
        write_json(vfile, first)
    else:
        atomic_write_text(cfg_file, yaml.safe_dump(resolved, sort_keys=False))
        write_json(vfile, info)
    return run_dir


# --------------------------------------------------------------------------- tables

def load_results(run_dir: str | Path, *, partial: bool = False) -> pd.DataFrame:
    """The tidy results table of a run, one row per batch element, sorted by ``row``.

    With ``partial=True`` an unfinished run (no ``results.parquet`` yet) returns
    the rows of its finished chunks (one row per batch element, before any
    experiment's ``tabulate``) instead of raising.

    Raises:
      FileNotFoundError: no results (naming the file looked for).
    """
    run_dir = Path(run_dir)
    path = run_dir / RESULTS_FILE
    if path.is_file():
        return pd.read_parquet(path)
    chunks = sorted((run_dir / CHUNKS_DIR).glob("chunk_*.parquet"))
    chunks += sorted((run_dir / PARTS_DIR).glob(f"*/{CHUNKS_DIR}/chunk_*.parquet"))
    if partial and chunks:
        df = pd.concat([pd.read_parquet(c) for c in chunks], ignore_index=True)
        return df.sort_values("row", kind="stable").reset_index(drop=True)
    hint = f" ({len(chunks)} finished chunks; the sweep is unfinished, re-run it to resume)" if chunks else ""
    raise FileNotFoundError(f"{path}: no results table{hint}")


def write_results(run_dir: str | Path, df: pd.DataFrame) -> Path:
    """Write the tidy results table ``run_dir/results.parquet`` atomically (process 0 only under jax.distributed)."""
    import io

    import jax

    path = Path(run_dir) / RESULTS_FILE
    if jax.process_index() == 0:
        buf = io.BytesIO()
        df.to_parquet(buf, index=False)
        atomic_write_bytes(path, buf.getvalue())
    return path


def write_summary(run_dir: str | Path, summary: Mapping[str, Any]) -> Path:
    """Atomically write ``summary`` to ``run_dir/summary.json`` (NaN -> null); returns the path."""
    path = Path(run_dir) / SUMMARY_FILE
    write_json(path, summary)
    return path


def read_summary(run_dir: str | Path, *, missing_ok: bool = False) -> dict[str, Any]:
    """``run_dir/summary.json`` as a dict (``{}`` if absent and ``missing_ok``)."""
    path = Path(run_dir) / SUMMARY_FILE
    if not path.is_file():
        if missing_ok:
            return {}
        raise FileNotFoundError(f"{path}: no summary")
    return json.loads(path.read_text())
