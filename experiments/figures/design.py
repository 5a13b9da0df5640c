"""Self-ID design figures: the loss against m_a per noise level with the gradient paths, and the optimum against
noise, from saved results.

:func:`plot` is the ``design`` experiment's ``plot`` (:mod:`selfid_jax.experiments.design`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from selfid_jax.runner.figures import save_figure

from ..design import best_point

__all__ = ["plot"]


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """``design_curves``: grid loss vs m_a per noise level with the gradient paths; ``design_optimum``: optimum vs
    noise.

    Curves: one panel per system; each noise level's grid (line; crosses where
    the gradient is flagged unreliable), the scalar gradient path (dots, from
    the grid's best), its optimum (star) and the per-actuator optimum's loss
    at its geometric-mean magnitude (diamond). Optimum: the refined scalar
    ``m_a`` (line), the grid's best (dashed) and each actuator's magnitude of
    the per-actuator design (markers) against the tracker's position noise.
    Reads the saved table only.
    """
    names = list(dict.fromkeys(table["system"]))
    written: list[Path] = []
    fig = Figure(figsize=(4.6 * len(names), 4.0), layout="constrained")
    axes = fig.subplots(1, len(names), squeeze=False)[0]
    for ax, name in zip(axes, names):
        t = table[table["system"] == name]
        for k, (_level, g) in enumerate(t.groupby("noise_level", sort=True)):
            color = f"C{k}"
            grid = g[g["stage"] == "grid"].sort_values("index")
            level_noise = float(grid["pose_noise"].iloc[0])
            ax.plot(grid["m_a"], grid["loss"], "-", color=color, lw=1.2, label=f"noise {1e3 * level_noise:g} mm")
            bad = grid[~grid["reliable"]]
            ax.plot(bad["m_a"], bad["loss"], "x", color=color, ms=6)
            sc = g[g["stage"] == "scalar"].sort_values("index")
            ax.plot(sc["m_a"], sc["loss"], ".-", color=color, ms=3, lw=0.6, alpha=0.8)
            sb = best_point(sc)
            ax.plot([sb["m_a"]], [sb["loss"]], "*", color=color, ms=12, mec="k", mew=0.5)
            per = g[g["stage"] == "per_actuator"]
            if len(per):
                pb = best_point(per)
                ax.plot([pb["m_a"]], [pb["loss"]], "D", color=color, ms=6, mec="k", mew=0.5)
        ax.set_xscale("log")
        ax.set_xlabel("self-ID magnitude m_a [rad or m]")
        ax.set_ylabel("loss: mean log(MSE to the path) [log m^2]")
        ax.set_title(f"{name}: grid (x: gradient unreliable), gradient path, optimum (*), per actuator (D)", fontsize=7)
        ax.legend(fontsize=7)
    fig.suptitle(_protocol_line(summary), fontsize=7)
    written += save_figure(fig, out_dir, "design_curves")

    fig = Figure(figsize=(4.6 * len(names), 4.0), layout="constrained")
    axes = fig.subplots(1, len(names), squeeze=False)[0]
    for ax, name in zip(axes, names):
        levels = summary.get("systems", {}).get(name, {}).get("noise_levels", [])
        if not levels:
            ax.set_axis_off()
            continue
        noise = np.asarray([lv["pose_noise"] for lv in levels])
        zero = noise <= 0
        if zero.any():  # noise-free levels sit left of the rest on the log axis, their tick labelled 0
            nonzero = noise[~zero]
            noise = np.where(zero, (nonzero.min() if nonzero.size else 1e-3) / 4.0, noise)
        band = np.asarray([lv["m_a_within_10pct"] for lv in levels])
        ax.fill_between(noise, band[:, 0], band[:, 1], color="0.85", label="within 10% of the best error (grid)")
        ax.plot(noise, [lv["scalar_m_a"] for lv in levels], "o-", color="k", label="refined scalar m_a")
        ax.plot(noise, [lv["grid_best_m_a"] for lv in levels], "s--", color="0.5", mfc="none", label="grid best")
        if "per_actuator_m_a" in levels[0]:
            per = np.asarray([lv["per_actuator_m_a"] for lv in levels])
            for i in range(per.shape[1]):
                ax.plot(noise * (1.0 + 0.04 * (i - per.shape[1] / 2)), per[:, i], "^", ms=5, color=f"C{i}",
                        label=f"actuator {i + 1}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        if zero.any():
            ticks = sorted(set(noise.tolist()))
            ax.set_xticks(ticks, ["0" if t == noise[zero][0] else f"{t:g}" for t in ticks], fontsize=7)
        ax.set_xlabel("tracker position noise sd [m]")
        ax.set_ylabel("optimal self-ID magnitude m_a [rad or m]")
        ax.set_title(name, fontsize=9)
        ax.legend(fontsize=6)
    fig.suptitle(_protocol_line(summary), fontsize=7)
    written += save_figure(fig, out_dir, "design_optimum")
    return written


def _protocol_line(summary: dict) -> str:
    if "iters" not in summary:
        return ""
    r = summary["refine"]
    return (f"{summary['iters']} self-ID samples, {summary['n_configs']} starts x {summary['n_trials']} trials "
            f"(held out: x {summary['eval_trials']}); Adam {r['steps']} steps, lr {r['learning_rate']:g} in log m_a; "
            f"gradient unreliable above {r['max_failed']:g} failed; path from {summary['follow_from']}")
