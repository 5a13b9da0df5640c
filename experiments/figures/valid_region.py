"""Valid-region figure (paper Fig. 2): completion and tracking error against eps_limit per system, from saved results.

:func:`plot` is the ``valid_region`` experiment's ``plot``
(:mod:`selfid_jax.experiments.valid_region`); the drawing is
:func:`selfid_jax.experiments.common.figures.valid_region_figure`, which other
figures share.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from ..common.figures import valid_region_figure
from ..valid_region import series

__all__ = ["plot"]


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """Fig. 2 from the saved table, each realism level a series of its own
    (:func:`~selfid_jax.experiments.valid_region.series`)."""
    return valid_region_figure(series(table), summary, out_dir)
