"""Reachable-workspace figures: manipulability and condition maps per r-z / x-z cell, from saved results.

:func:`plot` is the ``workspace`` experiment's ``plot`` (:mod:`selfid_jax.experiments.workspace`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from selfid_jax.runner.figures import save_figure

from ..workspace import PLANES, cell_maps

__all__ = ["plot"]


def _panel(fig, ax, grid, extent, title, label, *, log=False, cmap="viridis"):
    data = np.ma.masked_invalid(grid)
    norm = None
    if log and data.count():
        norm = LogNorm(vmin=max(float(data.min()), 1e-12), vmax=float(data.max()))
    im = ax.imshow(data, origin="lower", extent=extent, cmap=cmap, norm=norm, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal")
    fig.colorbar(im, ax=ax, shrink=0.8, label=label)


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """``workspace`` (seed 004's metrics) and ``workspace_position`` (position-only, unit-consistent) maps."""
    cell = float(summary["cell_m"])
    paths = []
    figures = (
        ("workspace", "sqrt_manipulability", "condition", r"$\sqrt{\prod\sigma_i}$ (6 x n)", "condition (6 x n)"),
        ("workspace_position", "position_sqrt_manipulability", "unit_consistent_condition",
         r"$\sqrt{\prod\sigma_i}$ (position, 3 x n)", f"unit-consistent condition (L = {summary['length_m']:g} m)"),
    )
    for name, mcol, ccol, mlabel, clabel in figures:
        fig = Figure(figsize=(15, 9), layout="constrained")
        axes = fig.subplots(2, 3)
        for row, plane in zip(axes, PLANES):
            cm = cell_maps(table, cell, plane, manipulability_column=mcol, condition_column=ccol)
            hname = "r" if plane == "rz" else "x"
            _panel(fig, row[0], cm.max_manipulability, cm.extent, f"max {mlabel}, {hname}-z", mlabel)
            _panel(fig, row[1], cm.mean_manipulability, cm.extent, f"mean {mlabel}, {hname}-z", mlabel)
            _panel(fig, row[2], cm.min_condition, cm.extent, f"min {clabel}, {hname}-z", clabel, log=True,
                   cmap="magma_r")
            for ax in row:
                ax.set_xlabel(f"{hname} [m]")
                ax.set_ylabel("z [m]")
        fig.suptitle(f"{summary['system']}: {summary['n_configs']} configurations, {1e3 * cell:g} mm cells "
                     f"({summary['cells_reached']['rz']} r-z / {summary['cells_reached']['xz']} x-z reached); "
                     "x-z: all configurations projected along y")
        paths += save_figure(fig, out_dir, name, dpi=110)
    return paths
