"""Demo figure: per run, the estimate against the truth, the traced stars and the convergence, from saved results.

An arm with more actuators than task axes (the UR5e's 6 on x, y, z) has many
right inverses of ``J``; the estimate need not be ``J^+``, only ``J Ĵ = I``,
so its panels show ``J Ĵ`` and ``J Ĵ - I``; a square system's show the
estimated and the true ``J^+``.

:func:`plot` is the ``demo`` experiment's ``plot`` (:mod:`selfid_jax.experiments.demo`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from selfid_jax.runner.figures import matrix_panel, right_inverse_panels, save_figure

__all__ = ["convergence_thresholds", "plot"]


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """``demo``: per run (a row each) estimated vs true inverse Jacobian (config 0), the traced stars, convergence.

    The convergence panel draws ``||J_t - J_{t-1}||_F`` per self-ID iteration
    and, per start configuration in its colour, the Sec. IV-D threshold
    ``eps + eps_rel ||J_est||_F`` (``J_est`` the configuration's final
    estimate, which the running ``||J_t||_F`` of the test approaches), so a
    relative threshold (the Model O's) has its line too.
    """
    runs = summary["runs"]
    fig = Figure(figsize=(17, 4.3 * len(runs)), layout="constrained")
    rows = fig.subplots(len(runs), 4, squeeze=False, width_ratios=(1, 1, 1.25, 1.25))
    for axes, (name, r) in zip(rows, runs.items()):
        _plot_run(fig, axes, table[table["system"] == name], name, r)
    return save_figure(fig, out_dir, "demo", dpi=110)


def convergence_thresholds(g: pd.DataFrame, r: dict) -> np.ndarray:
    """``(n_configs,)`` Sec. IV-D threshold ``eps + eps_rel ||J_est||_F`` of each row of ``g`` (its final estimate)."""
    s = r["self_id"]
    norms = np.array([np.linalg.norm(np.asarray(e, float)) for e in g["estimate"]])
    return float(s["eps"]) + float(s.get("eps_rel", 0.0)) * norms


def _plot_run(fig, axes, g: pd.DataFrame, name: str, r: dict) -> None:
    n_act, m = r["n_act"], r["task_dim"]
    est0 = np.asarray(g["estimate"].iloc[0]).reshape(n_act, m)
    true0 = np.asarray(g["truth"].iloc[0]).reshape(n_act, m)
    axis_names = ["x", "y", "z", "rx", "ry", "rz"][:m]
    if n_act > m:  # redundant: right inverses differ in the null space, so compare J Ĵ with the identity
        J = np.linalg.pinv(true0)  # (m, n): the truth is J's pseudo-inverse
        im = right_inverse_panels(axes[:2], J, est0, axis_names, f"{name}, config 0: ")
        label = "task unit per task unit"
    else:
        joints = [f"q{i + 1}" for i in range(n_act)]
        vmax = float(np.abs(true0).max())
        im = matrix_panel(axes[0], est0, f"{name}: estimated $J^+$, config 0", axis_names, joints, vmax)
        matrix_panel(axes[1], true0, f"{name}: true $J^+$, config 0", axis_names, joints, vmax)
        label = "actuator unit per task unit"
    fig.colorbar(im, ax=list(axes[:2]), shrink=0.8, label=label)
    ax = axes[2]
    for b in range(len(g)):
        p_true = np.asarray(g["positions_true"].iloc[b]).reshape(-1, 3)
        p_est = np.asarray(g["positions_estimated"].iloc[b]).reshape(-1, 3)
        p_true, p_est = p_true - p_true[0], p_est - p_est[0]
        ax.plot(1e3 * p_true[:, 0], 1e3 * p_true[:, 1], color="0.6", lw=3, label="true inverse" if b == 0 else None)
        ax.plot(1e3 * p_est[:, 0], 1e3 * p_est[:, 1], lw=1, color=f"C{b % 10}", label=f"estimate, config {b}")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_title(f"{name}: star traced by the point of manipulation", fontsize=10)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    ax = axes[3]
    s = r["self_id"]
    thresholds = convergence_thresholds(g, r)
    for b in range(len(g)):
        d = np.asarray(g["deltas"].iloc[b])
        ax.semilogy(np.arange(1, len(d) + 1)[d > 0], d[d > 0], marker=".", color=f"C{b % 10}", label=f"config {b}")
    rule = f"threshold {s['eps']:g}" if s.get("eps_rel", 0) == 0 else (
        "threshold " + (f"{s['eps']:g} + " if s["eps"] > 0 else "") + f"{s['eps_rel']:g}" + r"$\,\|J_{est}\|_F$")
    if np.allclose(thresholds, thresholds[0], rtol=1e-12, atol=0):  # an absolute test: one line for all
        ax.axhline(thresholds[0], color="k", ls=":", lw=1, gid="threshold:all", label=rule)
    else:  # relative: each configuration's own, in its colour
        for b, thr in enumerate(thresholds):
            ax.axhline(thr, color=f"C{b % 10}", ls=":", lw=1, gid=f"threshold:{b}")
        ax.plot([], [], color="k", ls=":", lw=1, label=rule + " (per config)")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("self-ID iteration")
    ax.set_ylabel(r"$\|J_t - J_{t-1}\|_F$")
    ax.set_title(f"{name}: convergence (Sec. IV-D)", fontsize=10)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
