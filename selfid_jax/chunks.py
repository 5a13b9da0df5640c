"""Chunk files and manifest of a :func:`selfid_jax.sweep.run_chunked` directory.

``DIR/manifest.json`` says what the chunks hold (rows, chunk size, hashes of
the parameters and labels); ``DIR/chunks/chunk_00012.parquet`` holds the rows
of one finished chunk (``row``, the label columns, one column per output);
``DIR/results.parquet`` is their concatenation. Every file is written
atomically, and a directory holding chunks of another sweep is refused.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from selfid_jax.results import CHUNKS_DIR, MANIFEST_FILE, RESULTS_FILE, RunDirError, atomic_write_bytes, write_json

__all__ = ["MANIFEST_FORMAT", "SweepResumeError", "assemble", "check_manifest", "chunk_path", "chunk_table",
           "prepare_dir", "table_bytes"]

MANIFEST_FORMAT = 2  # 2: params and outputs are named pytree leaves


class SweepResumeError(RunDirError):
    """``out_dir`` holds chunks of a different sweep; the message names what differs."""


def chunk_path(out_dir: Path, i: int, n_chunks: int) -> Path:
    width = max(5, len(str(n_chunks - 1)))
    return out_dir / CHUNKS_DIR / f"chunk_{i:0{width}d}.parquet"



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



def check_manifest(out_dir: Path, manifest: dict) -> None:
    path = out_dir / MANIFEST_FILE
    old = json.loads(path.read_text())
    keys = ("format", "n_rows", "chunk_size", "n_chunks", "params_hash", "meta_hash")
    diff = [f"{k} (was {old.get(k)!r}, now {manifest[k]!r})" for k in keys if old.get(k) != manifest[k]]
    if diff:
        raise SweepResumeError(
            f"{path}: the chunks in {out_dir} belong to a different sweep; differing: "
            + "; ".join(diff)
            + ". Use --fresh (fresh=True) to discard them, or choose another output directory."
        )



def prepare_dir(out_dir: Path, manifest: dict, fresh: bool) -> None:
    """Writer side: clear on ``fresh``, verify or write the manifest, drop stale temp files."""
    chunk_dir = out_dir / CHUNKS_DIR
    if fresh:
        for p in (out_dir / MANIFEST_FILE, out_dir / RESULTS_FILE):
            p.unlink(missing_ok=True)
        if chunk_dir.exists():
            for p in [*chunk_dir.glob("chunk_*.parquet"), *chunk_dir.glob(".*.tmp")]:
                p.unlink()
    if (out_dir / MANIFEST_FILE).exists():
        check_manifest(out_dir, manifest)
    elif chunk_dir.exists() and any(chunk_dir.glob("chunk_*.parquet")):
        raise SweepResumeError(
            f"{chunk_dir}: holds chunks but {out_dir / MANIFEST_FILE} is missing, so they cannot be "
            "checked. Use --fresh (fresh=True) to discard them."
        )
    chunk_dir.mkdir(parents=True, exist_ok=True)
    for p in chunk_dir.glob(".*.tmp"):  # left by a killed writer
        p.unlink(missing_ok=True)
    write_json(out_dir / MANIFEST_FILE, manifest)



def assemble(out_dir: Path, n_rows: int, n_chunks: int, rows_per_chunk: int) -> pd.DataFrame:
    """Concatenate all chunk files, check every row appears once, write results.parquet."""
    tables = []
    for i in range(n_chunks):
        path = chunk_path(out_dir, i, n_chunks)
        t = pq.read_table(path)
        expect = np.arange(i * rows_per_chunk, min((i + 1) * rows_per_chunk, n_rows))
        got = t.column("row").to_numpy()
        if not np.array_equal(got, expect):
            raise SweepResumeError(f"{path}: holds rows {got[:3]}... not {expect[:3]}...; use --fresh")
        tables.append(t)
    table = pa.concat_tables(tables, promote_options="default")
    atomic_write_bytes(out_dir / RESULTS_FILE, table_bytes(table))
    return table.to_pandas()
