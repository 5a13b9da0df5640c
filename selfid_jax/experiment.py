"""The experiment contract: config model -> (static setup, traced params) -> pure compute -> table -> summary -> figures.

An :class:`Experiment` is a frozen bundle of pure pieces:

* ``config``: its pydantic config model (a :class:`~selfid_jax.config.BaseConfig`
  subclass whose ``experiment`` field is the experiment's name);
* ``build(cfg) -> Part | list[Part]``: everything the compute needs, split into
  a static setup (systems, paths, estimators, sizes: closed over, never a
  config object) and a ``Params`` pytree (a ``NamedTuple`` of arrays, batch
  axis first: every number a user may sweep, so one compilation serves the
  whole sweep) with an ``N``-row label table. One :class:`Part` per compiled
  program (e.g. one per system, whose shapes differ);
* ``compute(static, params_row) -> Outputs``: pure JAX for ONE row
  (``params_row`` has no batch axis), returning a ``NamedTuple`` of named
  metric arrays; the runner vmaps, jits, chunks and shards it;
* ``summarize(table, cfg) -> dict`` (JSON-ready) and
  ``plot(table, summary, out_dir) -> list[Path]`` (reads saved results only);
* optionally ``tabulate(wide, part, cfg) -> DataFrame`` (reshape one part's
  ``row``-per-batch-element table, e.g. one row per method and checkpoint) and
  ``report(summary) -> str`` (what ``selfid-jax sweep`` prints).

Experiments are found by name through the Python entry-point group
``selfid_jax.experiments`` (``pyproject.toml``: ``valid_region =
"experiments.valid_region:EXPERIMENT"``), so a user's package adds one the same
way; :func:`register` adds one at run time (tests, notebooks). The library never
imports an experiment module by name.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib.metadata
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

from selfid_jax import lock
from selfid_jax.config import BaseConfig, ConfigError, ControllerConfig

__all__ = [
    "ENTRY_POINT_GROUP",
    "Experiment",
    "Part",
    "available",
    "controller_rows",
    "get",
    "precision",
    "register",
    "run",
]

ENTRY_POINT_GROUP = "selfid_jax.experiments"


class Part(NamedTuple):
    """One compiled program of an experiment: its static setup and ``N`` rows of traced parameters."""

    name: str  # label; the part's chunks go to RUN/parts/<name>/
    static: Any  # closed over by compute (systems, paths, estimators, static sizes); no config object
    params: Any  # NamedTuple (or dict) pytree of arrays, each with leading axis N
    meta: pd.DataFrame  # N rows of labels copied into the results table
    x64: bool = False  # run this part in float64 (jax.enable_x64), e.g. a closed-chain hand; the others stay as set


@dataclasses.dataclass(frozen=True)
class Experiment:
    """A named experiment: config model, build, pure per-row compute, summary and figures (see module docstring)."""

    name: str
    config: type[BaseConfig]
    build: Callable[[Any], Part | Sequence[Part]]
    compute: Callable[[Any, Any], Any]
    summarize: Callable[[pd.DataFrame, Any], dict]
    plot: Callable[[pd.DataFrame, dict, Path], Sequence[Path]] | None = None
    tabulate: Callable[[pd.DataFrame, Part, Any], pd.DataFrame] | None = None
    report: Callable[[dict], str] | None = None
    description: str = ""

    def __post_init__(self):
        if not self.name.isidentifier():
            raise ValueError(f"experiment name must be an identifier, got {self.name!r}")
        if not (isinstance(self.config, type) and issubclass(self.config, BaseConfig)):
            raise TypeError(f"experiment {self.name!r}: config must be a BaseConfig subclass, got {self.config!r}")
        for field in ("build", "compute", "summarize"):
            if not callable(getattr(self, field)):
                raise TypeError(f"experiment {self.name!r}: {field} must be callable")

    def parts(self, cfg) -> list[Part]:
        """``build(cfg)`` as a list of :class:`Part`, checked: unique names, ``N`` rows everywhere."""
        built = self.build(cfg)
        parts = [built] if isinstance(built, Part) else list(built)
        names = [p.name for p in parts]
        if not parts or len(set(names)) != len(names):
            raise ValueError(f"experiment {self.name!r}: build must return parts with unique names, got {names}")
        return parts

    def batched(self, static) -> Callable[[Any], Any]:
        """``params (B, ...) -> outputs (B, ...)``: :attr:`compute` vmapped over rows, ``static`` closed over."""
        import jax

        return jax.vmap(functools.partial(self.compute, static))


# --------------------------------------------------------------------------- registry

_RUNTIME: dict[str, Experiment] = {}


def register(experiment: Experiment) -> Experiment:
    """Make ``experiment`` available by name in this process (in addition to the entry points)."""
    if not isinstance(experiment, Experiment):
        raise TypeError(f"register needs an Experiment, got {type(experiment).__name__}")
    _RUNTIME[experiment.name] = experiment
    return experiment


def _entry_points() -> dict[str, importlib.metadata.EntryPoint]:
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


def available() -> list[str]:
    """Names of every experiment: installed entry points and run-time registrations, sorted."""
    return sorted(set(_entry_points()) | set(_RUNTIME))


@functools.lru_cache(maxsize=None)
def _load(name: str) -> Experiment:
    ep = _entry_points()[name]
    exp = ep.load()
    if not isinstance(exp, Experiment) or exp.name != name:
        raise TypeError(
            f"entry point {name!r} = {ep.value!r} (group {ENTRY_POINT_GROUP}) must be an Experiment named {name!r}, "
            f"got {exp!r}"
        )
    return exp


def get(name: str) -> Experiment:
    """The experiment called ``name``; :class:`~selfid_jax.config.ConfigError` listing the known ones if none."""
    if name in _RUNTIME:
        return _RUNTIME[name]
    if isinstance(name, str) and name in _entry_points():
        return _load(name)
    raise ConfigError(f"unknown experiment {name!r}; allowed: one of {', '.join(available()) or '(none installed)'}")


# --------------------------------------------------------------------------- helpers for build

def precision(x64: bool):
    """Context for building or running a part: ``jax.enable_x64(True)`` if ``x64``, else the current setting."""
    import jax

    return jax.enable_x64(True) if x64 else contextlib.nullcontext()


def controller_rows(controller: ControllerConfig, n_rows: int):
    """The traced controller settings of ``controller`` repeated for ``n_rows`` rows: ``ControllerParams`` of ``(N,)``."""
    from selfid_jax.control import ControllerParams

    return ControllerParams(**{k: np.full((n_rows,), float(v)) for k, v in controller.traced().items()})


# --------------------------------------------------------------------------- running

def run(
    experiment: Experiment,
    cfg,
    out_dir: str | Path,
    *,
    fresh: bool = False,
    progress: bool = False,
    parts: Sequence[Part] | None = None,
) -> tuple[pd.DataFrame, dict] | None:
    """Run ``experiment`` on ``cfg`` into the run directory ``out_dir``; returns ``(table, summary)``.

    Each part runs through :func:`selfid_jax.sweep.run_chunked` (resumable
    chunks under ``out_dir/parts/<name>/``), the parts' tables (after
    ``tabulate``) are concatenated into ``out_dir/results.parquet`` and the
    summary is written to ``out_dir/summary.json``. ``parts``: the result of
    ``experiment.parts(cfg)`` if already built (the CLI builds them, and so
    finds every bad input, before it creates the run directory). Returns
    ``None`` on the processes other than 0 of a ``jax.distributed`` run.
    """
    import jax

    if not isinstance(cfg, experiment.config):
        raise TypeError(f"experiment {experiment.name!r} needs a {experiment.config.__name__}, got {type(cfg).__name__}")
    out_dir = Path(out_dir)
    if jax.process_index() != 0:
        return _run_parts(experiment, cfg, out_dir, fresh, progress, parts)
    with lock.hold(out_dir):  # no other process may write or --fresh this directory meanwhile
        return _run_parts(experiment, cfg, out_dir, fresh, progress, parts)


def _run_parts(experiment: Experiment, cfg, out_dir: Path, fresh: bool, progress: bool, parts):
    import jax

    from selfid_jax.results import PARTS_DIR, write_results, write_summary
    from selfid_jax.sweep import run_chunked

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
            )
        if wide is None:  # another process of a jax.distributed run writes the files
            return None
        wide = wide.drop(columns=["row"])
        tables.append(experiment.tabulate(wide, part, cfg) if experiment.tabulate is not None else wide)
    table = pd.concat(tables, ignore_index=True)
    if jax.process_index() != 0:
        return None
    write_results(out_dir, table)
    summary = experiment.summarize(table, cfg)
    write_summary(out_dir, summary)
    return table, summary
