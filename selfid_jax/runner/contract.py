"""The experiment contract: config model -> (static setup, traced params) -> pure compute -> table -> summary ->
figures.

An :class:`Experiment` is a frozen bundle of pure pieces:

* ``config``: its pydantic config model (a :class:`~selfid_jax.runner.config.BaseConfig`
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
  ``row``-per-batch-element table, e.g. one row per method and checkpoint),
  ``report(summary) -> str`` (what ``selfid-jax sweep`` prints) and
  ``columns``: the results table's column names, each with its one-line
  meaning and unit in brackets (``"mean distance to the path [m]"``); a run
  whose table holds a column not listed warns :class:`UndocumentedColumns`.

:mod:`selfid_jax.runner.registry` finds experiments by name and
:func:`selfid_jax.runner.execute.run` runs one into a run directory.
"""

from __future__ import annotations

import dataclasses
import functools
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import pandas as pd

from selfid_jax.runner.config import BaseConfig
from selfid_jax.runner.layout import SAFE_NAME

__all__ = ["Experiment", "Part", "UndocumentedColumns"]


class UndocumentedColumns(UserWarning):
    """A results table holds columns its experiment's ``columns`` does not document (the tests make it an error)."""


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
    columns: Mapping[str, str] | None = None  # results column -> "one-line meaning [unit]"; None: not documented

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
        unsafe = [n for n in names if not (isinstance(n, str) and re.fullmatch(SAFE_NAME, n))]
        if unsafe:
            raise ValueError(f"experiment {self.name!r}: part names must be one path component (letters, digits, "
                             f"'.', '_', '+', '-'; not starting with '.'), got {unsafe}")
        return parts

    def batched(self, static) -> Callable[[Any], Any]:
        """``params (B, ...) -> outputs (B, ...)``: :attr:`compute` vmapped over rows, ``static`` closed over."""
        import jax

        return jax.vmap(functools.partial(self.compute, static))
