"""Chunked, sharded, resumable execution of one batched computation over a grid.

The runner knows nothing of any experiment: it takes a pure batched function
``compute_fn(params_chunk) -> outputs`` over pytrees (``NamedTuple``s or dicts
of arrays) and ``N`` parameter rows (:func:`selfid_jax.runner.contract.run` feeds it
each part of an experiment). :func:`run_chunked` cuts the table into
chunks of ``chunk_size`` rows, runs every chunk through ONE compiled function
whose batch axis is sharded over the devices, writes each finished chunk to
``out_dir/chunks/chunk_00012.parquet`` atomically, and finally writes the tidy
``out_dir/results.parquet`` (one row per batch element). Re-running the same
call skips the chunk files that match their record in the manifest (row
range, SHA-256; :mod:`selfid_jax.runner.manifest`) and recomputes the others, so an
interrupted sweep (Ctrl-C, kill, lost machine) resumes without recomputing,
losing or duplicating rows, and a damaged chunk file is recomputed, never used.

One process at a time
    The writing process holds the lock of the run directory (``out_dir``, or
    ``RUN`` for ``out_dir = RUN/parts/<name>``: :mod:`selfid_jax.runner.lock`) from
    before it deletes or writes anything until the results are written; a
    second process is refused with :class:`~selfid_jax.runner.lock.RunDirBusy`.

Devices and chunk size
    The compiled batch is ``chunk_size`` rounded up to a multiple of the number
    of devices; the extra rows are padding (copies of a real row) that are
    dropped. Chunk boundaries therefore depend only on ``chunk_size`` and
    ``N``, never on the device count, so a sweep started on one device can be
    resumed on two with the same results. Pick ``chunk_size`` a multiple of
    the device count to waste nothing.

One compilation per program
    Compiled programs are kept in memory, keyed by the lowered program's text and the devices (and
    its host callbacks, which the text does not show): a repeated sweep and :func:`compute_rows` reuse them.

Several hosts (``jax.distributed``)
    Start the same command on every host (``selfid-jax sweep CONFIG --distributed`` or ``--coordinator
    host0:1234 --num-processes P --process-id i``), which calls
    ``jax.distributed.initialize(coordinator_address="host0:1234",
    num_processes=P, process_id=i)`` before any JAX computation (on GPU
    clusters with SLURM/Open MPI the arguments may be omitted). Then
    ``jax.devices()`` lists the devices of all hosts and :func:`run_chunked`
    shards each chunk over all of them: every process builds the same
    parameter table from the config, feeds the rows of its own devices, and
    the outputs are gathered (replicated) to every process. Only process 0
    writes files, so ``out_dir`` need only exist on host 0; process 0 also
    decides which chunks are already done and broadcasts that, so resuming
    works whether or not the directory is shared. Processes other than 0
    return the table if they can read ``out_dir/results.parquet`` (shared
    filesystem), else ``None``. On CPU, cross-process collectives need
    ``jax.config.update("jax_cpu_collectives_implementation", "gloo")`` (the
    CLI sets it). Checked on one machine with two CPU processes: the table
    equals the single-process one, and a re-run resumes.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pandas as pd
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from tqdm.auto import tqdm

from selfid_jax.runner import lock
from selfid_jax.runner import manifest as chunks
from selfid_jax.runner.errors import SweepResumeError
from selfid_jax.runner.files import atomic_write_bytes
from selfid_jax.runner.grids import grid_table, row_keys
from selfid_jax.runner.layout import CHUNKS_DIR, PARTS_DIR, RESULTS_FILE
from selfid_jax.runner.limits import check_memory, check_rows
from selfid_jax.runner.manifest import params_hash
from selfid_jax.runner.signals import phase

__all__ = [
    "SweepInterrupted",
    "SweepResumeError",
    "clear_stop",
    "compiled_batch",
    "compute_rows",
    "grid_table",
    "named_leaves",
    "params_hash",
    "request_stop",
    "stop_requested",
    "row_keys",
    "run_chunked",
]

BATCH_AXIS = "batch"


class SweepInterrupted(KeyboardInterrupt):
    """:func:`run_chunked` stopped early after :func:`request_stop`; re-run to resume."""


_STOP = threading.Event()


def request_stop() -> None:
    """Ask a running :func:`run_chunked` to stop after saving the chunk in flight.

    Safe to call from a signal handler (the CLI does so on SIGTERM); the run
    raises :class:`SweepInterrupted`. Call :func:`clear_stop` before the next run.
    Ignored when several processes run one sweep (they must stay in lockstep).
    """
    _STOP.set()


def stop_requested() -> bool:
    """Whether :func:`request_stop` was called since the last :func:`clear_stop`."""
    return _STOP.is_set()


def clear_stop() -> None:
    """Forget an earlier :func:`request_stop`."""
    _STOP.clear()


# --------------------------------------------------------------------------- pytrees

def _key_name(k) -> str:
    for attr in ("name", "key", "idx"):
        if hasattr(k, attr):
            return str(getattr(k, attr))
    return str(k)


def named_leaves(tree) -> tuple[dict[str, Any], Any]:
    """``({dotted name: leaf}, treedef)`` of a pytree: ``Params(q0=.., controller=ControllerParams(tol=..))``
    gives ``q0``, ``controller.tol``; ``None`` fields have no leaf. Rebuild with ``jax.tree.unflatten``."""
    flat, treedef = jax.tree_util.tree_flatten_with_path(tree)
    names = [".".join(_key_name(k) for k in path) for path, _ in flat]
    if any(not n for n in names) or len(set(names)) != len(names):
        raise ValueError(f"params/outputs must be a NamedTuple or dict of named arrays, got leaves named {names}")
    return dict(zip(names, (leaf for _, leaf in flat))), treedef


# --------------------------------------------------------------------------- grid helpers

# --------------------------------------------------------------------------- files

def _write_chunk(path: Path, data: bytes) -> None:
    """Atomically write one finished chunk's file bytes (module-level so tests can interrupt here)."""
    atomic_write_bytes(path, data)


