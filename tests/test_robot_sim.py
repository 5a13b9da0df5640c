"""The virtual robot over TCP on localhost (`selfid-jax robot-sim` in a process of its own) driven by the online
runner end to end: self-ID, convergence, a star; and faults: tracker dropouts, a latency spike, a frozen tracker,
the simulator killed mid-run (the runner stops, its log is intact, resume continues). Where no process of its own
is needed (a check of what the client sees, a fault that no clock's timing decides, the fresh simulator a resumed
session finds), robot-sim's robot and server run in the test's process (:func:`_sim_here`): a process start takes
about 4 s."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import textwrap
import threading
import time
from pathlib import Path

import mujoco
import numpy as np
import pytest

from selfid_jax.robot import live, options
from selfid_jax.robot.journal import read_journal
from selfid_jax.robot.protocol import RobotConnectionError, RobotError
from selfid_jax.robot.transport import RemoteRobot, RobotServer

# subprocesses with JAX and a real-time clock: one worker runs them and the Franka simulator's test (a full core of
# its own) one after the other, so that neither starves the other's clock into a stale stop
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("realtime")]

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "robot"
UR5E_XML = Path(__file__).resolve().parents[1] / "selfid_jax" / "systems" / "assets" / "ur5e.xml"


class Sim:
    """``selfid-jax robot-sim CONFIG --port 0`` in a subprocess, started at once; ``port`` waits until it listens
    (so a test starts every simulator it needs side by side: each process's start, about 4 s of importing JAX and
    building the system, overlaps the others' instead of adding to them)."""

    def __init__(self, console, tmp_path: Path, text: str, name: str = "sim"):
        self.cfg = tmp_path / f"{name}.yaml"
        self.cfg.write_text(textwrap.dedent(text))
        self._port_file = tmp_path / f"{name}.port"
        self._port: int | None = None
        self.proc = subprocess.Popen([*console, "robot-sim", str(self.cfg), "--port", "0", "--port-file",
                                      str(self._port_file)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True)

    @property
    def port(self) -> int:
        if self._port is None:
            deadline = time.monotonic() + 120
            while not self._port_file.exists():
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(f"robot-sim did not start: {self.proc.communicate(timeout=5)[0]}")
                time.sleep(0.05)
            self._port = int(self._port_file.read_text())
        return self._port

    def stop(self) -> str:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        return self.proc.communicate(timeout=30)[0]


@pytest.fixture
def sims(console, tmp_path):
    started: list[Sim] = []

    def start(text, name="sim"):
        started.append(Sim(console, tmp_path, text, name))
        return started[-1]

    yield start
    for s in started:
        if s.proc.poll() is None:
            s.proc.kill()
            s.proc.communicate(timeout=30)


UR5E = """\
    system: ur5e
    max_step: 0.05
    realism: {period: 0.01, latency: 2, noise_pos: 0.0, dropout: 0.0, servo_tau: 0.02}
    seed: 0
    """


def _mujoco_site(q) -> np.ndarray:
    """MuJoCo's own position of the UR5e's flange site at joint positions ``q``."""
    model = mujoco.MjModel.from_xml_path(str(UR5E_XML))
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    return data.site("ee").xpos.copy()


@contextlib.contextmanager
def _sim_here(tmp_path: Path, text: str, name: str):
    """robot-sim's robot and server in this process (``online_sim.listen``, what the command serves), on a free
    port for the block: for faults that no clock's timing decides, without a process start (about 4 s each)."""
    from selfid_jax.sessions import online_sim

    cfg = tmp_path / f"{name}.yaml"
    cfg.write_text(textwrap.dedent(text))
    robot, server = online_sim.listen(online_sim.load_sim_config(cfg), 0)
    robot.start()
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield server.port
    finally:
        server.shutdown()  # the serving thread ends at its next poll (after a delayed reply's sleep)


def test_client_sees_the_model_pose_servo_lag_latency_and_refused_moves(tmp_path):
    """Over TCP from robot-sim's robot and server (in this process; the end-to-end test below runs the command):
    MuJoCo's pose of the joints read, the tracker's latency, the servo's first-order lag, refused moves."""
    with _sim_here(tmp_path, UR5E, "client") as port:
        _client_sees(RemoteRobot("127.0.0.1", port, timeout_s=10))


def _client_sees(robot: RemoteRobot) -> None:
    lim = robot.limits()
    o = robot.read()
    np.testing.assert_allclose(o.position, _mujoco_site(o.q), atol=1e-12)  # at rest: the pose of q itself
    assert o.valid and abs((o.t - o.tracker_t) - 0.02) < 1e-9  # two periods of latency
    target = o.q.copy()
    target[1] += 0.04
    robot.move(target)
    seen = []
    t_end = time.monotonic() + 0.6
    while time.monotonic() < t_end:
        seen.append(robot.read())
        time.sleep(0.003)
    gaps = np.array([abs(r.q[1] - target[1]) for r in seen])
    assert gaps[0] > 1e-3 and gaps[-1] < 1e-8  # servo lag: not there at once, there within 0.6 s (30 tau)
    k = np.array([r.t for r in seen])
    moving = (gaps > 1e-6) & (gaps < 0.035) & np.r_[True, np.diff(k) > 0]  # one reading per tick
    tau = -np.diff(k[moving]) / np.diff(np.log(gaps[moving]))  # first order: gap ~ exp(-t / tau)
    np.testing.assert_allclose(np.median(tau), 0.02, rtol=0.05)
    late = seen[len(seen) // 4]  # mid-motion: the tracker shows the pose of two ticks before
    assert abs(late.t - late.tracker_t - 0.02) < 1e-9
    with pytest.raises(RobotError, match="outside the limits"):
        robot.move(np.where(np.arange(6) == 0, lim.upper + 0.1, seen[-1].q))
    with pytest.raises(RobotError, match="more than max_step"):
        robot.move(seen[-1].q + 0.2)
    with pytest.raises(RobotError, match="7 entries"):
        robot.move(np.zeros(7))
    time.sleep(0.1)
    np.testing.assert_allclose(robot.read().q, seen[-1].q, atol=1e-12)  # refused moves moved nothing
    robot.close()
    robot.close()  # idempotent


def test_online_ur5e_and_model_o_self_identify_then_follow_a_star_with_no_random_move_after(sims, tmp_path,
                                                                                             console):
    """The shipped pair of configs, end to end through both commands (real processes, real sockets). Both
    simulators start at once and each session as soon as its simulator listens, so the two run side by side (a
    session waits on its simulator's clock most of the time). Each follows its star at gain 1 with twice the
    shipped step cap or more (ur5e 10 mm, model_o 0.5 mm a move instead of 5 and 0.2): the same waypoints in
    about half the moves (20 and 28 instead of 40 and 66)."""
    names = ("ur5e", "model_o")
    started = {name: sims((CONFIGS / f"robot_sim_{name}.yaml").read_text(), name) for name in names}
    faster = {"ur5e": "path.max_task_step=0.01", "model_o": "path.max_task_step=0.0005"}
    runs = {}
    for name in names:
        # stale_s 2 s: three processes on 2 loaded cores starved the simulator's clock past the shipped 0.5 s in 2
        # of 4 full runs (a stale stop, safe); the watchdog itself is tested in test_online and below
        runs[name] = subprocess.Popen([*console, "online", str(CONFIGS / f"online_{name}.yaml"), "--out",
                                       str(tmp_path / f"online_{name}"), "--set", f"robot.port={started[name].port}",
                                       "--set", "safety.stale_s=2.0", "--set", "path.gain=1.0", "--set",
                                       faster[name]], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for name in names:
        out = tmp_path / f"online_{name}"
        text = runs[name].communicate(timeout=300)[0]
        assert runs[name].returncode == 0, text
        summary = json.loads((out / "summary.json").read_text())
        assert summary["status"] == "completed" and summary["converged_at"] >= 2, summary
        records = read_journal(out / live.LOG_FILE).records
        at = next(i for i, r in enumerate(records) if r["e"] == "converged")
        assert all(r.get("phase") != "selfid" for r in records[at:] if r["e"] == "move")  # no random move after
        moves = [r for r in records if r["e"] == "move" and r["phase"] == "selfid"]
        rejected = sum(1 for r in records if r["e"] == "sample" and not r.get("accepted", True))
        assert len(moves) == summary["converged_at"] + rejected
        assert f"robot-sim: serving {name}" in started[name].stop()


def test_dropouts_are_rejected_and_a_latency_spike_or_a_frozen_tracker_stops_safely(sims, tmp_path):
    """A session through robot-sim (its own process: a real-time clock) that drops 30 % of the tracker's poses
    converges with the dropouts rejected; a latency spike (3 s late replies) is a lost connection and a tracker
    frozen from the start a stale stop before any sample, each against the simulator's robot and server in this
    process while the first simulator starts."""
    sim = sims("""\
        system: ur5e
        max_step: 0.05
        realism: {period: 0.01, latency: 1, noise_pos: 1.0e-5, dropout: 0.3, servo_tau: 0.01}
        seed: 1
        """, "dropouts")
    opts = options.OnlineOptions(m_a=0.03, eps_rel=0.05, max_samples=150, settle_s=0.08, stale_s=0.5)

    with _sim_here(tmp_path, """\
            system: ur5e
            max_step: 0.05
            realism: {period: 0.01}
            faults: {latency_spike: {at_s: 0.0, duration_s: 600.0, extra_s: 3.0}}
            """, "spike") as port, pytest.raises(RobotConnectionError, match="no reply"):
        RemoteRobot("127.0.0.1", port, timeout_s=1.0).read()

    with _sim_here(tmp_path, """\
            system: ur5e
            max_step: 0.05
            realism: {period: 0.01}
            faults: {freeze_tracker_at_s: 0.0}
            """, "frozen") as port:
        t0 = time.monotonic()
        res = live.run_online(RemoteRobot("127.0.0.1", port, timeout_s=5), opts._replace(stale_s=0.3),
                              tmp_path / "frozen")
    assert res.status == live.Stop.STALE and time.monotonic() - t0 < 30
    assert res.samples == 0

    res = live.run_online(RemoteRobot("127.0.0.1", sim.port, timeout_s=5), opts, tmp_path / "dropouts")
    assert res.status == live.Stop.CONVERGED and res.rejected.get("dropout", 0) >= 1
    assert res.moves == res.converged_at + sum(res.rejected.values())


def test_simulator_killed_mid_run_stops_cleanly_and_resume_continues(sims, tmp_path):
    """robot-sim's process killed (SIGKILL) after 4 samples: the session stops as a lost connection, its log
    intact; resume against a fresh simulator (robot-sim's robot and server in this process) replays the logged
    samples and continues to convergence."""
    text = """\
        system: ur5e
        max_step: 0.05
        realism: {period: 0.01, latency: 1, noise_pos: 1.0e-5, servo_tau: 0.01}
        seed: 2
        """
    sim = sims(text, "first")
    run_dir = tmp_path / "run"
    opts = options.OnlineOptions(m_a=0.03, eps_rel=0.02, max_samples=200, settle_s=0.08)
    box: dict = {}
    thread = threading.Thread(target=lambda: box.update(
        res=live.run_online(RemoteRobot("127.0.0.1", sim.port, timeout_s=2), opts, run_dir)))
    thread.start()
    log = run_dir / live.LOG_FILE
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (log.exists() and log.read_bytes().count(b'"e":"sample"') >= 4):
        time.sleep(0.02)
    os.kill(sim.proc.pid, signal.SIGKILL)
    thread.join(timeout=60)
    res = box["res"]
    assert res.status == live.Stop.CONNECTION, res.detail
    records = read_journal(log).records  # intact: every line parses (a cut last line would be counted)
    assert records[-1]["e"] == "stop" and records[-1]["reason"] == "connection"
    done = sum(1 for r in records if r["e"] == "sample")
    assert done >= 4
    with _sim_here(tmp_path, text, "second") as port:  # a fresh simulator, here: no second process start
        res2 = live.run_online(RemoteRobot("127.0.0.1", port, timeout_s=5), opts, run_dir, resume=True)
    assert res2.replayed == res.samples and res2.status == live.Stop.CONVERGED
    assert res2.samples > res.samples


def test_server_answers_bad_requests_without_moving(tmp_path):
    """The server's own checks, in process: malformed requests get an error reply, the robot does not move."""
    moves = []

    class Recorder:
        def limits(self):
            from selfid_jax.robot.protocol import RobotLimits

            return RobotLimits(np.zeros(2), np.ones(2), np.full(2, 0.1))

        def move(self, target):
            moves.append(target)

        def close(self):
            pass

    server = RobotServer(Recorder())
    assert server.handle({"op": "move", "target": "x"})["ok"] is False
    assert server.handle({"op": "launch"})["error"].startswith("unknown op 'launch'")
    reply = server.handle({"op": "move", "target": [0.5], "id": 4})  # wrong length: refused here, id echoed
    assert reply["ok"] is False and reply["id"] == 4 and "target has 1 entries" in reply["error"]
    assert server.handle({"op": "move", "target": [float("nan"), 0.5]})["ok"] is False
    assert moves == []
    assert server.handle({"op": "limits"})["upper"] == [1.0, 1.0]
    server.shutdown()


def test_a_tracker_frozen_from_time_zero_is_frozen_for_a_read_before_the_first_tick():
    """freeze_tracker_at_s 0 holds at tick 0 too: a read before the clock's first tick, a move, and a later read see
    one pose with one stamp (the freeze used to start at the first tick, a stamp newer than the first read's)."""
    from selfid_jax.control.realism import Realism
    from selfid_jax.robot import virtual
    from selfid_jax.systems.two_link import two_link

    robot = virtual.VirtualRobot(two_link(), realism=Realism(period=0.01),
                                 faults=virtual.Faults(freeze_tracker_at_s=0.0), start=False)
    try:
        a = robot.read()
        robot.move(a.q + 0.01)
        robot.start()
        time.sleep(0.05)
        b = robot.read()
        assert b.t > a.t and not np.array_equal(b.q, a.q)  # the clock and the arm moved on
        assert b.tracker_t == a.tracker_t and np.array_equal(b.position, a.position)
    finally:
        robot.close()


def test_robot_sim_loads_a_urdf_at_a_body_and_offset_and_resets_per_client(tmp_path):
    """robot-sim's config takes a sweep's robot keys (a URDF, its tool body and an offset: the pose is MuJoCo's
    point there), refuses half of them naming the keys, and with reset_on_connect each client finds q0."""
    from helpers_mjcf import URDF
    from helpers_mjcf import body_point_jacobian as _body_point_jacobian

    from selfid_jax.runner.errors import ConfigError
    from selfid_jax.sessions import online_sim

    (tmp_path / "arm3.urdf").write_text(URDF)
    cfg_file = tmp_path / "sim.yaml"
    cfg_file.write_text("mjcf: arm3.urdf\nbody: tool\noffset: [0, 0, 0.03]\nactuators: joints\nq0: [0.3, -0.4, 0.8]\n"
                        "reset_on_connect: true\nrealism: {period: 0.005}\nport: 0\n")
    cfg = online_sim.load_sim_config(cfg_file)
    robot = online_sim.build(cfg, start=True)
    spec = mujoco.MjSpec.from_file(str(tmp_path / "arm3.urdf"))
    spec.compiler.fusestatic = False
    point, _ = _body_point_jacobian(spec.compile(), np.array([0.3, -0.4, 0.8]), "tool", (0, 0, 0.03))
    server = RobotServer(robot, "127.0.0.1", 0, info=robot.info(), position=robot.position, on_connect=robot.reset)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        first = RemoteRobot("127.0.0.1", server.port, timeout_s=5)
        np.testing.assert_allclose(first.read().position, point, atol=1e-9)
        first.move(np.array([0.32, -0.4, 0.8]))
        time.sleep(0.05)
        assert abs(first.read().q[0] - 0.32) < 1e-9
        first.close()
        second = RemoteRobot("127.0.0.1", server.port, timeout_s=5)  # a new client: back at q0
        time.sleep(0.02)
        np.testing.assert_allclose(second.read().q, [0.3, -0.4, 0.8], atol=1e-12)
        second.close()
    finally:
        server.shutdown()
    for body, msg in (("site: tip\nbody: tool\n", "'site: NAME', or 'body: NAME'"),
                      ("offset: [0, 0, 0.1]\n", "needs the point the tracker follows"),
                      ("system: ur5e\nbody: tool\n", "are for an 'mjcf' file")):
        bad = tmp_path / "bad.yaml"
        bad.write_text(("mjcf: arm3.urdf\n" if not body.startswith("system") else "") + body)
        with pytest.raises(ConfigError, match=msg):
            online_sim.load_sim_config(bad)
