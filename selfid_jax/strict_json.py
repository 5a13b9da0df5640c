"""Strict JSON values: the one conversion of what the package writes as JSON (run directories, session logs).

:func:`jsonable` turns numpy scalars and arrays into Python numbers and
lists, mapping keys into strings, paths into strings, and NaN/inf into
``None`` (strict JSON has no non-finite numbers). Floats are kept exactly:
``json`` writes ``repr``, the shortest string that reads back as the same
float64, so a number is written one way wherever it is written. A grid
built by arithmetic should be built from clean decimals at its source (for
example :func:`selfid_jax.runner.grids.decimal_linspace`) rather than rounded
here.

A bottom layer beside :mod:`selfid_jax.math` (the layers contract in
``pyproject.toml``): it imports nothing else of ``selfid_jax``, so both the
runner and the robot, which may not import each other, use it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import PurePath
from typing import Any

import numpy as np

__all__ = ["jsonable"]


def jsonable(x: Any) -> Any:
    """``x`` as plain JSON values: numpy -> Python, NaN/inf -> None, Path -> str, mapping keys -> str; floats exact.

    Mappings become dicts, lists and tuples lists, numpy arrays nested lists
    and numpy scalars Python ``float``/``int``/``bool``; anything else is
    returned as it is (``json.dumps`` then refuses what it cannot write).
    """
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, PurePath):
        return str(x)
    return x
