"""Running an experiment into a run directory: the lock taken once, the parts chunked and resumable, table and summary
written.

:func:`run` is the one place that takes the run directory's lock
(:func:`selfid_jax.runner.lock.hold`) for a run; everything below it (creating or
reopening the directory, each part's :func:`~selfid_jax.runner.sweep.run_chunked`,
the results and summary) runs under that hold.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from selfid_jax.runner import lock
from selfid_jax.runner.config import dump_config
from selfid_jax.runner.contract import Experiment, Part, UndocumentedColumns
from selfid_jax.runner.fingerprint import fingerprint
from selfid_jax.runner.layout import PARTS_DIR
from selfid_jax.runner.rundir import create_run_dir, record_refused, write_results, write_summary
from selfid_jax.runner.errors import SweepResumeError
from selfid_jax.runner.sweep import run_chunked

__all__ = ["check_columns", "precision", "run"]


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
    chunks under ``out_dir/parts/<name>/``), the parts' tables (after
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


def _run_parts(experiment: Experiment, cfg, out_dir: Path, fresh: bool, progress: bool, parts):
    import jax

    inputs = cfg.input_files() if hasattr(cfg, "input_files") else {}
    fp = fingerprint(dump_config(cfg), inputs)
    tables = []
    for part in experiment.parts(cfg) if parts is None else parts:
        with precision(part.x64):
            wide = run_chunked(
                experiment.batched(part.static),
                part.params,
                chunk_size=cfg.chunk_size,
                out_dir=out_dir / PARTS_DIR / part.name,
                meta=part.meta,
                fresh=fresh,
                progress=progress,
                desc=part.name,
                fingerprint=fp,
            )
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
