"""An experiment's ``plot``, which imports the experiment's figures module (and so matplotlib) when first called.

Each experiment ``experiments/<name>.py`` keeps its schema, build, compute and
summary; its figures are in ``experiments/figures/<name>.py``. The experiment
hands the runner ``plot=figures_plot("<name>")``, so importing an experiment
(to run a sweep, to validate a config) does not load matplotlib: only drawing
does (``selfid-jax plot RUN_DIR`` and the end of ``selfid-jax sweep``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["FIGURES_PACKAGE", "figures_plot"]

FIGURES_PACKAGE = "selfid_jax.experiments.figures"
"""The package of the experiments' figures modules, one per experiment and named after it."""


def figures_plot(experiment: str) -> Callable[[Any, dict, Path], Sequence[Path]]:
    """``plot(table, summary, out_dir) -> [Path]``: :data:`FIGURES_PACKAGE`'s ``<experiment>.plot``, imported on the
    first call (an experiment's ``Experiment.plot``; it reads saved results only)."""
    module = f"{FIGURES_PACKAGE}.{experiment}"

    def plot(table, summary: dict, out_dir: Path) -> Sequence[Path]:
        return importlib.import_module(module).plot(table, summary, out_dir)

    plot.__doc__ = f"The figures of the {experiment} experiment: ``{module}.plot`` (imported on the first call)."
    return plot