# --------------------------------------------------------------------------- main loop

def _run_root(out_dir: Path) -> Path:
    """The run directory whose lock guards ``out_dir``: ``RUN`` for ``RUN/parts/<name>``, else ``out_dir``."""
    return out_dir.parent.parent if out_dir.parent.name == PARTS_DIR else out_dir


def _canonical(name: str, v: Any, n_rows: int | None) -> np.ndarray:
    arr = np.asarray(v)
    if arr.ndim == 0:
        raise ValueError(f"params[{name!r}] must have a leading row axis, got a scalar")
    if n_rows is not None and arr.shape[0] != n_rows:
        raise ValueError(f"params[{name!r}] has {arr.shape[0]} rows, expected {n_rows} (all params share axis 0)")
    return np.ascontiguousarray(arr, dtype=jax.dtypes.canonicalize_dtype(arr.dtype))


def _sync_done(done: np.ndarray, error: bool) -> tuple[np.ndarray, bool]:
    """Process 0's view of finished chunks and errors, broadcast to every process."""
    if jax.process_count() == 1:
        return done, error
    from jax.experimental import multihost_utils

    msg = np.concatenate([[int(error)], done.astype(np.int32)]).astype(np.int32)
    msg = np.asarray(multihost_utils.broadcast_one_to_all(msg))
    return msg[1:].astype(bool), bool(msg[0])


