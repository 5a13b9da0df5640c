"""Run directories: create or resume one, record versions, read and write its table and summary.

The layout is :mod:`selfid_jax.runner.layout`'s.
Files are written atomically (temporary file + ``os.replace``), so a killed run
never leaves a half-written file under its final name, with the permissions
the user's umask gives. ``RUN/.lock`` is the lock of a running sweep
(:mod:`selfid_jax.runner.lock`). A file that cannot be read raises
:class:`RunDirError` naming it and the command that rebuilds it; an ``OSError``
while writing names the file it was writing.
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import json
import platform
import shlex
import shutil
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import yaml

from selfid_jax.runner.config import dump_config, flatten_dict, yaml_load
from selfid_jax.runner.errors import RunDirError
from selfid_jax.runner.files import atomic_write_bytes, atomic_write_text, write_json
from selfid_jax.runner.fingerprint import PACKAGE_ROOT, key_changes, package_source
from selfid_jax.runner.layout import (
    CHUNKS_DIR,
    CONFIG_FILE,
    OWNED,
    PARTS_DIR,
    RESULTS_FILE,
    SUMMARY_FILE,
    VERSIONS_FILE,
)
from selfid_jax.runner.lock import is_held
from selfid_jax.runner.manifest import finished_tables
from selfid_jax.strict_json import jsonable

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
    "record_refused",
    "write_summary",
]



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
    """Package versions, the package's own revision and source hash, and devices.

    ``git_revision`` is the commit of the repository that holds the imported
    ``selfid_jax`` source (None for an installed wheel, outside a repository or
    before a commit), ``git_dirty`` whether the package's files differ from it,
    ``source_sha256`` the hash of the source actually imported
    (:func:`selfid_jax.runner.fingerprint.package_source`). ``cwd`` is unused (kept for callers).
    """
    import jax  # local: keep `selfid_jax.runner.rundir` cheap to import for plotting

    del cwd
    root = PACKAGE_ROOT
    tracked = _git("ls-files", "--error-unmatch", "__init__.py", cwd=root)  # the package is in this repository
    rev = _git("rev-parse", "HEAD", cwd=root) if tracked else None
    dirty = None
    if rev is not None:
        status = _git("status", "--porcelain", "--untracked-files=no", "--", ".", cwd=root)
        dirty = bool(status) if status is not None else None
    source = package_source()
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
        "source_sha256": source["source_sha256"],
        "package_root": str(root),
        "jax_backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "process_count": jax.process_count(),
        "x64": bool(jax.config.jax_enable_x64),  # type: ignore[attr-defined]
    }


# --------------------------------------------------------------------------- run dir

def _one_line(err: BaseException, limit: int = 200) -> str:
    text = " ".join(str(err).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _rerun(run_dir: Path, *extra: str) -> str:
    """The quoted ``selfid-jax sweep`` command that (re)builds ``run_dir``, from its versions.json if readable."""
    try:
        info = json.loads((run_dir / VERSIONS_FILE).read_text())
        config, overrides = str(info["config_source"]), [str(o) for o in info.get("overrides", [])]
    except (OSError, ValueError, TypeError, KeyError):
        config, overrides = "CONFIG", []
    args = ["selfid-jax", "sweep", config, *(a for o in overrides for a in ("--set", o)), "--out", str(run_dir)]
    return "'" + " ".join([*map(shlex.quote, args), *extra]) + "'"


def _unreadable(path: Path, err: BaseException, what_to_do: str) -> RunDirError:
    return RunDirError(f"{path}: unreadable ({_one_line(err)}); {what_to_do}")


def read_run_config(run_dir: str | Path) -> dict:
    """The resolved config saved in ``run_dir/config.yaml`` as a plain dict."""
    run_dir = Path(run_dir)
    path = run_dir / CONFIG_FILE
    if not path.is_file():
        raise RunDirError(f"{path}: not found; is {run_dir} a run directory?")
    try:
        data = yaml_load(path.read_text())
    except (yaml.YAMLError, ValueError) as err:
        raise _unreadable(path, err, f"restore it, or start over with {_rerun(run_dir, '--fresh')}") from None
    if not isinstance(data, dict):
        raise _unreadable(path, TypeError("not a mapping"),
                          f"restore it, or start over with {_rerun(run_dir, '--fresh')}")
    return data


def clear_run_dir(run_dir: str | Path) -> None:
    """Remove everything a run writes in ``run_dir`` (and nothing else)."""
    run_dir = Path(run_dir)
    for name in OWNED:
        p = run_dir / name
        if p.is_dir():
            shutil.rmtree(p)
        else:
            p.unlink(missing_ok=True)


def _diff_keys(old: Mapping, new: Mapping) -> list[str]:
    """The differing keys of two resolved configs, dotted (``a.b``), each with its old and new value."""
    return key_changes(flatten_dict(old), flatten_dict(new), added=lambda v: f"new: {v!r}",
                       removed=lambda v: f"was {v!r}, now absent", changed=lambda a, b: f"was {a!r}, now {b!r}")


def _attempt(config_path, overrides) -> dict[str, Any]:
    info = collect_versions()
    info.update(
        config_source=str(Path(config_path).resolve()) if config_path is not None else None,
        overrides=list(overrides),
        command=list(sys.argv),
        created_utc=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    )
    return jsonable(info)


_ATTEMPTS: dict[Path, dict] = {}  # resolved run dir -> this process's latest entry in its versions.json


def _read_versions(vfile: Path) -> dict:
    try:
        data = json.loads(vfile.read_text())
    except (OSError, ValueError) as err:
        raise _unreadable(vfile, err, "restore it or delete it (the run's history is lost), or use --fresh") from None
    if not isinstance(data, dict):
        raise _unreadable(vfile, TypeError("not a mapping"), "restore it or delete it, or use --fresh")
    return data


def record_refused(run_dir: str | Path, reason: str, *, config_path=None, overrides: Sequence[str] = ()) -> None:
    """Append a refused resumption (versions, command, ``reason``) to ``run_dir/versions.json["refused"]``.

    If this process recorded the attempt as resumed (:func:`create_run_dir`),
    that entry moves to ``refused``. Nothing else in ``run_dir`` changes; an
    unreadable or unwritable versions.json is left as it is.
    """
    run_dir = Path(run_dir)
    vfile = run_dir / VERSIONS_FILE
    try:
        data = _read_versions(vfile) if vfile.exists() else {}
        mine = _ATTEMPTS.pop(run_dir.resolve(), None)
        resumed = data.get("resumed")
        if mine is not None and isinstance(resumed, list) and resumed and resumed[-1] == mine:
            entry = resumed.pop()
            if not resumed:
                del data["resumed"]
        else:
            entry = _attempt(config_path, overrides)
        data.setdefault("refused", []).append({**entry, "reason": reason})
        write_json(vfile, data)
    except (RunDirError, OSError):
        pass


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
    the overrides, the command line and a UTC timestamp). The caller holds the
    directory's lock (:func:`selfid_jax.runner.lock.hold`; :func:`selfid_jax.runner.execute.run`
    takes it once per run) before anything is deleted or written.

    Reopening a directory whose ``config.yaml`` equals the resolved config keeps
    its results (so a sweep can resume); the versions of each resumption are
    appended to ``versions.json["resumed"]``. A directory holding a different
    config raises :class:`RunDirError` naming the differing keys (the attempt
    is appended to ``versions.json["refused"]``), unless ``fresh``, which first
    removes everything a run writes there.

    Under ``jax.distributed`` only process 0 touches the directory.

    Returns:
      ``Path(out)``.

    Raises:
      RunDirBusy: another process holds the directory.
      RunDirError: a different config, unreadable files, or ``out`` is not a directory.
    """
    import jax

    run_dir = Path(out)
    if jax.process_index() != 0:
        return run_dir
    resolved = dump_config(cfg) if not isinstance(cfg, Mapping) else dict(cfg)
    cfg_file = run_dir / CONFIG_FILE
    if not is_held(run_dir):
        raise RuntimeError(f"create_run_dir({run_dir}): hold the run directory's lock first "
                           "(selfid_jax.runner.lock.hold)")
    if fresh:
        clear_run_dir(run_dir)
    elif cfg_file.exists():
        diff = _diff_keys(read_run_config(run_dir), resolved)
        if diff:
            msg = (f"{run_dir}: holds results of a different config; differing keys: " + "; ".join(diff)
                   + ". Use --fresh (fresh=True) to discard them, or choose another --out.")
            record_refused(run_dir, msg, config_path=config_path, overrides=overrides)
            raise RunDirError(msg)
    elif any((run_dir / d).exists() for d in (CHUNKS_DIR, PARTS_DIR, RESULTS_FILE)):
        raise RunDirError(
            f"{run_dir}: holds results but no {CONFIG_FILE}; use --fresh to discard them or another --out."
        )

    info = _attempt(config_path, overrides)
    vfile = run_dir / VERSIONS_FILE
    if cfg_file.exists() and vfile.exists():
        first = _read_versions(vfile)
        first.setdefault("resumed", []).append(info)
        write_json(vfile, first)
    else:
        atomic_write_text(cfg_file, yaml.safe_dump(resolved, sort_keys=False))
        write_json(vfile, info)
    _ATTEMPTS[run_dir.resolve()] = info
    return run_dir


