"""Articulated-object figures: handle and gripper trajectories, metric distributions, the stiffness x resistance
plane, from saved results.

:func:`plot` is the ``articulated`` experiment's ``plot`` (:mod:`selfid_jax.experiments.articulated`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from selfid_jax.runner.figures import save_figure

from ..articulated import METRICS

__all__ = ["metrics_figure", "plane_figure", "plot"]


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """Handle and gripper trajectories per object kind (G1 frame, true arm), and metric distributions side by side."""
    written: list[Path] = []
    kinds = list(dict.fromkeys(table["kind"]))
    ctrls = list(dict.fromkeys(table["controller"]))
    fig = Figure(figsize=(4 * len(ctrls), 3.4 * len(kinds)), layout="constrained")
    for i, kind in enumerate(kinds):
        for j, ctrl in enumerate(ctrls):
            ax = fig.add_subplot(len(kinds), len(ctrls), i * len(ctrls) + j + 1)
            g = table[(table["kind"] == kind) & (table["controller"] == ctrl) & (table["arm"] == table["arm"].iloc[0])]
            for n, (_, r) in enumerate(g.head(6).iterrows()):
                h = 1e3 * np.asarray(r["handle_trace"]).reshape(-1, 3)
                gr = 1e3 * np.asarray(r["gripper_trace"]).reshape(-1, 3)
                ax.plot(h[:, 0], h[:, 1], lw=1.2, color=f"C{n}")
                ax.plot(gr[:, 0], gr[:, 1], lw=0.6, ls="--", color=f"C{n}")
            ax.set_title(f"{kind}: {ctrl} (arm {table['arm'].iloc[0]})", fontsize=9)
            ax.set_xlabel("x_G1 [mm] (u0 direction)")
            ax.set_ylabel("y_G1 [mm]")
            ax.set_aspect("equal", adjustable="datalim")
    fig.suptitle("handle (solid) and gripper (dashed) paths, first objects", fontsize=9)
    written += save_figure(fig, out_dir, "articulated_trajectories")

    written += save_figure(metrics_figure(table), out_dir, "articulated_metrics")
    if len({(r["grasp_k"], r["resistance"]) for r in summary.get("plane", [])}) > 1:
        written += save_figure(plane_figure(summary), out_dir, "articulated_plane")
    return written


def metrics_figure(table: pd.DataFrame):
    """Success rate and each metric's distribution (successful rollouts, both arms) per kind x controller.

    One panel per quantity on a grid of four columns; tick labels ``kind/controller`` vertical, each panel wide
    enough for its labels (no two overlap)."""
    kinds = list(dict.fromkeys(table["kind"]))
    ctrls = list(dict.fromkeys(table["controller"]))
    labels = [(k, c) for k in kinds for c in ctrls]
    names = ("success_rate",) + METRICS
    cols = 4
    rows = -(-len(names) // cols)
    width = max(3.2, 0.16 * len(labels) + 0.9)
    fig = Figure(figsize=(cols * width, rows * 3.4), layout="constrained")
    for m_i, m in enumerate(names):
        ax = fig.add_subplot(rows, cols, m_i + 1)
        if m == "success_rate":
            rate = [100 * table[(table["kind"] == k) & (table["controller"] == c)]["success"].mean()
                    for k, c in labels]
            ax.bar(range(len(labels)), rate, color=[f"C{ctrls.index(c)}" for _, c in labels])
            ax.set_ylim(0, 105)
            ax.set_title("success rate [%]", fontsize=9)
        else:
            data = [table[(table["kind"] == k) & (table["controller"] == c) & table["success"]][m].dropna()
                    .to_numpy() for k, c in labels]
            pos = [i for i, d in enumerate(data) if len(d)]
            if pos:
                ax.boxplot([data[i] for i in pos], positions=pos)
            log = m in ("time_s", "jerk", "jerk_tw") and pos and min(float(np.min(data[i])) for i in pos) > 0
            if log:
                ax.set_yscale("log")
            ax.set_title(m + (" (log)" if log else ""), fontsize=9)
        ax.set_xticks(range(len(labels)), [f"{k[:5]}/{c}" for k, c in labels], fontsize=6, rotation=90)
        ax.set_xlim(-0.6, len(labels) - 0.4)
    fig.suptitle("articulated objects: success (all rollouts) and metrics (successful rollouts, both arms)",
                 fontsize=9)
    return fig


def plane_figure(summary: dict):
    """Success rate and mean time per controller over the grasp-stiffness x resistance plane (``summary["plane"]``).

    Rows: success [%] and mean time to success [s] (blank where nothing succeeded); columns: controllers; cells:
    stiffness ``grasp_k`` [N/m] (x) by resistance scale (y), each annotated with its value."""
    plane = summary["plane"]
    ctrls = list(dict.fromkeys(r["controller"] for r in plane))
    ks = sorted({r["grasp_k"] for r in plane})
    rs = sorted({r["resistance"] for r in plane})
    fig = Figure(figsize=(3.3 * len(ctrls), 5.8), layout="constrained")
    for j, c in enumerate(ctrls):
        succ = np.full((len(rs), len(ks)), np.nan)
        time = np.full((len(rs), len(ks)), np.nan)
        for r in plane:
            if r["controller"] == c:
                a, b = rs.index(r["resistance"]), ks.index(r["grasp_k"])
                succ[a, b] = 100 * r["success_rate"]
                t = r["time_s"]["mean"]
                time[a, b] = np.nan if t is None else t
        for i, (grid, name, cmap, lim) in enumerate(((succ, "success [%]", "RdYlGn", (0, 100)),
                                                      (time, "mean time [s]", "viridis", None))):
            ax = fig.add_subplot(2, len(ctrls), i * len(ctrls) + j + 1)
            im = ax.imshow(grid, origin="lower", cmap=cmap, aspect="auto", vmin=lim[0] if lim else None,
                           vmax=lim[1] if lim else None)
            for a in range(len(rs)):
                for b in range(len(ks)):
                    v = grid[a, b]
                    ax.text(b, a, "-" if np.isnan(v) else f"{v:.0f}" if i == 0 else f"{v:.1f}", ha="center",
                            va="center", fontsize=8)
            ax.set_xticks(range(len(ks)), [f"{k:.2g}" for k in ks], fontsize=7)
            ax.set_yticks(range(len(rs)), [f"{r:g}" for r in rs], fontsize=7)
            ax.set_xlabel("grasp stiffness k [N/m]", fontsize=8)
            ax.set_ylabel("resistance scale", fontsize=8)
            ax.set_title(f"{c}: {name}", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle("spring grasp: stiffness x object resistance (all kinds, all arms)", fontsize=9)
    return fig
