"""Running an experiment into a run directory: the lock taken once, the parts chunked and resumable, table and summary
written.

:func:`run` takes the run directory's lock (:func:`selfid_jax.runner.lock.hold`)
for a run; everything below it (creating or reopening the directory, each part's
:func:`~selfid_jax.runner.sweep.run_chunked`, the results and summary) runs under
that hold. The lock is re-entrant within a process, so a caller with more to write
after the run (``selfid-jax sweep`` and ``demo`` draw the figures) holds it around
:func:`run` and releases it only once that is written too.
"""

from __future__ import annotations

import contextlib
import threading
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

import pandas as pd

from selfid_jax.runner import lock
from selfid_jax.runner.config import dump_config
from selfid_jax.runner.contract import Experiment, Part, UndocumentedColumns
from selfid_jax.runner.errors import ConfigError, SweepResumeError
from selfid_jax.runner.fingerprint import fingerprint
from selfid_jax.runner.layout import PARTS_DIR
from selfid_jax.runner.rundir import create_run_dir, record_refused, write_results, write_summary
from selfid_jax.runner.sweep import run_chunked

T = TypeVar("T")
R = TypeVar("R")

__all__ = ["PART_THREADS_ENV", "check_columns", "part_threads", "precision", "run", "side_by_side"]


def precision(x64: bool):
    """Context for building or running a part: ``jax.enable_x64(True)`` if ``x64``, else the current setting."""
    import jax

    return jax.enable_x64(True) if x64 else contextlib.nullcontext()


def run(
    experiment: Experiment,
    cfg,
    out_dir: str | Path,
    *,
    fresh: bool = False,
    progress: bool = False,
    parts: Sequence[Part] | None = None,
    config_path: str | Path | None = None,
    overrides: Sequence[str] = (),
) -> tuple[pd.DataFrame, dict] | None:
    """Run ``experiment`` on ``cfg`` into the run directory ``out_dir``; returns ``(table, summary)``.

    Under the directory's lock, taken once here: the directory is created or
    reopened for resuming (:func:`~selfid_jax.runner.rundir.create_run_dir`,
    recording ``config_path`` and ``overrides``; ``fresh`` discards what it
    holds), then each part runs through :func:`selfid_jax.runner.sweep.run_chunked` (resumable
    chunks under ``out_dir/parts/<name>/``; several parts side by side in threads, one per core,
    :func:`part_threads`), the parts' tables (after
    ``tabulate``) are concatenated into ``out_dir/results.parquet`` and the
    summary is written to ``out_dir/summary.json``. ``parts``: the result of
    ``experiment.parts(cfg)`` if already built (the CLI builds them, and so
    finds every bad input, before it creates the run directory). Returns
    ``None`` on the processes other than 0 of a ``jax.distributed`` run.
    """
    import jax

    if not isinstance(cfg, experiment.config):
        raise TypeError(f"experiment {experiment.name!r} needs a {experiment.config.__name__}, "
                        f"got {type(cfg).__name__}")
    out_dir = Path(out_dir)
    if jax.process_index() != 0:
        return _run_parts(experiment, cfg, out_dir, fresh, progress, parts)
    with lock.hold(out_dir):  # no other process may write or --fresh this directory meanwhile
        create_run_dir(out_dir, cfg, config_path, overrides=overrides, fresh=fresh)
        try:
            return _run_parts(experiment, cfg, out_dir, fresh, progress, parts)
        except SweepResumeError as err:
            record_refused(out_dir, str(err), config_path=config_path, overrides=overrides)
            raise


def check_columns(experiment: Experiment, table: pd.DataFrame) -> list[str]:
    """Warn :class:`~selfid_jax.runner.contract.UndocumentedColumns` for the columns of ``table`` that
    ``experiment.columns`` does not list (nothing if it is ``None``); returns them."""
    if experiment.columns is None:
        return []
    missing = [str(c) for c in table.columns if c not in experiment.columns]
    if missing:
        warnings.warn(f"experiment {experiment.name!r}: results columns not documented in its columns: {missing}",
                      UndocumentedColumns, stacklevel=3)
    return missing


PART_THREADS_ENV = "SELFID_JAX_PART_THREADS"