# --------------------------------------------------------------------------- tables

def load_results(run_dir: str | Path, *, partial: bool = False) -> pd.DataFrame:
    """The tidy results table of a run, one row per batch element, sorted by ``row``.

    With ``partial=True`` an unfinished run (no ``results.parquet`` yet) returns
    the rows of its finished chunks (one row per batch element, before any
    experiment's ``tabulate``; only chunks that match their manifest record)
    instead of raising.

    Raises:
      FileNotFoundError: no results (naming the file looked for).
      RunDirError: ``results.parquet`` is unreadable (naming the command that rebuilds it).
    """

    run_dir = Path(run_dir)
    path = run_dir / RESULTS_FILE
    if path.is_file():
        try:
            return pd.read_parquet(path)
        except (pa.ArrowException, OSError, ValueError) as err:
            raise _unreadable(path, err, f"rerun {_rerun(run_dir)} to rebuild it") from None
    chunks = sorted((run_dir / CHUNKS_DIR).glob("chunk_*.parquet"))
    chunks += sorted((run_dir / PARTS_DIR).glob(f"*/{CHUNKS_DIR}/chunk_*.parquet"))
    tables = [t for d in [run_dir, *sorted((run_dir / PARTS_DIR).glob("*/"))] for t in finished_tables(d)]
    if partial and tables:
        df = pd.concat([t.to_pandas() for t in tables], ignore_index=True)
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
    try:
        data = json.loads(path.read_text())
    except ValueError as err:
        raise _unreadable(path, err, f"rerun {_rerun(Path(run_dir))} to rebuild it") from None
    if not isinstance(data, dict):
        raise _unreadable(path, TypeError("not a JSON object"), f"rerun {_rerun(Path(run_dir))} to rebuild it")
    return data
