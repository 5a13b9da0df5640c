"""Tracking figures (Fig. 6-9 style): executed and commanded paths, per-step error traces, from saved results.

:func:`plot` is the ``tracking`` experiment's ``plot``
(:mod:`selfid_jax.experiments.tracking`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from selfid_jax.control import paths
from selfid_jax.runner.figures import save_figure

from ..common import realism as realistic
from ..common.schema import format_m_a
from ..tracking import INVERSES, TrackingPath

__all__ = ["commanded_paths", "plot", "tracked_position_axes"]



def commanded_paths(path: dict) -> list[np.ndarray]:
    """The commanded position path of each of the ``L`` paths of a saved ``summary["path"]``.

    Returns:
      ``L`` arrays ``(W + 1, 3)`` [mm]: the start (the origin) then the
      waypoints' position offsets, as :meth:`TrackingPath.waypoints` commands
      them (a rotation path's are all zero).
    """
    spec = TrackingPath(**path)
    return [1e3 * np.concatenate([np.zeros((1, 3)), np.asarray(w, float)[:, :3]]) for w in spec._paths()]


def tracked_position_axes(table: pd.DataFrame, task_axes: list[str] | None) -> list[int]:
    """The position components (0, 1, 2 for x, y, z) the task controls, whose error traces mean something.

    From ``task_axes`` when the config named them; otherwise the components
    whose ``error_trace_mm`` is not zero at every step of every row (the
    simulation writes exactly 0 for a component outside the task).
    """
    if task_axes is not None:
        return [j for j, a in enumerate("xyz") if a in task_axes]
    err = np.concatenate([np.asarray(e, float).reshape(-1, 3) for e in table["error_trace_mm"]])
    return [j for j in range(3) if np.any(err[:, j] != 0)]


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """Executed and commanded paths and per-step error traces, estimated vs analytical (Fig. 6-9 style).

    One figure per system, ``tracking_<system>.png|pdf``, from the noise-free
    rows of the first start configuration (with a realism section one per
    system and realism level, ``tracking_<system>_realism<level>``, the
    level's values in the title). Top row: the executed paths [mm] relative to
    where each path started, in the path's plane (3-D for a cube), under the
    commanded path (black, dashed); letters are placed side by side on a
    baseline, each shifted by the same amount as its commanded path (each
    letter starts from where its own self-ID ended). For
    a rotation path: the orientation error along each rotation [deg]. Bottom
    row: the per-step distance to the path [mm] along the position components
    the task controls (:func:`tracked_position_axes`; untracked ones are not
    drawn) and, where the task has rotation, the orientation error [deg], the
    paths (letters) one after another, each labelled where it begins. The protocol is in the title.
    """
    written: list[Path] = []
    kind = summary["path"]["kind"]
    three_d = kind == "cube"
    h_ax, v_ax = paths.PLANES[summary["path"].get("plane", "xy")]
    commanded = commanded_paths(summary["path"])
    shifts = _letter_shifts(summary["path"], len(commanded))
    rotates = "rot_trace_deg" in table and bool(np.any(np.concatenate(table["rot_trace_deg"].to_list()) != 0))
    labels = realistic.level_labels(table)
    for (system, level), g in table.groupby(["system", realistic.level_of(table)], sort=False):
        first = g[(g["noise_level"] == 0) & (g["config_id"] == 0) & (g["trial"] == 0)]
        tracked = tracked_position_axes(g, summary.get("task_axes")) if "error_trace_mm" in g else []
        fig = Figure(figsize=(max(10.0, 3.0 + 1.3 * len(commanded)) if kind == "letters" else 10.0, 8),
                     layout="constrained")
        for k, inverse in enumerate(INVERSES):
            rows = first[first["inverse"] == inverse].sort_values("letter_id")  # one row per letter / rotation
            color = "C0" if inverse == "estimated" else "C2"
            ax = fig.add_subplot(2, 2, k + 1, projection="3d" if three_d else None)
            if kind == "rotation":
                for _, row in rows.iterrows():
                    used = int(row["steps_used"]) + 1
                    ax.plot(np.asarray(row["rot_trace_deg"])[:used], lw=1, label=str(row["path"]))
                ax.set_xlabel("control step")
                ax.set_ylabel("orientation error to the pursued waypoint [deg]")
                ax.legend(fontsize=7)
            else:
                for _, row in rows.iterrows():
                    used = int(row["steps_used"]) + 1
                    pts = 1e3 * np.asarray(row["positions"]).reshape(-1, 3)[:used]
                    pts = pts - pts[0]
                    i = int(row["letter_id"])
                    pts[:, [h_ax, v_ax]] += shifts[i] if i < len(shifts) else 0.0
                    _draw(ax, pts, three_d, h_ax, v_ax, color=color, lw=1.2, gid=f"executed:{i}",
                          label="executed" if i == 0 else None)
                for i, cmd in enumerate(commanded):  # on top, thin and dashed: visible where tracking is exact
                    c = cmd.copy()
                    c[:, [h_ax, v_ax]] += shifts[i]
                    _draw(ax, c, three_d, h_ax, v_ax, color="k", alpha=0.7, ls="--", lw=0.8, gid=f"commanded:{i}",
                          label="commanded" if i == 0 else None)
                ax.legend(fontsize=7, loc="best")
                if three_d:
                    ax.set_xlabel("x [mm]")
                    ax.set_ylabel("y [mm]")
                    cast(Any, ax).set_zlabel("z [mm]")  # a 3-D Axes; mpl_toolkits.mplot3d ships no types
                    ax.set_aspect("equal")
                else:
                    ax.set_aspect("equal", adjustable="datalim")
                    ax.set_xlabel(f"{'xyz'[h_ax]} [mm]" + (" (letters side by side)" if len(commanded) > 1 else ""))
                    ax.set_ylabel(f"{'xyz'[v_ax]} [mm]")
            ax.set_title(f"{system}: {inverse} inverse Jacobian", fontsize=9)
            tr = fig.add_subplot(2, 2, k + 3)
            if "error_trace_mm" not in rows:  # a run directory written before the traces were recorded
                tr.set_axis_off()
                continue
            traces = [np.asarray(r["error_trace_mm"]).reshape(-1, 3)[: int(r["steps_used"]) + 1]
                      for _, r in rows.iterrows()]
            err = np.concatenate(traces) if traces else np.zeros((0, 3))
            for j in tracked:
                tr.plot(err[:, j], lw=0.8, color=f"C{j}", label=f"|e_{'xyz'[j]}|", gid=f"error:{'xyz'[j]}")
            if len(traces) > 1:  # where each path (letter, rotation) begins, labelled at the top
                starts = np.cumsum([0] + [len(t) for t in traces[:-1]])
                for x0 in starts:
                    tr.axvline(x0, color="0.7", lw=0.6, ls=":")
                top = tr.secondary_xaxis("top")
                top.set_xticks(starts, [f"{r['path']}" for _, r in rows.iterrows()], fontsize=7, ha="left")
                top.tick_params(length=0, pad=1)
            tr.set_xlabel("control step" + (" (paths one after another)" if len(traces) > 1 else ""))
            tr.set_ylabel("distance to the path [mm]")
            if rotates:
                rot = np.concatenate([np.asarray(r["rot_trace_deg"])[: int(r["steps_used"]) + 1]
                                      for _, r in rows.iterrows()])
                tw = tr.twinx()
                tw.plot(rot, lw=0.8, color="k", alpha=0.6, label="rotation")
                tw.set_ylabel("orientation error [deg]")
                tw.legend(fontsize=7, loc="upper right")
            if tracked:
                tr.legend(fontsize=7, loc="upper left")
            untracked = [a for j, a in enumerate("xyz") if j not in tracked]
            tr.set_title(f"per-step error, {inverse}" + (f" ({', '.join(untracked)} not in the task)"
                                                         if untracked else ""), fontsize=9)
        c, s = summary["controller"], summary["self_id"]
        axes = summary.get("task_axes")
        fig.suptitle(f"path {kind}{'' if axes is None else f', task {axes}'}; step {1e3 * c['max_step']:g} mm "
                     f"({c['max_rot_step']:g} rad), tol {1e3 * c['tol']:g} mm ({c['rot_tol']:g} rad), "
                     f"{c['steps']} steps, gain {c['gain']:g};\nself-ID m_a {format_m_a(s['m_a'])}, "
                     f"eps {s['eps']:g}, eps_rel {s['eps_rel']:g}; noise-free rows, first configuration"
                     + (f"\nrealism: {labels[int(level)]}" if labels else ""), fontsize=8)
        written += save_figure(fig, out_dir, f"tracking_{system}" + (f"_realism{int(level)}" if labels else ""))
    return written


def _letter_shifts(path: dict, n: int) -> np.ndarray:
    """``(n, 2)`` shift [mm] along the plane's (horizontal, vertical) axes of each of the ``n`` paths.

    For letters (kind ``letters``): each letter's box (``paths.text_box``)
    is moved so that its lower-left corner sits on the baseline, right of the
    letter before with a gap of 0.4 letter heights, so the letters read as a
    word; each path starts at its own first stroke point, so without the shift
    they would all be drawn on top of each other. Other kinds: zeros.
    """
    shifts = np.zeros((n, 2))
    if path["kind"] != "letters":
        return shifts
    height = float(path["height"])
    left = 0.0
    for i, char in enumerate(path["text"]):
        box = paths.text_box(char, height=height)
        shifts[i] = 1e3 * (np.array([left, 0.0]) - np.asarray(box.origin, float))
        left += box.width + 0.4 * height
    return shifts


def _draw(ax, pts: np.ndarray, three_d: bool, h_ax: int, v_ax: int, **kw) -> None:
    """``pts`` (N, 3) [mm]: a 3-D line, or its (h_ax, v_ax) components on a 2-D axes."""
    if three_d:
        ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], **kw)
    else:
        ax.plot(pts[:, h_ax], pts[:, v_ax], **kw)