def part_threads(n_parts: int) -> int:
    """How many parts :func:`run` runs at once: one per CPU core this process may use, at most ``n_parts``.

    ``$SELFID_JAX_PART_THREADS`` (a positive integer) overrides the core count; 1 runs the parts one after
    another. XLA compiles one program on one core, so on ``k`` cores ``k`` parts compile side by side.
    A bad value raises :class:`~selfid_jax.runner.errors.ConfigError` naming it.
    """
    import os

    raw = os.environ.get(PART_THREADS_ENV, "").strip()
    if raw:
        if not raw.isdigit() or int(raw) < 1:
            raise ConfigError(f"${PART_THREADS_ENV} must be a positive integer, got {raw!r}")
        cores = int(raw)
    else:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(int(n_parts), cores))


def side_by_side(fn: Callable[[int, T], R], items: Sequence[T], *, threads: int, name: str = "selfid-jax-part"
                 ) -> list[R]:
    """``[fn(i, item) for i, item in enumerate(items)]``, on ``threads`` worker threads when more than one.

    Each call runs under the caller's JAX setting contexts (``jax.enable_x64(...)``,
    ``jax.default_device(...)``, ``jax.numpy_rank_promotion(...)``,
    ``jax.default_matmul_precision(...)``), which hold for the thread that
    entered them only: they are read here and entered around each call, so an
    item computed in a worker is what it would be in the caller's thread. The
    results come back in order; the first error is raised once the calls
    already running have returned (calls not yet started are dropped).
    ``name``: the worker threads' name prefix.
    """
    if threads <= 1 or len(items) <= 1:
        return [fn(i, item) for i, item in enumerate(items)]
    import concurrent.futures

    import jax

    cfg = jax.config
    settings = (bool(cfg.jax_enable_x64), cfg.jax_default_device,  # type: ignore[attr-defined]
                cfg.jax_numpy_rank_promotion, cfg.jax_default_matmul_precision)  # type: ignore[attr-defined]

    def call(i: int, item: T) -> R:
        x64, device, promotion, matmul = settings
        with (jax.enable_x64(x64), jax.default_device(device), jax.numpy_rank_promotion(promotion),
              jax.default_matmul_precision(matmul)):
            return fn(i, item)

    pool = concurrent.futures.ThreadPoolExecutor(max_workers=threads, thread_name_prefix=name)
    futures = [pool.submit(call, i, item) for i, item in enumerate(items)]
    try:
        return [f.result() for f in futures]
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _run_parts(experiment: Experiment, cfg, out_dir: Path, fresh: bool, progress: bool, parts):
    import jax

    inputs = cfg.input_files() if hasattr(cfg, "input_files") else {}
    fp = fingerprint(dump_config(cfg), inputs)
    parts = list(experiment.parts(cfg) if parts is None else parts)

    threads = part_threads(len(parts)) if jax.process_count() == 1 else 1
    execution_lock = threading.Lock() if threads > 1 else None  # see run_chunked: one program in flight at a time

    def one(index: int, part: Part):
        with precision(part.x64):
            return run_chunked(
                experiment.batched(part.static),
                part.params,
                chunk_size=cfg.chunk_size,
                out_dir=out_dir / PARTS_DIR / part.name,
                meta=part.meta,
                fresh=fresh,
                progress=progress,
                desc=part.name,
                fingerprint=fp,
                position=index if len(parts) > 1 else None,
                execution_lock=execution_lock,
            )

    # Several parts of one process run side by side in threads (XLA releases the GIL while it compiles and
    # computes): every part's table is what it would be alone. Several processes of a jax.distributed run must
    # dispatch in lockstep, so they run the parts in order.
    wides = side_by_side(one, parts, threads=threads)
    tables = []
    for wide, part in zip(wides, parts):
        if wide is None:  # another process of a jax.distributed run writes the files
            return None
        wide = wide.drop(columns=["row"])
        tables.append(experiment.tabulate(wide, part, cfg) if experiment.tabulate is not None else wide)
    table = pd.concat(tables, ignore_index=True)
    if jax.process_index() != 0:
        return None
    check_columns(experiment, table)
    write_results(out_dir, table)
    summary = experiment.summarize(table, cfg)
    write_summary(out_dir, summary)
    return table, summary
