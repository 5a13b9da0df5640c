"""Write the shipped example log ``selfid_jax/robot/data/ur5e_example_log.csv`` (``selfid-jax fit --example``).

A simulated UR5e (:func:`selfid_jax.systems.ur5e`) at :data:`UR5E_HOME` makes
random actuations ``dtheta ~ uniform(-m_a, m_a)`` (the system's ``m_a``),
one every 0.1 s; a tracker reads the flange pose with 0.1 mm position noise
and 0.1 mrad rotation noise. The raw time series (``t``, ``q_0..q_5``,
``p_x, p_y, p_z``, ``q_w, q_x, q_y, q_z``) has 64 rows, with three bad ones on
purpose: a NaN position, a row logged twice (duplicated timestamp), and a
tracker dropout of 1 s during which the robot made three unrecorded moves (a gap).

    python scripts/make_example_log.py [--out PATH] [--seed 0]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np

import selfid_jax  # noqa: F401  (XLA flags before JAX starts)
from selfid_jax.math import geometry
from selfid_jax.systems.ur5e import UR5E_HOME, ur5e

OUT = Path(__file__).resolve().parents[1] / "selfid_jax" / "robot" / "data" / "ur5e_example_log.csv"
POS_NOISE = 1e-4  # m
ROT_NOISE = 1e-4  # rad
DT = 0.1  # s
MOVES = 64


def make(seed: int = 0) -> list[list[float]]:
    """Rows ``[t, q_0..q_5, p_x, p_y, p_z, q_w, q_x, q_y, q_z]`` of the log, bad rows included."""
    jax.config.update("jax_enable_x64", True)
    system = ur5e(task_dim=6)
    rng = np.random.default_rng(seed)
    m_a = np.broadcast_to(np.asarray(system.m_a, np.float64), (system.n_act,))
    q = np.asarray(UR5E_HOME, np.float64)
    rows, t = [], 0.0
    for k in range(MOVES):
        p, R = system.pose(q)
        p = np.asarray(p) + POS_NOISE * rng.normal(size=3)
        R = np.asarray(geometry.so3_exp(ROT_NOISE * rng.normal(size=3))) @ np.asarray(R)
        wxyz = np.asarray(geometry.rotation_to_quaternion(R))
        wxyz = wxyz if wxyz[0] >= 0 else -wxyz
        rows.append([t, *q, *p, *wxyz])
        moves = 4 if k == 40 else 1  # the dropout: three moves happen while the tracker is lost
        for _ in range(moves):
            q = np.asarray(system.apply(q, rng.uniform(-1.0, 1.0, system.n_act) * m_a))
        t = round(t + (1.0 if k == 40 else DT), 6)
    rows[20][8] = float("nan")  # a tracker glitch: NaN position
    rows.insert(31, list(rows[30]))  # a row logged twice: duplicated timestamp
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    header = ["t", *(f"q_{i}" for i in range(6)), "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z"]
    lines = [",".join(header)]
    for r in make(args.seed):
        lines.append(",".join(f"{v:.6f}" if i == 0 else ("nan" if np.isnan(v) else f"{v:.10g}")
                              for i, v in enumerate(r)))
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out} ({len(lines) - 1} rows)")


if __name__ == "__main__":
    main()
