"""Peg-in-hole figure (Table III as bars per layout), from saved results.

:func:`plot` is the ``peg_in_hole`` experiment's ``plot``
(:mod:`selfid_jax.experiments.peg_in_hole`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from selfid_jax.runner.figures import save_figure

from ..common.schema import format_m_a
from ..peg_in_hole import INVERSES, TABLE

__all__ = ["plot"]


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """Table III as bars per layout (estimated vs analytical, noise-free rows; with a realism section those of its
    first level), protocol in the title."""
    clean = table[(table["noise_level"] == 0) & (table["realism_level"] == 0 if "realism_level" in table else True)]
    fig = Figure(figsize=(11, 3.6), layout="constrained")
    labels = {"arm_pos_mm": "UR5e position error [mm]", "arm_rot_deg": "UR5e rotation error [deg]",
              "hand_rot_deg": "Model O rotation error [deg]"}
    for k, col in enumerate(TABLE):
        ax = fig.add_subplot(1, 3, k + 1)
        for j, inverse in enumerate(INVERSES):
            g = clean[(clean["inverse"] == inverse) & ~clean["failed"]].groupby("layout")[col]
            mean, sd = g.mean(), g.std(ddof=0).fillna(0.0)
            ax.bar(mean.index + (j - 0.5) * 0.38, mean.to_numpy(), 0.38, yerr=sd.to_numpy(), label=inverse,
                   color="C0" if inverse == "estimated" else "C2")
        layouts = np.sort(clean["layout"].unique())
        ax.set_xticks(layouts, [f"{int(v)}" for v in layouts])  # one tick per layout, not a continuous axis
        ax.set_xlabel("layout")
        ax.set_ylabel(labels[col])
        ax.legend(fontsize=7)
    pr = summary["protocol"]
    fig.suptitle(f"peg-in-hole, UR5e + Model O; arm m_a {format_m_a(pr['arm']['m_a'])} rad, eps {pr['arm']['eps']:g}, "
                 f"step {1e3 * pr['arm']['controller']['max_step']:g} mm, tol {1e3 * pr['arm']['controller']['tol']:g}"
                 f" mm; hand m_a {format_m_a(pr['hand']['m_a'])} m, eps_rel {pr['hand']['eps_rel']:g}, tilt "
                 f"{pr['rotation']['angle']:g} rad about {pr['rotation']['about']}; noise-free rows", fontsize=8)
    return save_figure(fig, out_dir, "peg_in_hole")