def run_chunked(
    compute_fn: Callable[[Any], Any],
    params: Any,
    *,
    chunk_size: int,
    out_dir: str | Path,
    meta: pd.DataFrame | None = None,
    fresh: bool = False,
    progress: bool = True,
    static_shapes: bool = True,
    devices: Sequence[jax.Device] | None = None,
    desc: str = "sweep",
    fingerprint: Mapping[str, Any] | None = None,
    position: int | None = None,
    execution_lock: contextlib.AbstractContextManager | None = None,
) -> pd.DataFrame:
    """Run ``compute_fn`` over ``N`` parameter rows in resumable, sharded chunks.

    Args:
      compute_fn: pure JAX function ``params_chunk -> outputs``. It receives
        ``params``' pytree with each array of shape ``(B, *row_shape)``
        (``B`` = the compiled batch, see module docstring) and returns a
        pytree (``NamedTuple`` or dict) of arrays with leading axis ``B``;
        each leaf becomes a column named by its dotted path
        (:func:`named_leaves`): shape ``(B,)`` a scalar column, ``(B, *s)`` a
        list column of the flattened ``s`` values. Rows must not interact
        (padding rows are copies). It is compiled once (twice with
        ``static_shapes=False``).
      params: a pytree (``NamedTuple`` or dict) of arrays with a shared
        leading axis of ``N`` rows (numbers a sweep varies, PRNG key data from
        :func:`row_keys`, ...). Dtypes are canonicalised (float64 -> float32
        unless x64 is enabled).
      chunk_size: rows per chunk (capped at ``N``); bounds device memory.
      out_dir: run directory; chunks go to ``out_dir/chunks/``.
      meta: optional ``N``-row table (e.g. :func:`grid_table`) whose columns
        are copied into the results, row for row.
      fresh: discard the chunks, manifest and results of ``out_dir`` first
        (only once the run directory's lock is held).
      progress: show a tqdm bar over chunks with ETA (never when stderr is not a TTY).
      static_shapes: pad the last chunk to the full batch (one compilation);
        ``False`` runs it at its own size (a second compilation, less padding).
      devices: devices to shard over (default ``jax.devices()``, all hosts).
      desc: progress-bar label.
      fingerprint: what the rows depend on beyond ``params`` and ``meta`` (config,
        files read, package source: :func:`selfid_jax.runner.fingerprint.fingerprint`),
        stored in the manifest; resuming chunks made with another one is refused.
      position: the progress bar's line (for sweeps run side by side in threads).
      execution_lock: for sweeps run side by side in threads, a lock they share: each chunk's program runs
        to completion while holding it, so one program executes at a time (compilation, placement and
        writing still overlap). A workaround for jaxlib 0.10.2 on 2 cores: with two programs in flight from
        two threads XLA's CPU client hung for good (``valid_region_all.yaml``: 3 of 3 runs before the lock,
        1 of 1 without it since), both threads of XLA's intra-op pool inside jaxlib's batched LAPACK LU, each
        waiting for the share of its batch it queued on that same pool. ``scripts/hang_repro.py --config
        configs/valid_region/valid_region_all.yaml`` reproduces it; neither switch upstream reports name
        (``jax_cpu_enable_async_dispatch=False``, ``--xla_cpu_multi_thread_eigen=false``) ended it.
        None (one sweep alone): a chunk computes while the one before it is written.

    Returns:
      The results table, ``N`` rows sorted by ``row`` (int64, 0..N-1), with the
      ``meta`` columns then the output columns; also written to
      ``out_dir/results.parquet``. ``df.attrs["sweep"]`` says which chunks were
      computed now and which were found on disk.

    Raises:
      SweepResumeError: ``out_dir`` holds chunks of a different sweep
        (different N, chunk size, params, meta or float width) or of an older
        manifest format, and ``fresh`` is False.
      RunDirBusy: another process holds the run directory's lock.
    """
    out_dir = Path(out_dir)
    params, treedef = named_leaves(params)
    if not params:
        raise ValueError("params is empty: need at least one N-row array")
    if not (isinstance(chunk_size, (int, np.integer)) and chunk_size > 0):
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    first = next(iter(params.values()))
    n_rows = int(np.shape(first)[0]) if np.ndim(first) else 0
    params = {k: _canonical(k, v, n_rows) for k, v in params.items()}
    if n_rows == 0:
        raise ValueError("params have 0 rows")
    check_rows({"rows": n_rows})
    if meta is not None:
        if len(meta) != n_rows:
            raise ValueError(f"meta has {len(meta)} rows, params have {n_rows}")
        meta = meta.reset_index(drop=True)
        if "row" in meta.columns:
            raise ValueError("meta must not have a 'row' column (it is added)")

    devices = list(devices) if devices is not None else jax.devices()
    n_dev = len(devices)
    rows_per_chunk = min(int(chunk_size), n_rows)
    batch = compiled_batch(n_rows, chunk_size, n_dev)
    n_chunks = math.ceil(n_rows / rows_per_chunk)  # = manifest["n_chunks"]
    x64 = bool(jax.config.jax_enable_x64)  # type: ignore[attr-defined]
    manifest = chunks.new_manifest(params, meta, rows_per_chunk, x64=x64, fingerprint=fingerprint)

    writer = jax.process_index() == 0
    with contextlib.ExitStack() as held:
        error: Exception | None = None
        done = np.zeros(n_chunks, bool)
        if writer:
            try:
                held.enter_context(lock.hold(_run_root(out_dir)))
                manifest = chunks.prepare_dir(out_dir, manifest, fresh)
                done = chunks.verify(out_dir, manifest)
            except Exception as err:  # noqa: BLE001 - broadcast before raising so other hosts do not hang
                error = err
        done, failed = _sync_done(done, error is not None)
        if failed:
            raise error if error is not None else SweepResumeError(f"{out_dir}: process 0 could not prepare the run")

        todo = [i for i in range(n_chunks) if not done[i]]
        skipped = [i for i in range(n_chunks) if done[i]]
        if todo:
            _compute_chunks(
                _row_function(compute_fn, treedef, list(params)), params, meta,
                todo, out_dir=out_dir, manifest=manifest, batch=batch, devices=devices, writer=writer,
                static_shapes=static_shapes, progress=progress, desc=desc, n_done=len(skipped), position=position,
                execution_lock=execution_lock,
            )
        result = chunks.assemble(out_dir, manifest) if writer else None
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices("selfid_jax.run_chunked.done")
        if not writer and (out_dir / RESULTS_FILE).is_file():
            result = pd.read_parquet(out_dir / RESULTS_FILE)
    if result is not None:
        result.attrs["sweep"] = {
            "n_chunks": n_chunks, "computed": todo, "skipped": skipped,
            "batch": batch, "n_devices": n_dev,
        }
    return result


