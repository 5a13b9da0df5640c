"""The Franka driver (selfid_jax.robot.drivers.franka): its contract against a stand-in franky module (fast), and
selfid-jax online end to end through libfranka against franky-sim's FR3 (slow; a subprocess on port 1337).

The end-to-end reference is MuJoCo's Jacobian of the simulator's own fr3.xml at the session's first joint reading
(tests/franka_reference.py), an independent computation from the model the simulator integrates.
"""

from __future__ import annotations

import time
import types
from pathlib import Path

import helpers_vendor_sim as vendor_sim
import numpy as np
import pytest

from selfid_jax.robot.drivers.franka import Franka, urdf_joint_limits
from selfid_jax.robot.protocol import RobotConnectionError, RobotError

URDF = """<robot name="fr3">{}</robot>""".format("".join(
    f'<joint name="j{i}" type="revolute"><limit lower="{-2 - i / 10}" upper="{2 + i / 10}"/></joint>'
    for i in range(1, 8)) + '<joint name="finger" type="prismatic"><limit lower="0" upper="0.04"/></joint>')


class _Affine:
    def __init__(self, translation, xyzw):
        self.translation, self.quaternion = np.asarray(translation, float), np.asarray(xyzw, float)


class _Model:
    """libfranka's kinematic model, for a stand-in arm whose end effector is at (0.3 + q0, q1, 0.5)."""

    def __init__(self):
        self.calls = []

    def pose(self, frame, q, F_T_EE, EE_T_K):
        self.calls.append((frame, np.array(q)))
        z = 0.5 if frame == "EndEffector" else 0.5 - F_T_EE.translation[2]
        return _Affine([0.3 + q[0], q[1], z], [1.0, 0.0, 0.0, 0.0])  # (x, y, z, w): pi about x

    def zero_jacobian(self, frame, q, F_T_EE, EE_T_K):
        self.calls.append((frame, np.array(q)))
        J = np.zeros((6, 7))
        J[0, 0] = J[1, 1] = 1.0
        return J


