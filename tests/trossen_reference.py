"""An independent reference for sessions on trossen-arm-sim's WidowX AI: MuJoCo's Jacobian from the simulator's own
model, and the simulator started and ended as a subprocess (the command, or its controller with faults on request).

Used by ``tests/test_trossen.py`` and ``benchmarks/trossen_sim.py``. The point
is the simulator's ``ee_site`` (0.156 m out along link 6's x axis), where the
driver's ``wxai_v0_follower`` end effector puts its tool frame; the driver's
pose and Jacobian come from the controller's own kinematic parameters, the
reference from the MJCF the simulator integrates.
"""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import helpers_vendor_sim as vendor_sim
import numpy as np

PORT = 50001  # the arm controller's TCP port (its UDP port is 50000); neither can be chosen


@functools.cache
def _model():
    import mujoco
    from trossen_arm_sim.sim import DEFAULT_SCENE, load_scene
    return mujoco, load_scene(DEFAULT_SCENE)


def ee_point(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's forward kinematics of the simulator's scene at arm joints ``q (6,)`` [rad]: ``ee_site``'s position
    (3,) [m] and rotation (3, 3), world frame."""
    mujoco, model = _model()
    data = mujoco.MjData(model)
    data.qpos[:6] = q
    mujoco.mj_kinematics(model, data)
    site = model.site("ee_site").id
    return data.site_xpos[site].copy(), data.site_xmat[site].reshape(3, 3).copy()


def ee_jacobian(q: np.ndarray, axes) -> np.ndarray:
    """``J (m, 6)``: MuJoCo's Jacobian (``mj_jacSite``) of ``ee_site``'s velocity [m/rad] and angular velocity
    [rad/rad], world frame, rows ``axes`` of (x, y, z, rx, ry, rz), at arm joints ``q (6,)``."""
    mujoco, model = _model()
    data = mujoco.MjData(model)
    data.qpos[:6] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    mujoco.mj_jacSite(model, data, jacp, jacr, model.site("ee_site").id)
    return np.vstack([jacp, jacr])[:, :6][list(axes)]


def session_error(run_dir: Path) -> tuple[float, np.ndarray]:
    """``(||J Ĵ - I||_F, q0 (6,))`` of a run directory's estimate against MuJoCo's Jacobian at the session's first
    joint reading."""
    return vendor_sim.session_error(run_dir, ee_jacobian)


def port_open(port: int = PORT) -> bool:
    return vendor_sim.port_open(port)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def trossen_sim(log: Path, timeout_s: float = 30.0) -> Iterator[subprocess.Popen]:
    """``trossen-arm-sim --host 127.0.0.1`` (its collision stream on a free port) for the block, ended by its PID
    (and its process group) after; RuntimeError if the controller's port is taken before it starts or does not
    open within ``timeout_s``."""
    command = ["trossen-arm-sim", "--host", "127.0.0.1", "--ws-port", str(free_port())]
    with vendor_sim.simulator(command, PORT, log, timeout_s) as proc:
        yield proc


def kill(proc: subprocess.Popen) -> None:
    """End the simulator by its PID's process group (SIGKILL: what a power cut looks like to the arm's driver)."""
    vendor_sim.kill(proc, PORT)


def _serve_controller(conn, driver_version: str | None) -> None:
    """The simulator's MuJoCo arm and controller server in this (child) process; puts the controller in the error
    state named by each message (``ErrorState``'s name) until the message ``stop``."""
    from trossen_arm_sim.protocol import ErrorState
    from trossen_arm_sim.server import TrossenArmSimServer
    from trossen_arm_sim.sim import WidowXSim

    sim = WidowXSim()
    sim.start()
    server = TrossenArmSimServer(sim, host="127.0.0.1", **({"driver_version": driver_version} if driver_version
                                                           else {}))
    server.start()
    conn.send("ready")
    while (message := conn.recv()) != "stop":
        server.fault(ErrorState[message], f"injected by the test: {message}")
        conn.send("ok")


@contextlib.contextmanager
def controller(driver_version: str | None = None, timeout_s: float = 30.0) -> Iterator[Callable[[str], None]]:
    """trossen-arm-sim's controller (``driver_version``: the firmware it reports, default the installed
    trossen-arm's) in a child process for the block, which gets ``fault(name)``: the controller enters the error
    state ``name`` (e.g. ``JOINT_LIMIT_EXCEEDED``), as a hardware fault would put it. A process, not threads of this
    one: its sockets close when it is killed (the server's own stop leaves its threads blocked on them)."""
    if port_open():
        raise RuntimeError(f"127.0.0.1:{PORT} is already in use: another trossen-arm-sim or arm controller is running")
    ctx = multiprocessing.get_context("spawn")  # no fork of a process that runs JAX's threads
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_serve_controller, args=(child, driver_version), daemon=True)
    proc.start()

    def fault(name: str) -> None:
        parent.send(name)
        parent.recv()

    try:
        if not parent.poll(timeout_s) or parent.recv() != "ready":
            raise RuntimeError(f"the simulated controller did not start within {timeout_s:g} s")
        yield fault
    finally:
        proc.kill()
        proc.join(10)
        deadline = time.monotonic() + 10
        while port_open() and time.monotonic() < deadline:
            time.sleep(0.05)
