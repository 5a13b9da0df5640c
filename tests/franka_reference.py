"""An independent reference for sessions on franky-sim's FR3: MuJoCo's Jacobian from the simulator's own model,
and the simulator started and ended as a subprocess.

Used by ``tests/test_franka.py`` and ``benchmarks/franka_sim.py``. The point is
franky's end effector ``O_T_EE``: link 7's origin plus ``FLANGE_Z + EE_Z`` along
link 7's z axis (the flange is 0.107 m out, franky's default end effector of
the Franka hand 0.1034 m further); :func:`fr3_point` lets a test check that
against the pose the arm reports.
"""

from __future__ import annotations

import contextlib
import functools
import subprocess
from collections.abc import Iterator
from pathlib import Path

import helpers_vendor_sim as vendor_sim
import numpy as np

FLANGE_Z = 0.107  # m, link 7 to the flange (fr3.xml's hand body, franky's O_T_F)
EE_Z = 0.1034  # m, the flange to franky's default end effector of the Franka hand (F_T_EE)
PORT = 1337  # libfranka's command port


@functools.cache
def _model():
    import franky_sim
    import mujoco
    assets = Path(franky_sim.__file__).parent / "assets"
    xml = (assets / "fr3.xml").read_text().replace('meshdir="assets"', f'meshdir="{assets / "meshes"}"')
    return mujoco, mujoco.MjModel.from_xml_string(xml)


def fr3_point(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's forward kinematics of fr3.xml at joints ``q (7,)`` [rad]: the end-effector point (3,) [m] and link
    7's rotation (3, 3), world frame."""
    mujoco, model = _model()
    data = mujoco.MjData(model)
    data.qpos[:7] = q
    mujoco.mj_kinematics(model, data)
    b = model.body("fr3_link7").id
    R = data.xmat[b].reshape(3, 3)
    return data.xpos[b] + R @ np.array([0.0, 0.0, FLANGE_Z + EE_Z]), R


def fr3_jacobian(q: np.ndarray, axes) -> np.ndarray:
    """``J (m, 7)``: MuJoCo's Jacobian (``mj_jac``) of the end-effector point's velocity [m/rad] and link 7's
    angular velocity [rad/rad], world frame, rows ``axes`` of (x, y, z, rx, ry, rz), at joints ``q (7,)``."""
    mujoco, model = _model()
    data = mujoco.MjData(model)
    data.qpos[:7] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    point, _ = fr3_point(q)
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    mujoco.mj_jac(model, data, jacp, jacr, point, model.body("fr3_link7").id)
    return np.vstack([jacp, jacr])[:, :7][list(axes)]


def session_error(run_dir: Path) -> tuple[float, np.ndarray]:
    """``(||J Ĵ - I||_F, q0 (7,))`` of a run directory's estimate against MuJoCo's Jacobian at the session's first
    joint reading."""
    return vendor_sim.session_error(run_dir, fr3_jacobian)


def port_open(port: int = PORT) -> bool:
    return vendor_sim.port_open(port)


@contextlib.contextmanager
def franky_sim(log: Path, timeout_s: float = 30.0) -> Iterator[subprocess.Popen]:
    """``franky-sim -s mujoco`` headless on 127.0.0.1:1337 for the block, ended by its PID (and its process
    group) after; RuntimeError if the port is taken before it starts or does not open within ``timeout_s``."""
    with vendor_sim.simulator(["franky-sim", "-s", "mujoco"], PORT, log, timeout_s) as proc:
        yield proc


def kill(proc: subprocess.Popen) -> None:
    """End the simulator by its PID's process group (SIGKILL: what a crash looks like to the arm's client)."""
    vendor_sim.kill(proc, PORT)