class Clock:
    """A clock the test controls: the driver's ``time.monotonic`` and ``time.sleep`` (monkeypatched into the
    driver's module) and the stand-in arm's motion all run on it, so a wait is as long as the driver asked for,
    however loaded the machine is."""

    def __init__(self, t: float = 100.0):
        self.t = t  # s

    def monotonic(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += seconds


def fake_franky(bias=None, lag=0, error_at=None, network_at=None, clock=None, speed=None):
    """A stand-in for the franky module: an arm whose joints land on each command plus ``bias`` (7,), ``lag``
    reads after the move returns, or with ``clock`` (a :class:`Clock`) each joint moving from where it was at
    ``speed`` [rad/s] until it lands; ``error_at`` / ``network_at`` raise franky's exceptions at that move."""
    mod = types.SimpleNamespace()

    class FrankyException(Exception):
        pass

    class NetworkException(FrankyException):
        pass

    mod.Exception, mod.NetworkException = FrankyException, NetworkException
    mod.RealtimeConfig = types.SimpleNamespace(Enforce="enforce", Ignore="ignore")
    mod.Frame = types.SimpleNamespace(EndEffector="EndEffector", Flange="Flange")
    mod.JointState = lambda q: np.asarray(q, float)
    mod.JointMotion = lambda state: state

    class Robot:
        def __init__(self, host, realtime_config):
            if host == "nowhere":
                raise NetworkException("libfranka: Connection timeout")
            self.host, self.realtime_config = host, realtime_config
            self.q = np.zeros(7)
            self.settled_q = self.q.copy()
            self.start_q, self.move_t = self.q.copy(), -np.inf  # where the last move started, and when (clock)
            self.pending = 0
            self.moves, self.commands, self.stopped = 0, [], 0
            self.t = 0.0
            self.has_errors = False
            self.clock_frozen = False
            self.model_urdf = URDF
            self.model = _Model()
            self.relative_dynamics_factor = 1.0

        def _on_clock(self):
            """The joints at ``clock``'s time: at most ``speed`` times the time since the move from where they
            were then, towards where they land (rad)."""
            d = self.settled_q - self.start_q
            travel = speed * (clock.t - self.move_t)
            return self.start_q + np.sign(d) * np.minimum(np.abs(d), travel)

        @property
        def state(self):
            if clock is not None:
                self.q = self._on_clock()
            elif self.pending:
                self.pending -= 1
                self.q = self.q + 0.5 * (self.settled_q - self.q)
            else:
                self.q = self.settled_q.copy()
            if not self.clock_frozen:
                self.t += 0.001
            return types.SimpleNamespace(q=self.q.astype(np.float32), time=types.SimpleNamespace(to_sec=lambda: self.t),
                                         F_T_EE=_Affine([0, 0, 0.1034], [0, 0, 0, 1]), EE_T_K=None,
                                         current_errors="[]")

        def move(self, command):
            self.moves += 1
            if error_at == self.moves:
                raise FrankyException("cartesian_reflex")
            if network_at == self.moves:
                raise NetworkException("libfranka: UDP receive: Timeout")
            self.commands.append(np.asarray(command))
            if clock is not None:
                self.start_q, self.move_t = self._on_clock(), clock.t
            self.settled_q = np.asarray(command) + (0 if bias is None else np.asarray(bias))
            self.pending = lag

        def stop(self):
            self.stopped += 1

    mod.Robot = Robot
    return mod


def _franka(franky, **kw):
    """A Franka driver on the stand-in ``franky``, its settling scaled to a 5 ms window (band_tol with it: the
    default 0.5 mrad per 0.1 s, 5 mrad/s)."""
    kw = {"settle_window_s": 0.005, "poll_s": 0.001, "settle_timeout_s": 0.5, "band_tol": 2.5e-5, **kw}
    return Franka("10.0.0.2", franky=franky, **kw)


def test_urdf_limits_in_order_and_refused_when_missing():
    lower, upper, names = urdf_joint_limits(URDF)
    assert names == [f"j{i}" for i in range(1, 8)]
    np.testing.assert_allclose(lower, [-2 - i / 10 for i in range(1, 8)])
    np.testing.assert_allclose(upper, [2 + i / 10 for i in range(1, 8)])
    with pytest.raises(ValueError, match="3 revolute joints"):
        urdf_joint_limits(URDF.replace('type="revolute"', 'type="fixed"', 4))
    with pytest.raises(ValueError, match="joint 'j2' no <limit lower upper>"):
        urdf_joint_limits(URDF.replace('<limit lower="-2.2" upper="2.2"/>', ""))


def test_limits_narrowed_by_margin_and_max_step():
    arm = _franka(fake_franky(), limit_margin=0.1, max_step=0.02)
    lim = arm.limits()
    np.testing.assert_allclose(lim.lower, [-1.9 - i / 10 for i in range(1, 8)])
    np.testing.assert_allclose(lim.upper, [1.9 + i / 10 for i in range(1, 8)])
    np.testing.assert_allclose(lim.max_step, np.full(7, 0.02))
    arm.robot.model_urdf = "<robot/>"
    with pytest.raises(RobotError, match="gives no joint limits: .*0 revolute joints"):
        arm.limits()


def test_read_reorders_franky_quaternion_and_stamps_the_monotonic_clock():
    arm = _franka(fake_franky())
    before = time.monotonic()
    obs = arm.read()
    assert before <= obs.t <= time.monotonic() and obs.tracker_t == obs.t and obs.valid
    np.testing.assert_allclose(obs.quaternion, [0.0, 1.0, 0.0, 0.0])  # franky's (x, y, z, w) = (1, 0, 0, 0)
    np.testing.assert_allclose(obs.position, [0.3, 0.0, 0.5])
    assert obs.q.dtype == np.float64 and obs.q.shape == (7,)
    frame, q = arm.robot.model.calls[-1]
    assert frame == "EndEffector" and np.array_equal(q, obs.q)  # the pose of the very joints reported
    flange = _franka(fake_franky(), tracker="flange").read()
    np.testing.assert_allclose(flange.position, [0.3, 0.0, 0.5 - 0.1034])


def test_a_frozen_arm_clock_keeps_the_pose_stamp_of_its_last_advance():
    arm = _franka(fake_franky())
    first = arm.read()
    arm.robot.clock_frozen = True
    time.sleep(0.01)
    later = arm.read()
    assert later.t > first.t + 0.005 and later.tracker_t == first.tracker_t  # the runner's stale check sees it


def test_move_waits_until_settled_and_corrects_a_held_offset(monkeypatch):
    """The arm moves at 0.1 rad/s on a clock the test controls (the driver's waits run on it too, so the test does
    not depend on the machine's load): a move returns only once the joints have landed, and the offset a joint
    holds is corrected over the following moves."""
    from selfid_jax.robot.drivers import franka as franka_module

    clock = Clock()
    monkeypatch.setattr(franka_module, "time", types.SimpleNamespace(monotonic=clock.monotonic, sleep=clock.sleep))
    bias = np.array([0, 0, 0, 0, 0, 0, -1.7e-3])  # what franky-sim's joint 7 holds under any command
    speed = 0.1  # rad/s: a 5 ms settle window sees 0.5 mrad of motion, above settle_tol
    franky = fake_franky(bias=bias, clock=clock, speed=speed)
    arm = _franka(franky)
    target = np.full(7, 0.01)
    t0 = clock.t
    arm.move(target)
    assert clock.t - t0 >= 0.01 / speed  # it waited for the whole motion (0.1 s), not just the window
    np.testing.assert_allclose(arm.read().q, target + bias, atol=1e-7)  # settled, offset held
    for _ in range(12):
        target = target + 0.001
        arm.move(target)
    np.testing.assert_allclose(arm.read().q, target, atol=1e-6)  # the offset is corrected: no walk away
    assert franky.Robot is not None and arm.robot.moves == 13
    np.testing.assert_allclose(arm.robot.commands[-1], target - bias, atol=1e-6)
    plain = _franka(fake_franky(bias=bias), offset_correction=False)
    plain.move(target)
    plain.move(target)
    np.testing.assert_allclose(plain.read().q, target + bias, atol=1e-7)


def test_offset_correction_is_bounded_by_target_tol():
    arm = _franka(fake_franky(bias=np.full(7, 0.05)), target_tol=0.1)
    arm.move(np.zeros(7))
    for _ in range(10):
        arm.move(np.zeros(7))
    assert np.all(np.abs(arm.offset) <= 0.1) and np.all(arm.offset > 0.04)


def test_a_joint_that_does_not_settle_raises_robot_error_naming_it():
    bias = np.zeros(7)
    bias[3] = 0.02  # off its target by more than target_tol
    arm = _franka(fake_franky(bias=bias), settle_timeout_s=0.05, offset_correction=False)
    with pytest.raises(RobotError, match=r"joint 4 did not settle within 0.05 s of the move: it stays 20 mrad from "
                       r"its target, beyond target_tol 10 mrad"):
        arm.move(np.zeros(7))


def test_vendor_exceptions_become_the_runner_s():
    with pytest.raises(RobotConnectionError, match="connect at nowhere: libfranka: Connection timeout"):
        Franka("nowhere", franky=fake_franky())
    arm = _franka(fake_franky(error_at=1, network_at=2))
    with pytest.raises(RobotError, match="move at 10.0.0.2: FrankyException: cartesian_reflex") as err:
        arm.move(np.zeros(7))
    assert not isinstance(err.value, RobotConnectionError)
    with pytest.raises(RobotConnectionError, match="UDP receive: Timeout"):
        arm.move(np.zeros(7))


def test_bad_targets_errors_and_arguments_are_refused_before_any_motion():
    arm = _franka(fake_franky())
    for bad in (np.zeros(6), np.array([0, 0, 0, np.nan, 0, 0, 0])):
        with pytest.raises(RobotError, match="7 finite joint angles"):
            arm.move(bad)
    arm.robot.has_errors = True
    with pytest.raises(RobotError, match="reports errors .*clear them at the arm"):
        arm.move(np.zeros(7))
    assert arm.robot.moves == 0
    for kw, msg in (({"dynamics": 1.5}, "dynamics must be in"), ({"limit_margin": -0.1}, "limit_margin"),
                    ({"tracker": "camera"}, "tracker must be"), ({"tracker_args": {"a": 1}}, "tracker_args are")):
        with pytest.raises(ValueError, match=msg):
            _franka(fake_franky(), **kw)


def test_close_stops_once_and_refuses_later_calls():
    arm = _franka(fake_franky())
    robot = arm.robot
    arm.close()
    arm.close()
    assert robot.stopped == 1
    with pytest.raises(RobotError, match="closed"):
        arm.read()


class ExternalTracker:
    """A position-only external tracker for the driver's ``tracker: "module:Class"``."""

    def __init__(self, offset):
        self.offset, self.closed = offset, False

    def read(self):
        return time.monotonic(), np.array([self.offset, 0.0, 0.0]), None, True

    def close(self):
        self.closed = True


def test_the_model_jacobian_is_libfranka_s_at_the_given_joints_and_none_for_an_external_tracker():
    arm = _franka(fake_franky())
    q = np.linspace(0.1, 0.7, 7)
    J = arm.jacobian(q)
    assert J.shape == (6, 7) and J[0, 0] == 1.0 and J.dtype == np.float64
    frame, asked = arm.robot.model.calls[-1]
    assert frame == "EndEffector" and np.array_equal(asked, q)
    external = _franka(fake_franky(), tracker="test_franka:ExternalTracker", tracker_args={"offset": 0.0})
    assert external.jacobian(q) is None


def test_an_external_tracker_replaces_the_arm_pose():
    arm = _franka(fake_franky(), tracker="test_franka:ExternalTracker", tracker_args={"offset": 0.25})
    obs = arm.read()
    np.testing.assert_allclose(obs.position, [0.25, 0, 0])
    assert obs.quaternion is None and obs.tracker_t >= obs.t - 1.0
    tracker = arm.tracker
    arm.close()
    assert tracker.closed


# ---- end to end: selfid-jax online through libfranka against franky-sim


@pytest.fixture(scope="module")
def franka_sim_available():
    pytest.importorskip("franky", reason="franky-control is not installed (pip install '.[test]' brings it)")
    pytest.importorskip("franky_sim", reason="franky-sim is not installed (pip install '.[test]' brings it)")
    import franka_reference
    if franka_reference.port_open():
        pytest.fail(f"127.0.0.1:{franka_reference.PORT} is in use: stop the other franky-sim or libfranka server")
    return franka_reference


CONFIG = Path(__file__).resolve().parents[1] / "configs" / "robot" / "online_franka_sim.yaml"
# Faster than the shipped config, the same checks: a 1 cm star (half the shipped 2 cm) followed at gain 1 with up
# to 1 cm a move (shipped 0.5 and 5 mm): about one move per waypoint, 10 to 14 instead of 27 to 29. Moves at the
# FR3's full dynamics limits (shipped a tenth, 0.5 before): franky-sim's joints trail the trajectory's end by up to
# 0.03 rad and close that with a time constant of about 0.2 s, and a joint within settle_band 5 mrad of its target
# (shipped 2) that moves less than band_tol 2 mrad per 0.1 s (shipped 0.5) is settled: 0.03 rad a joint takes about
# 0.55 s (trajectory and settling) instead of 0.8 s at 0.5 (the loaded 2-core machine). A sample is unaffected by
# when it is read: the pose is libfranka's model at the joints of the same reading.
SMALL = ["--set", "path.size=0.01", "--set", "path.gain=1.0", "--set", "path.max_task_step=0.01",
         "--set", "robot.args.dynamics=1.0", "--set", "robot.args.settle_band=0.005",
         "--set", "robot.args.band_tol=0.002"]


@pytest.mark.slow
@pytest.mark.xdist_group("realtime")  # one real-time simulator at a time (tests/test_robot_sim.py too)
def test_online_through_libfranka_on_franky_sim(franka_sim_available, tmp_path, capsys, monkeypatch):
    """3-D: converges, stops random motion, completes the star; ||J Ĵ - I||_F <= 0.08 against MuJoCo's Jacobian
    at the start pose (0.012-0.018 measured over four runs; the estimate averages the Jacobian over the poses
    self-ID visits, within 0.03 rad a joint of the start, so it cannot be exact: up to 0.04 over twelve seeds of
    MuJoCo's own kinematics). 6-D: the simulator killed during self-ID stops the session cleanly (exit 3, a
    connection stop, a stop line in the journal); --resume against a fresh simulator continues the logged samples,
    converges with the default rule, completes the star and draws the run's figures; ||J Ĵ - I||_F <= 0.2
    (0.049-0.092 measured over four runs; up to 0.12 over twelve seeds offline). The first two sessions draw no
    figures (about 4 s of plotting each, from a log like the third's; the figures are tested in
    test_online_session and test_online_lab)."""
    from selfid_jax.cli import main
    from selfid_jax.sessions import online_figures

    fr = franka_sim_available
    out3, out6 = tmp_path / "xyz", tmp_path / "6d"
    draw = online_figures.write_figures
    monkeypatch.setattr(online_figures, "write_figures", lambda run_dir: [])
    with fr.franky_sim(tmp_path / "sim.log"):
        assert main(["online", str(CONFIG), "--out", str(out3), *SMALL, "--quiet"]) == 0
    vendor_sim.converged_then_followed(out3, fr.session_error, 0.08)  # libfranka's model agrees with fr3.xml's

    six = ["--set", "selfid.task=x,y,z,rx,ry,rz", *SMALL, "--quiet"]
    with fr.franky_sim(tmp_path / "sim.log") as sim:
        vendor_sim.killed_during_selfid(lambda: main(["online", str(CONFIG), "--out", str(out6), *six]), sim,
                                        fr.PORT, out6, "libfranka")
    capsys.readouterr()
    monkeypatch.setattr(online_figures, "write_figures", draw)
    with fr.franky_sim(tmp_path / "sim.log"):
        assert main(["online", str(CONFIG), "--out", str(out6), "--resume", *six]) == 0
    vendor_sim.converged_then_followed(out6, fr.session_error, 0.2, resumed=True)
    assert {f.name for f in (out6 / "figures").iterdir()} >= {"convergence.png", "path.png", "estimate.png"}


def test_settling_judges_a_whole_window_even_when_reads_are_slower_than_it(monkeypatch):
    """Reads 20 ms apart against a 5 ms window (a loaded machine): the spread is taken over at least two readings
    a window apart, so a joint still moving is never taken for settled from a single reading."""
    arm = _franka(fake_franky(lag=6), settle_tol=1e-6, poll_s=0.02)
    arm.move(np.full(7, 0.01))
    np.testing.assert_allclose(arm.read().q, np.full(7, 0.01), atol=1e-12)
