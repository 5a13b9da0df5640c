"""Valid region over the workspace figure: bounds against dexterity, completion and predicted-stability heatmaps.

:func:`plot` is the ``valid_region_workspace`` experiment's ``plot``
(:mod:`selfid_jax.experiments.valid_region_workspace`), from saved results.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from selfid_jax.runner.figures import save_figure

__all__ = ["plot", "threshold_outline"]


def threshold_outline(passing: np.ndarray, eps: np.ndarray, half: float):
    """The boundary of the passing cells of a ``(bins, eps)`` heatmap, as a white ``LineCollection``.

    Args:
      passing: ``(n_bins, n_eps)`` bool, a cell's mean completion >= the threshold.
      eps: ``(n_eps,)`` the cells' centres along x (``eps_limit``); rows are centred on ``0 .. n_bins - 1``.
      half: half a cell's width along x.

    Returns:
      a ``LineCollection`` (gid ``"threshold"``) of the cell edges between a passing and a failing (or outside) cell.
    """
    ok = np.pad(np.asarray(passing, bool), 1)
    segments = []
    for i, j in zip(*np.nonzero(ok)):
        x0, x1, y0, y1 = eps[j - 1] - half, eps[j - 1] + half, i - 1.5, i - 0.5
        for di, dj, seg in ((-1, 0, [(x0, y0), (x1, y0)]), (1, 0, [(x0, y1), (x1, y1)]),
                            (0, -1, [(x0, y0), (x0, y1)]), (0, 1, [(x1, y0), (x1, y1)])):
            if not ok[i + di, j + dj]:
                segments.append(seg)
    return LineCollection(segments, colors="w", linewidths=1.5, gid="threshold")


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """Bounds against manipulability and condition (scatter), completion and predicted stability heatmaps."""
    per = pd.DataFrame(summary["configs"])
    threshold = float(summary["completion_threshold"])
    fig = Figure(figsize=(16, 9), layout="constrained")
    ax = fig.subplots(2, 2)
    for a, col, label in ((ax[0, 0], "manipulability", "Yoshikawa manipulability of the task Jacobian"),
                          (ax[0, 1], "condition", "condition of the task Jacobian")):
        x = per[col].astype(float)
        a.scatter(x, per["upper"], s=12, label="upper (simulated)")
        a.scatter(x, per["lower"], s=12, label="lower (simulated)")
        a.scatter(x, per["predicted_upper"], s=12, marker="x", label=r"upper (predicted: $\rho(I - JJ_{hat})<1$)")
        a.set_xscale("log")
        a.set_xlabel(col if col == "condition" else label)
        a.set_ylabel("eps_limit")
        a.legend(fontsize=8, loc="best")
    ax[0, 0].set_title(f"{summary['system']}: valid region per start configuration "
                       f"({summary['fail_with_exact_inverse']} of {summary['n_configs']} fail with the exact inverse)",
                       fontsize=10)
    ax[0, 1].set_title("the same against the condition number", fontsize=10)
    for a, col, title in ((ax[1, 0], "completion", "mean completion (simulated)"),
                          (ax[1, 1], "predicted_stable", r"fraction of $m_\epsilon$ draws with $\rho < 1$")):
        grid = table.groupby(["manipulability_bin", "eps_limit"])[col].mean().unstack("eps_limit")
        eps = grid.columns.to_numpy(float)
        half = 0.5 * (float(np.mean(np.diff(eps))) if len(eps) > 1 else 1.0)  # cells centred on the grid values
        im = a.imshow(grid.to_numpy(float), origin="lower", aspect="auto", vmin=0, vmax=1, cmap="viridis",
                      extent=(eps[0] - half, eps[-1] + half, -0.5, grid.shape[0] - 0.5), interpolation="nearest")
        if col == "completion":  # outline the cells whose mean completion reaches the threshold
            a.add_collection(threshold_outline(grid.to_numpy(float) >= threshold, eps, half))
            a.plot([], [], color="w", lw=1.5, label=f"mean completion >= {threshold:g}")
            a.legend(fontsize=8, loc="upper right", facecolor="0.3", labelcolor="w")
        a.set_xlabel("eps_limit")
        a.set_ylabel("manipulability bin (quantiles, low to high)")
        a.set_title(title, fontsize=10)
        fig.colorbar(im, ax=a, shrink=0.8)
    ctrl = summary["controller"]
    fig.suptitle(f"star {summary['path']['size']} m; controller max_step {ctrl['max_step']} m, tol {ctrl['tol']} m, "
                 f"gain {ctrl['gain']}, budget {ctrl['steps']} steps; threshold {summary['completion_threshold']}")
    return save_figure(fig, out_dir, "valid_region_workspace", dpi=110)
