"""Sweep grids: the label table of a Cartesian product and per-row PRNG keys that do not depend on chunking."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, cast

import jax
import numpy as np
import pandas as pd

from selfid_jax.runner.limits import check_rows

__all__ = ["decimal_linspace", "decimal_points", "grid_table", "row_keys"]


def grid_table(axes: Mapping[str, Sequence[Any]]) -> pd.DataFrame:
    """Cartesian product of named axes, one row per combination, last axis fastest.

    ``grid_table({"system": ["a", "b"], "trial": range(3)})`` has 6 rows with
    columns ``system, trial``. Use it as the ``meta`` table of :func:`run_chunked`
    and derive the parameter arrays from its columns. A product above the row
    limit raises :class:`~selfid_jax.runner.limits.SizeError` naming the axes.
    """
    if not axes:
        raise ValueError("grid_table needs at least one axis")
    axes = {k: list(v) for k, v in axes.items()}
    check_rows({k: len(v) for k, v in axes.items()})  # before the product is allocated
    index = pd.MultiIndex.from_product([list(v) for v in axes.values()], names=list(axes))
    return index.to_frame(index=False)


def decimal_linspace(start: float, stop: float, num: int) -> np.ndarray:
    """``np.linspace(start, stop, num)`` (``(num,)`` float64) with each point the float of its 12-digit decimal.

    ``linspace`` computes its points by arithmetic, so ``decimal_linspace(0, 3, 61)[7]`` would be
    ``0.35000000000000003``: here it is ``0.35``, the value a user who wrote the grid by hand would sweep, and it is
    written to JSON (exactly, :mod:`selfid_jax.strict_json`) and shown as such. Points differ from ``linspace``'s by
    at most a few ulps; endpoints are ``start`` and ``stop``.
    """
    return decimal_points(np.linspace(start, stop, num))


def decimal_points(points) -> np.ndarray:
    """``points (num,)`` as float64, each the float of its 12-digit decimal: a grid built by arithmetic
    (``linspace``, ``geomspace``) with its binary noise dropped, so the value swept is the value written."""
    return np.array([float(f"{x:.12g}") for x in np.asarray(points, np.float64)], np.float64)


def row_keys(seed: int, rows: int | np.ndarray) -> np.ndarray:
    """PRNG key data for each row, ``fold_in(key(seed), row)``: same numbers however rows are chunked.

    Args:
      seed: the config's seed.
      rows: ``N`` (rows ``0..N-1``) or an array of global row indices, shape ``(N,)``.

    Returns:
      ``(N, k)`` uint32 key data (``k = 2`` for the default threefry PRNG); in
      ``compute_fn`` turn a row back into a key with ``jax.random.wrap_key_data``.
    """
    idx = np.arange(cast(int, rows)) if np.ndim(rows) == 0 else np.asarray(rows)
    if idx.size and (idx.min() < 0 or idx.max() >= 2**32):
        raise ValueError("row indices must lie in [0, 2**32)")
    base = jax.random.key(seed)
    keys = jax.vmap(jax.random.fold_in, in_axes=(None, 0))(base, idx.astype(np.uint32))
    return np.asarray(jax.random.key_data(keys))
