"""Chunk files and manifest of a :func:`selfid_jax.runner.sweep.run_chunked` directory.

``DIR/manifest.json`` says what the chunks hold (rows, chunk size, float
width, hashes of the parameters and labels) and, per chunk written, its row
range and the SHA-256 of its file (``"chunks": {"3": {"rows": [15, 20],
"sha256": ...}}``); ``DIR/chunks/chunk_00003.parquet`` holds the rows of one
finished chunk (``row``, the label columns, one column per output);
``DIR/results.parquet`` is their concatenation.

Every file is written atomically, and the manifest's record of a chunk is
written before the chunk file, so a chunk file on disk always has a record. On
resume, every chunk file is checked against its record (hash, row range,
readable Parquet) before any compute; one that fails is reported on stderr
and recomputed, and assembly re-checks every chunk, so a truncated file or a
chunk copied from another run never reaches ``results.parquet``. A directory
holding chunks of another sweep, or of an older manifest format, is refused.
"""

from __future__ import annotations

import hashlib
import json
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from selfid_jax.runner.errors import RunDirError, SweepResumeError
from selfid_jax.runner.files import atomic_write_bytes, write_json
from selfid_jax.runner.fingerprint import changes as fingerprint_changes
from selfid_jax.runner.layout import CHUNKS_DIR, MANIFEST_FILE, RESULTS_FILE

__all__ = ["MANIFEST_FORMAT", "SweepResumeError", "assemble", "check_manifest", "chunk_path", "chunk_rows",
           "chunk_table", "finished_tables", "new_manifest", "params_hash", "prepare_dir", "record_chunk",
           "table_bytes", "verify"]

MANIFEST_FORMAT = 4  # 2: named pytree leaves; 3: per-chunk row range and sha256, x64; 4: fingerprint of the inputs


def chunk_path(out_dir: Path, i: int, n_chunks: int) -> Path:
    width = max(5, len(str(n_chunks - 1)))
    return out_dir / CHUNKS_DIR / f"chunk_{i:0{width}d}.parquet"


def chunk_rows(manifest: Mapping, i: int) -> tuple[int, int]:
    """``[start, stop)`` of chunk ``i``."""
    size = manifest["chunk_size"]
    return i * size, min((i + 1) * size, manifest["n_rows"])


def table_bytes(table: pa.Table) -> bytes:
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


def _output_column(arr: np.ndarray) -> pa.Array:
    if arr.ndim == 1:
        return pa.array(arr)
    flat = arr.reshape(arr.shape[0], -1)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[1])


def chunk_table(rows: np.ndarray, meta: pd.DataFrame | None, outputs: Mapping[str, np.ndarray]) -> pa.Table:
    cols: dict[str, pa.Array] = {"row": pa.array(rows.astype(np.int64))}
    if meta is not None:
        mt = pa.Table.from_pandas(meta.iloc[rows[0] : rows[-1] + 1], preserve_index=False)
        cols.update(zip(mt.column_names, mt.columns))
    for name, arr in outputs.items():
        cols[name] = _output_column(arr)
    return pa.table(cols)


# --------------------------------------------------------------------------- manifest

def params_hash(params: Mapping[str, np.ndarray], meta: pd.DataFrame | None = None) -> str:
    """SHA-256 over the names, dtypes, shapes and bytes of ``params`` (and ``meta``'s values)."""
    h = hashlib.sha256()
    for name in sorted(params):
        arr = np.ascontiguousarray(params[name])
        h.update(f"{name}|{arr.dtype.str}|{arr.shape}|".encode())
        h.update(arr.tobytes())
    if meta is not None:
        h.update(f"meta|{list(meta.columns)}|{[str(t) for t in meta.dtypes]}|".encode())
        h.update(pd.util.hash_pandas_object(meta, index=False).to_numpy().tobytes())
    return h.hexdigest()