_EXECUTABLES: collections.OrderedDict[tuple, Any] = collections.OrderedDict()
_MAX_EXECUTABLES = 8


def _row_function(compute_fn, treedef, names):
    """The function every chunk runs: named leaves ``{name: (B, ...)}`` -> ``compute_fn(params pytree)``."""
    return lambda leaves: compute_fn(jax.tree.unflatten(treedef, [leaves[k] for k in names]))


def _executables(rows_fn, params: Mapping[str, np.ndarray], devices):
    """``size -> compiled`` for ``rows_fn`` sharded over ``devices``; compilations are shared process-wide."""
    mesh = Mesh(np.asarray(devices), (BATCH_AXIS,))
    in_sharding = NamedSharding(mesh, P(BATCH_AXIS))
    out_sharding = NamedSharding(mesh, P())  # replicated: every process can read all rows
    jitted = jax.jit(rows_fn, in_shardings=(in_sharding,), out_shardings=out_sharding)
    local: dict[int, Any] = {}

    def executable(size: int):
        if size not in local:
            phase("trace")
            lowered = jitted.lower({k: jax.ShapeDtypeStruct((size, *v.shape[1:]), v.dtype, sharding=in_sharding)
                                    for k, v in params.items()})
            cbs = getattr(getattr(lowered, "_lowering", None), "compile_args", {}).get("host_callbacks") or ()
            key = (hashlib.sha256(lowered.as_text().encode()).hexdigest(), tuple(d.id for d in devices),
                   tuple(map(id, cbs)))  # host callbacks (native MuJoCo) are not in the text: never shared
            if key not in _EXECUTABLES:
                phase("compile")
                _EXECUTABLES[key] = lowered.compile()
                _check_outputs(named_leaves(_EXECUTABLES[key].out_info)[0], size)
                out_bytes = sum(int(np.prod(i.shape[1:])) * np.dtype(i.dtype).itemsize
                                for i in named_leaves(_EXECUTABLES[key].out_info)[0].values())
                in_bytes = sum(v[:1].nbytes for v in params.values())
                n_total = len(next(iter(params.values())))  # before any chunk runs: the table it would build
                check_memory(n_total, in_bytes + out_bytes + 8, "the sweep's results table")
                while len(_EXECUTABLES) > _MAX_EXECUTABLES:
                    _EXECUTABLES.popitem(last=False)
            _EXECUTABLES.move_to_end(key)
            local[size] = _EXECUTABLES[key]
        return local[size]

    def place(v: np.ndarray, idx: np.ndarray, size: int):
        h = v[idx]
        return jax.make_array_from_callback((size, *v.shape[1:]), in_sharding, lambda s: h[s])

    return executable, place