def new_manifest(params: Mapping[str, np.ndarray], meta: pd.DataFrame | None, chunk_size: int, *, x64: bool,
                 fingerprint: Mapping | None = None) -> dict:
    """The manifest of a sweep over ``params`` (N-row arrays) in chunks of ``chunk_size`` rows, no chunk recorded.

    ``fingerprint``: what the chunks depend on beyond the params (:func:`selfid_jax.runner.fingerprint.fingerprint`:
    config, files read, package source); a resume with another one is refused.
    """
    n_rows = len(next(iter(params.values())))
    return {
        "format": MANIFEST_FORMAT,
        "x64": x64,
        "n_rows": n_rows,
        "chunk_size": chunk_size,
        "n_chunks": -(-n_rows // chunk_size),
        "params_hash": params_hash(params),
        "meta_hash": params_hash({}, meta) if meta is not None else None,
        "params": {k: {"dtype": v.dtype.str, "row_shape": list(v.shape[1:])} for k, v in params.items()},
        "meta_columns": list(meta.columns) if meta is not None else [],
        "fingerprint": dict(fingerprint or {}),
        "chunks": {},
    }


def _read_manifest(path: Path) -> dict:
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise SweepResumeError(
            f"{path}: unreadable ({err}), so the chunks beside it cannot be checked; use --fresh to discard them"
        ) from None
    if not isinstance(old, dict) or not isinstance(old.get("chunks", {}), dict):
        raise SweepResumeError(f"{path}: not a sweep manifest; use --fresh to discard the chunks beside it")
    return old


def _width(x64: bool) -> str:
    return "float64 (jax_enable_x64)" if x64 else "float32 (jax_enable_x64 off)"


def check_manifest(out_dir: Path, manifest: dict) -> dict:
    """The manifest saved in ``out_dir``, checked to describe the same sweep as ``manifest``."""
    path = out_dir / MANIFEST_FILE
    old = _read_manifest(path)
    fmt = old.get("format")
    if fmt != MANIFEST_FORMAT:
        age = "an older" if not isinstance(fmt, int) or fmt < MANIFEST_FORMAT else "a newer"
        raise SweepResumeError(
            f"{path}: made by {age} selfid_jax (manifest format {fmt}, this one reads {MANIFEST_FORMAT}); "
            "use --fresh (fresh=True) to discard its chunks, or finish the run with that version"
        )
    if old.get("x64") != manifest["x64"]:
        raise SweepResumeError(
            f"{path}: this run was made with {_width(bool(old.get('x64')))}; "
            "rerun with the same setting or --fresh (fresh=True)"
        )
    keys = ("n_rows", "chunk_size", "n_chunks", "params_hash", "meta_hash")
    diff = [f"{k} (was {old.get(k)!r}, now {manifest[k]!r})" for k in keys if old.get(k) != manifest[k]]
    if diff:
        raise SweepResumeError(
            f"{path}: the chunks in {out_dir} belong to a different sweep; differing: "
            + "; ".join(diff)
            + ". Use --fresh (fresh=True) to discard them, or choose another output directory."
        )
    changed = fingerprint_changes(old.get("fingerprint", {}), manifest.get("fingerprint", {}))
    if changed:
        raise SweepResumeError(
            f"{path}: the chunks in {out_dir} were computed from other inputs; changed since: " + "; ".join(changed)
            + ". Nothing old and new is assembled together: use --fresh (fresh=True) to recompute them, or choose "
            "another output directory."
        )
    return old


def prepare_dir(out_dir: Path, manifest: dict, fresh: bool) -> dict:
    """Writer side: clear on ``fresh``, check or write the manifest, drop stale temp files.

    Returns ``manifest`` with the chunk records of the saved one (none if new or ``fresh``).
    """
    chunk_dir = out_dir / CHUNKS_DIR
    if fresh:
        for p in (out_dir / MANIFEST_FILE, out_dir / RESULTS_FILE):
            p.unlink(missing_ok=True)
        if chunk_dir.exists():
            for p in [*chunk_dir.glob("chunk_*.parquet"), *chunk_dir.glob(".*.tmp")]:
                p.unlink()
    records: dict = {}
    if (out_dir / MANIFEST_FILE).exists():
        records = check_manifest(out_dir, manifest).get("chunks", {})
    elif chunk_dir.exists() and any(chunk_dir.glob("chunk_*.parquet")):
        raise SweepResumeError(
            f"{chunk_dir}: holds chunks but {out_dir / MANIFEST_FILE} is missing, so they cannot be "
            "checked. Use --fresh (fresh=True) to discard them."
        )
    chunk_dir.mkdir(parents=True, exist_ok=True)
    for p in [*chunk_dir.glob(".*.tmp"), *out_dir.glob(".*.tmp")]:  # left by a killed writer
        p.unlink(missing_ok=True)
    manifest = {**manifest, "chunks": dict(records)}
    write_json(out_dir / MANIFEST_FILE, manifest)
    return manifest


def record_chunk(out_dir: Path, manifest: dict, i: int, data: bytes) -> None:
    """Record chunk ``i``'s row range and the SHA-256 of ``data`` (its file's bytes) in the manifest on disk."""
    start, stop = chunk_rows(manifest, i)
    manifest["chunks"][str(i)] = {"rows": [start, stop], "sha256": hashlib.sha256(data).hexdigest()}
    write_json(out_dir / MANIFEST_FILE, manifest)


# --------------------------------------------------------------------------- verification

def _read_verified(path: Path, manifest: Mapping, i: int, columns=None) -> tuple[pa.Table | None, str | None]:
    """``(table, None)`` if chunk file ``path`` matches its record and holds the rows of chunk ``i``, else
    ``(None, why)``."""
    record = manifest.get("chunks", {}).get(str(i))
    start, stop = chunk_rows(manifest, i)
    if not isinstance(record, Mapping) or record.get("rows") != [start, stop]:
        return None, "no record of it in the manifest"
    try:
        data = path.read_bytes()
    except OSError as err:
        return None, f"unreadable: {err.strerror or err}"
    if hashlib.sha256(data).hexdigest() != record.get("sha256"):
        return None, "hash mismatch"
    try:
        table = pq.read_table(pa.BufferReader(data), columns=columns)
        got = table.column("row").to_numpy()
    except (pa.ArrowException, OSError, KeyError) as err:
        return None, f"unreadable: {err}"
    if not np.array_equal(got, np.arange(start, stop)):
        return None, f"holds rows {got[:1]}..{got[-1:]}, expected {start}..{stop - 1}"
    return table, None


def verify(out_dir: Path, manifest: Mapping) -> np.ndarray:
    """Which chunks are finished: their file exists and matches its record; a failing one is reported on stderr."""
    n_chunks = manifest["n_chunks"]
    done = np.zeros(n_chunks, bool)
    for i in range(n_chunks):
        path = chunk_path(out_dir, i, n_chunks)
        if not path.exists():
            continue
        _, problem = _read_verified(path, manifest, i, columns=["row"])
        if problem is None:
            done[i] = True
        else:
            print(f"{out_dir}: chunk {i}: corrupt ({problem}), recomputing", file=sys.stderr)
    return done


def finished_tables(out_dir: Path) -> list[pa.Table]:
    """The verified chunk tables of ``out_dir`` (an unfinished sweep's rows so far); ``[]`` if none can be checked."""
    try:
        manifest = _read_manifest(out_dir / MANIFEST_FILE)
    except SweepResumeError:
        return []
    if manifest.get("format") != MANIFEST_FORMAT:
        return []
    tables = []
    for i in range(int(manifest.get("n_chunks", 0))):
        path = chunk_path(out_dir, i, manifest["n_chunks"])
        if path.exists():
            table, _ = _read_verified(path, manifest, i)
            if table is not None:
                tables.append(table)
    return tables


def assemble(out_dir: Path, manifest: Mapping) -> pd.DataFrame:
    """Concatenate all chunk files, each re-checked against its record, and write results.parquet."""
    n_chunks = manifest["n_chunks"]
    tables = []
    for i in range(n_chunks):
        path = chunk_path(out_dir, i, n_chunks)
        table, problem = _read_verified(path, manifest, i) if path.exists() else (None, "missing")
        if problem is not None:
            raise RunDirError(f"{path}: changed during the run ({problem}); rerun the same command to recompute it")
        tables.append(table)
    table = pa.concat_tables(tables, promote_options="default")
    atomic_write_bytes(out_dir / RESULTS_FILE, table_bytes(table))
    return table.to_pandas()