def compiled_batch(n_rows: int, chunk_size: int, n_devices: int | None = None) -> int:
    """The batch :func:`run_chunked` compiles: ``min(chunk_size, n_rows)`` rounded up to a multiple of the devices."""
    n_dev = jax.device_count() if n_devices is None else int(n_devices)
    rows = min(int(chunk_size), int(n_rows))
    return -(-rows // n_dev) * n_dev


def compute_rows(compute_fn: Callable[[Any], Any], params: Any, *, batch: int,
                 devices: Sequence[jax.Device] | None = None) -> dict[str, np.ndarray]:
    """``compute_fn`` over ``N`` parameter rows in memory, ``batch`` at a time: ``{output name: (N, ...) numpy}``.

    The program :func:`run_chunked` compiles for the same ``compute_fn``,
    parameter structure and ``batch`` (:func:`compiled_batch`), and shares its
    compilation. For work an experiment finishes before it fixes its rows.
    """
    params, treedef = named_leaves(params)
    n_rows = int(np.shape(next(iter(params.values())))[0])
    params = {k: _canonical(k, v, n_rows) for k, v in params.items()}
    devices = list(devices) if devices is not None else jax.devices()
    executable, place = _executables(_row_function(compute_fn, treedef, list(params)), params, devices)
    outs = []
    for start in range(0, n_rows, batch):
        rows = np.arange(start, min(start + batch, n_rows))
        idx = np.concatenate([rows, np.full(batch - len(rows), rows[-1])])
        out = executable(batch)({k: place(v, idx, batch) for k, v in params.items()})
        outs.append({k: np.asarray(v)[: len(rows)] for k, v in named_leaves(out)[0].items()})
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}


def _compute_chunks(
    compute_fn, params, meta, todo, *, out_dir, manifest, batch, devices, writer, static_shapes, progress, desc,
    n_done, position=None, execution_lock=None,
) -> None:
    n_chunks = manifest["n_chunks"]
    executable, place = _executables(compute_fn, params, devices)

    def dispatch(i: int):
        rows = np.arange(*chunks.chunk_rows(manifest, i))
        size = batch if static_shapes else -(-len(rows) // len(devices)) * len(devices)
        idx = np.concatenate([rows, np.full(size - len(rows), rows[-1])])
        args = {k: place(v, idx, size) for k, v in params.items()}
        program = executable(size)  # compiles outside the lock
        if execution_lock is None:
            return rows, program(args)
        with execution_lock:
            return rows, jax.block_until_ready(program(args))

    bar = tqdm(
        total=n_chunks, initial=n_done, unit="chunk", desc=desc, dynamic_ncols=True, position=position,
        disable=None if progress and writer else True,
    )
    t0, rows_done = time.perf_counter(), 0
    with bar:
        pending = None
        single = jax.process_count() == 1  # several processes must dispatch in lockstep
        for i in [*todo, None]:
            stop = single and _STOP.is_set()
            # dispatch is async: chunk i computes while chunk `pending` is written
            nxt = (i, *dispatch(i)) if i is not None and not stop else None
            if pending is not None:
                j, rows, out = pending
                host = {k: np.asarray(v)[: len(rows)] for k, v in named_leaves(out)[0].items()}
                if writer:
                    data = chunks.table_bytes(chunks.chunk_table(rows, meta, host))
                    chunks.record_chunk(out_dir, manifest, j, data)  # before the file: a chunk file always has a record
                    _write_chunk(chunks.chunk_path(out_dir, j, n_chunks), data)
                    phase("chunk")
                rows_done += len(rows)
                bar.set_postfix(rows_per_s=f"{rows_done / max(time.perf_counter() - t0, 1e-9):.3g}", refresh=False)
                bar.update(1)
            pending = nxt
            if stop:
                raise SweepInterrupted(f"stop requested; finished chunks are in {out_dir / CHUNKS_DIR}")


def _check_outputs(out_info: Any, size: int) -> None:
    if not out_info:
        raise TypeError("compute_fn must return a non-empty NamedTuple or dict of arrays")
    for name, info in out_info.items():
        shape = getattr(info, "shape", None)
        if shape is None:
            raise TypeError(f"compute_fn output {name!r} must be an array, got {type(info).__name__}")
        if len(shape) == 0 or shape[0] != size:
            raise ValueError(f"compute_fn output {name!r} has shape {tuple(shape)}; need leading batch axis {size}")
        if name == "row":
            raise ValueError("compute_fn output must not be named 'row' (the row index column)")


