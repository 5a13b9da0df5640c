"""The Trossen WidowX AI driver (selfid_jax.robot.drivers.trossen), the drivers' shared parts (drivers.common) and
drivers by name (drivers.load): the contract against a stand-in trossen_arm module (fast); the unmodified vendor
driver against trossen-arm-sim's controller in this process (its faults and a firmware it refuses); and selfid-jax
online end to end against trossen-arm-sim in a subprocess (slow).

The end-to-end reference is MuJoCo's Jacobian of the simulator's own MJCF at the session's first joint reading
(tests/trossen_reference.py), an independent computation from the model the simulator integrates; the driver's own
reference (summary.json reference_error) comes from the kinematic parameters the controller serves.
"""

from __future__ import annotations

import contextlib
import time
import types
from pathlib import Path

import helpers_vendor_sim as vendor_sim
import numpy as np
import pytest

from selfid_jax.robot.drivers import common
from selfid_jax.robot.drivers.trossen import Trossen, kinematic_model, rotvec_quaternion
from selfid_jax.robot.protocol import Robot, RobotConnectionError, RobotError

HOME = [0.0, np.pi / 2, np.pi / 2, 0.0, 0.0, 0.0]
LOWER = [-3.05, 0.0, 0.0, -1.57, -1.57, -3.14, 0.0]  # rad (the gripper's in m)
UPPER = [3.05, 3.14, 2.36, 1.57, 1.57, 3.14, 0.044]


class Clock:
    """The driver's ``time.monotonic`` and ``time.sleep`` (monkeypatched into its module) and the stand-in arm's
    motion on one clock the test controls, so waits do not depend on the machine's load."""

    def __init__(self, t: float = 50.0):
        self.t = t

    def monotonic(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += seconds


def fake_trossen_arm(clock: Clock, speed: float = 0.5, bias=None, fail: dict | None = None, joints: int = 7):
    """A stand-in for the trossen_arm module: an arm whose six joints move from where they were at ``speed``
    [rad/s] towards each target (plus ``bias`` (6,)) on ``clock``; its pose is ``(0.3 + q0, q1, 0.2 + q2)`` with
    the rotation vector ``(q3, q4, q5)``. ``fail`` maps a call name to the message its trossen_arm.RuntimeError
    carries."""
    mod = types.SimpleNamespace()
    fail = dict(fail or {})

    class VendorRuntimeError(RuntimeError):
        pass

    class LogicError(AssertionError):
        pass

    mod.RuntimeError, mod.LogicError = VendorRuntimeError, LogicError
    mod.Model = types.SimpleNamespace(__members__={"wxai_v0": 0}, wxai_v0=0)
    mod.StandardEndEffector = type("StandardEndEffector", (), {"wxai_v0_follower": "follower"})
    mod.Mode = types.SimpleNamespace(position="position", idle="idle")

    def check(call):
        if call in fail:
            raise VendorRuntimeError(fail[call])

    class Driver:
        def __init__(self):
            self.q, self.start_q, self.goal = np.zeros(6), np.zeros(6), np.zeros(6)
            self.move_t, self.commands, self.modes, self.cleaned, self.frozen = clock.t, [], [], 0, False
            self.t_us = 0

        def configure(self, model, end_effector, host, clear_error, timeout):
            check("configure")
            self.configured = (model, end_effector, host, clear_error, timeout)

        def get_num_joints(self):
            return joints

        def set_arm_modes(self, mode):
            self.modes.append(mode)

        def _now(self):
            d = self.goal - self.start_q
            travel = speed * (clock.t - self.move_t)
            return self.start_q + np.sign(d) * np.minimum(np.abs(d), travel)

        def set_arm_positions(self, goal, goal_time, blocking):
            check("move")
            if len(goal) != 6:
                raise LogicError("The size of the vectors should be equal to the number of arm joints.")
            self.start_q, self.move_t = self._now(), clock.t
            self.goal = np.asarray(goal, float) + (0 if bias is None else np.asarray(bias))
            self.commands.append((np.array(goal), goal_time, blocking))

        def get_arm_positions(self):
            check("read")
            return list(self._now())

        def get_robot_output(self):
            check("read")
            q = self._now()
            if not self.frozen:
                self.t_us += 1000
            return types.SimpleNamespace(
                joint=types.SimpleNamespace(arm=types.SimpleNamespace(positions=list(q))),
                cartesian=types.SimpleNamespace(positions=[0.3 + q[0], q[1], 0.2 + q[2], q[3], q[4], q[5]]),
                header=types.SimpleNamespace(timestamp=self.t_us))

        def get_joint_limits(self):
            return [types.SimpleNamespace(position_min=lo, position_max=hi) for lo, hi in zip(LOWER, UPPER)]

        def cleanup(self):
            self.cleaned += 1

    mod.TrossenArmDriver = Driver
    return mod


@pytest.fixture
def clock(monkeypatch):
    from selfid_jax.robot.drivers import trossen as trossen_module

    c = Clock()
    monkeypatch.setattr(trossen_module, "time", types.SimpleNamespace(monotonic=c.monotonic, sleep=c.sleep))
    return c


def _arm(clock, **kw):
    fake = {k: kw.pop(k) for k in ("speed", "bias", "fail", "joints") if k in kw}
    return Trossen("10.0.0.3", trossen_arm=fake_trossen_arm(clock, **fake), **kw)


def test_connect_configures_the_vendor_driver_and_moves_to_start_only_when_asked(clock):
    arm = _arm(clock, connect_timeout_s=2.0)
    assert arm.arm.configured == (0, "follower", "10.0.0.3", False, 2.0) and arm.arm.modes == ["position"]
    assert arm.arm.commands == [] and isinstance(arm, Robot)
    t0 = clock.t
    started = _arm(clock, start=HOME, start_time_s=2.0)
    np.testing.assert_allclose(started.read().q, HOME, atol=1e-12)
    assert clock.t - t0 >= np.pi / 2 / 0.5  # it waited for the whole motion at 0.5 rad/s
    goal, goal_time, blocking = started.arm.commands[0]
    assert goal_time == 2.0 and not blocking


def test_limits_are_the_controller_s_six_arm_joints_narrowed(clock):
    lim = _arm(clock, limit_margin=0.1, max_step=0.02).limits()
    np.testing.assert_allclose(lim.lower, np.array(LOWER[:6]) + 0.1)
    np.testing.assert_allclose(lim.upper, np.array(UPPER[:6]) - 0.1)
    np.testing.assert_allclose(lim.max_step, np.full(6, 0.02))
    with pytest.raises(RobotError, match=r"joint 2's limits \[0, 0.98\] leave nothing inside a margin of 0.49"):
        common.narrow_limits("Trossen", [0.0, 0.0], [3.0, 0.98], 0.49, 0.1)


def test_read_gives_one_cycle_s_joints_and_pose_and_a_frozen_controller_reads_stale(clock):
    arm = _arm(clock, start=[0.1, 0.2, 0.3, 0.0, np.pi / 2, 0.0])
    obs = arm.read()
    np.testing.assert_allclose(obs.position, [0.4, 0.2, 0.5], atol=1e-12)
    np.testing.assert_allclose(obs.quaternion, [np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0], atol=1e-12)
    assert obs.t == clock.t and obs.tracker_t == obs.t and obs.valid is True and obs.q.dtype == np.float64
    arm.arm.frozen = True
    clock.sleep(0.5)
    later = arm.read()
    assert later.t == obs.t + 0.5 and later.tracker_t == obs.tracker_t  # the runner's stale check sees it


def test_move_waits_for_the_trajectory_and_settling(clock):
    arm = _arm(clock, speed=0.02, move_time_s=0.3)  # 0.05 rad at 0.02 rad/s: 2.5 s, beyond the trajectory
    t0 = clock.t
    target = np.full(6, 0.05)
    arm.move(target)
    assert clock.t - t0 >= 2.5
    np.testing.assert_allclose(arm.read().q, target, atol=1e-12)
    goal, goal_time, blocking = arm.arm.commands[-1]
    assert goal_time == 0.3 and not blocking and np.array_equal(goal, target)


def test_offset_correction_lands_a_biased_joint_on_its_target(clock):
    bias = np.array([0, 0, 0, 0, 0, -2e-3])
    arm = _arm(clock, bias=bias, offset_correction=True)
    target = np.zeros(6)
    for _ in range(12):
        target = target + 1e-3
        arm.move(target)
    np.testing.assert_allclose(arm.read().q, target, atol=1e-5)
    plain = _arm(clock, bias=bias)
    plain.move(target)
    np.testing.assert_allclose(plain.read().q, target + bias, atol=1e-12)


def test_a_joint_that_does_not_settle_raises_robot_error_naming_it(clock):
    arm = _arm(clock, bias=np.array([0, 0, 0.03, 0, 0, 0]), settle_timeout_s=0.5)
    with pytest.raises(RobotError, match=r"Trossen: joint 3 did not settle within 0.5 s of the move: it stays 30 "
                       r"mrad from its target"):
        arm.move(np.zeros(6))


def test_vendor_errors_become_the_runner_s(clock):
    lost = "Failed to read UDP message from 10.0.0.3:50000 due to Connection refused"
    fault = "Error occurred: Joint limit exceeded\nLatest log on the arm controller since powered on: joint 2"
    timeout = "Failed to connect to the arm controller's TCP server at 10.0.0.3:50001 within 2 seconds"
    with pytest.raises(RobotConnectionError, match="Trossen connect at 10.0.0.3: Failed to connect"):
        _arm(clock, fail={"configure": timeout})
    with pytest.raises(RobotError, match="Trossen at 10.0.0.3: the controller reports 5 joints"):
        _arm(clock, joints=5)
    for call, message, kind in (("move", fault, RobotError), ("read", lost, RobotConnectionError)):
        fake = fake_trossen_arm(clock, fail={call: message})
        arm = Trossen("10.0.0.3", trossen_arm=fake)
        with pytest.raises(kind) as err:
            arm.move(np.zeros(6))
        assert (type(err.value) is RobotConnectionError) == (kind is RobotConnectionError)
        assert f"Trossen {call} at 10.0.0.3" in str(err.value)


def test_bad_targets_and_arguments_are_refused_before_any_motion(clock):
    arm = _arm(clock)
    for bad in (np.zeros(7), np.array([0, 0, 0, np.nan, 0, 0])):
        with pytest.raises(RobotError, match="6 finite joint angles"):
            arm.move(bad)
    assert arm.arm.commands == []
    for kw, msg in (({"move_time_s": 0}, r"move_time_s must be in \(0, 10\]"), ({"limit_margin": 0.5},
                    r"limit_margin must be in \[0, 0.5\) rad"), ({"settle_tol": -1}, "settle_tol"),
                    ({"model": "px100"}, r"model must be one of trossen_arm.Model's \['wxai_v0'\]"),
                    ({"end_effector": "hand"}, "end_effector must be one of"), ({"tracker": "flange"},
                    "tracker must be 'end_effector' or 'module:Class'"), ({"start": [0, 1]}, "start must be 6")):
        with pytest.raises((ValueError, RobotError), match=msg):
            _arm(clock, **kw)


def test_close_holds_the_joints_cleans_up_once_and_refuses_later_calls(clock):
    arm = _arm(clock, start=HOME)
    vendor = arm.arm
    arm.close()
    arm.close()
    assert vendor.cleaned == 1
    goal, goal_time, _ = vendor.commands[-1]
    np.testing.assert_allclose(goal, HOME, atol=1e-12)
    assert goal_time == 0.0
    with pytest.raises(RobotError, match="closed"):
        arm.read()


def test_the_vendor_driver_is_released_when_connecting_fails(clock):
    fake = fake_trossen_arm(clock, fail={"move": "Error occurred: Joint limit exceeded"})
    made = []
    original = fake.TrossenArmDriver
    fake.TrossenArmDriver = lambda: made.append(original()) or made[-1]
    with pytest.raises(RobotError, match="Trossen start at 10.0.0.3"):
        Trossen("10.0.0.3", trossen_arm=fake, start=HOME)
    assert made[0].cleaned == 1


def test_a_controller_that_sends_no_joint_outputs_yet_is_configured_again_until_connect_timeout_s(clock):
    """libtrossen_arm's configure gives up within a second on a controller that took the TCP connection but sent no
    joint outputs (a loaded machine's trossen-arm-sim did, 3 of 16 connects): the driver configures again with a
    fresh vendor driver, the failed one cleaned up, until connect_timeout_s; any other failure is raised at once."""
    no_outputs = ("Failed to receive initial joint outputs Please refer to our troubleshooting guide at "
                  "https://docs.trossenrobotics.com/trossen_arm/main/troubleshooting.html")

    def vendor(failures: int, message: str = no_outputs):
        fake = fake_trossen_arm(clock)
        made, original = [], fake.TrossenArmDriver

        def make():
            driver = original()
            if len(made) < failures:
                def configure(*args, **kwargs):
                    raise fake.RuntimeError(message)
                driver.configure = configure
            made.append(driver)
            return driver
        fake.TrossenArmDriver = make
        return fake, made

    fake, made = vendor(2)
    t0 = clock.t
    arm = Trossen("10.0.0.3", trossen_arm=fake, connect_timeout_s=2.0)
    assert len(made) == 3 and arm.arm is made[2] and [d.cleaned for d in made] == [1, 1, 0]
    assert clock.t - t0 == pytest.approx(0.2)  # a 0.1 s pause before each new try
    assert made[2].configured[-1] == pytest.approx(1.8)  # the TCP timeout is what is left of connect_timeout_s
    assert arm.arm.commands == []  # nothing moved

    fake, made = vendor(10**6)
    t0 = clock.t
    with pytest.raises(RobotConnectionError, match="Trossen connect at 10.0.0.3: Failed to receive initial joint"):
        Trossen("10.0.0.3", trossen_arm=fake, connect_timeout_s=1.0)
    assert 1.0 - 0.1 <= clock.t - t0 <= 1.0 + 1e-9 and 9 <= len(made) <= 11 and all(d.cleaned == 1 for d in made)

    fake, made = vendor(1, "Failed to connect to the arm controller's TCP server at 10.0.0.3:50001 within 2 seconds")
    with pytest.raises(RobotConnectionError, match="Failed to connect"):
        Trossen("10.0.0.3", trossen_arm=fake, connect_timeout_s=5.0)
    assert len(made) == 1 and made[0].cleaned == 1


class ExternalTracker:
    """A position-only external tracker for the driver's ``tracker: "module:Class"``."""

    def __init__(self, offset):
        self.offset, self.closed = offset, False

    def read(self):
        return time.monotonic(), np.array([self.offset, 0.0, 0.0]), None, True

    def close(self):
        self.closed = True


def test_an_external_tracker_replaces_the_arm_pose_and_has_no_model(clock):
    arm = _arm(clock, tracker="test_trossen:ExternalTracker", tracker_args={"offset": 0.25})
    obs = arm.read()
    np.testing.assert_allclose(obs.position, [0.25, 0, 0])
    assert obs.quaternion is None and arm.jacobian(np.zeros(6)) is None
    tracker = arm.tracker
    arm.close()
    assert tracker.closed


# ---- the kinematic model and the rotation helpers, against closed forms


def _rot(axis: str, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def test_rotvec_quaternion_is_the_exponential_map():
    for r in (np.zeros(3), np.array([1e-9, 0, 0]), np.array([0.3, -0.2, 0.9]), np.array([0, np.pi, 0])):
        w, v = rotvec_quaternion(r)[0], rotvec_quaternion(r)[1:]
        theta = np.linalg.norm(r)
        assert np.isclose(w, np.cos(theta / 2)) and np.allclose(v, np.sin(theta / 2) * r / max(theta, 1e-300))


def test_kinematic_model_is_the_urdf_chain_of_the_controller_s_parameters():
    """Two joints with roll-pitch-yaw frames and a rotated tool: MuJoCo's site pose and Jacobian of the model equal
    the chain written out with numpy (URDF: the joint frame is Trans(xyz) Rz(y) Ry(p) Rx(r) in its parent's)."""
    import mujoco

    joints = [([0, 0, 1, 0, 0, 0], [0.0, 0.0, 0.1], [0.2, -0.1, 0.3]),
              ([0, 1, 0, 0, 0, 0], [0.25, 0.02, 0.0], [0.0, 0.4, -0.2])]
    tool = [0.1, 0.0, 0.03, 0.0, 0.0, 0.5]
    model = kinematic_model(joints, tool)
    data = mujoco.MjData(model)
    q = np.array([0.7, -0.4])
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)

    def chain(q):
        R, p = np.eye(3), np.zeros(3)
        for (axis, xyz, (r, pi, y)), qi in zip(joints, q):
            p = p + R @ np.asarray(xyz)
            R = R @ _rot("z", y) @ _rot("y", pi) @ _rot("x", r)
            R = R @ _rot("z" if axis[2] else "y", qi)
        return p + R @ np.asarray(tool[:3]), R @ _rot("z", 0.5)

    p, R = chain(q)
    np.testing.assert_allclose(data.site_xpos[0], p, atol=1e-12)
    np.testing.assert_allclose(data.site_xmat[0].reshape(3, 3), R, atol=1e-12)
    mujoco.mj_comPos(model, data)
    jacp = np.zeros((3, 2))
    mujoco.mj_jacSite(model, data, jacp, None, 0)
    eps = 1e-6
    fd = np.column_stack([(chain(q + eps * e)[0] - chain(q - eps * e)[0]) / (2 * eps) for e in np.eye(2)])
    np.testing.assert_allclose(jacp, fd, atol=1e-8)
    with pytest.raises(ValueError, match="joint 1's axis .* is not a unit rotation"):
        kinematic_model([([0, 0, 0, 0, 1, 0], [0, 0, 0], [0, 0, 0])], tool)


# ---- the shared parts and drivers by name


def test_settling_takes_a_window_of_readings_and_checks_its_values():
    reads = iter([(0.0, np.zeros(2)), (0.05, np.full(2, 1e-3)), (0.2, np.full(2, 1e-3)), (0.35, np.full(2, 1e-3))])
    settled = common.wait_settled(lambda: next(reads), np.full(2, 1e-3), common.Settling(), driver="X",
                                  monotonic=lambda: 0.0, sleep=lambda s: None)
    np.testing.assert_allclose(settled, 1e-3)
    with pytest.raises(ValueError, match=r"X: poll_s must be in \(0, 1\], got 0"):
        common.Settling(poll_s=0).check("X")
    with pytest.raises(ValueError, match=r"X: a must be in \(0, 1\], got True"):
        common.check_range("X", "a", True, 0.0, 1.0)
    clock = common.ArmClock()
    assert clock.stamp(1.0, 10.0) == 10.0 and clock.stamp(1.0, 11.0) == 10.0 and clock.stamp(2.0, 12.0) == 12.0


def test_drivers_are_found_by_name_and_a_user_s_module_still_works(tmp_path, monkeypatch):
    import sys

    from selfid_jax.robot.drivers import DRIVERS, check_robot_args, connect, import_driver
    from selfid_jax.robot.drivers.franka import Franka
    from selfid_jax.robot.drivers.load import DriverFailure

    assert import_driver("trossen") is Trossen and import_driver("franka") is Franka
    assert set(DRIVERS) == {"franka", "trossen"}
    check_robot_args(driver="trossen", args={"host": "x"})
    with pytest.raises(ValueError, match=r"driver must be one of franka, trossen or 'package.module:Class', got 'ur'"):
        check_robot_args(driver="ur")
    with pytest.raises(DriverFailure, match="driver trossen failed in connect, before any motion: .*Failed to "
                       r"connect \(TCP\) \(no WidowX AI controller answered at 127.0.0.1: check "
                       r"robot.args.host") as failed:
        connect(driver="trossen", args={"host": "127.0.0.1", "connect_timeout_s": 0.2,
                                        "trossen_arm": fake_trossen_arm(Clock(), fail={"configure":
                                                                                       "Failed to connect (TCP)"})},
                announce=None)
    assert failed.value.exit_code == 3 and failed.value.call == "connect"
    (tmp_path / "my_lab_arm.py").write_text("from test_trossen import ExternalTracker as Arm\n")
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    monkeypatch.delitem(sys.modules, "my_lab_arm", raising=False)
    assert import_driver("my_lab_arm:Arm", tmp_path) is ExternalTracker


# ---- the unmodified vendor driver against trossen-arm-sim's controller (a child process)


@pytest.fixture(scope="module")
def trossen_sim_available():
    pytest.importorskip("trossen_arm", reason="trossen-arm is not installed (pip install '.[test]' brings it)")
    pytest.importorskip("trossen_arm_sim", reason="trossen-arm-sim is not installed (pip install '.[test]')")
    import trossen_reference
    if trossen_reference.port_open():
        pytest.fail(f"127.0.0.1:{trossen_reference.PORT} is in use: stop the other trossen-arm-sim")
    return trossen_reference


@pytest.mark.slow
@pytest.mark.xdist_group("realtime")  # the controller's ports are fixed: one simulator at a time
def test_the_vendor_driver_against_the_simulated_controller(trossen_sim_available):
    """The controller's pose, limits and kinematic parameters through the real driver: the pose agrees with MuJoCo's
    ee_site, the driver's model Jacobian with MuJoCo's; a controller fault is a robot_error (not a lost link); a
    firmware the driver refuses is a DriverFailure (exit 3) naming the versions, with our hint."""
    tr = trossen_sim_available
    from selfid_jax.robot.drivers import connect
    from selfid_jax.robot.drivers.load import DriverFailure

    with tr.controller() as fault:
        arm = Trossen("127.0.0.1", start=HOME, start_time_s=1.0, connect_timeout_s=2.0)
        try:
            obs = arm.read()
            np.testing.assert_allclose(obs.q, HOME, atol=0.01)
            point, _ = tr.ee_point(obs.q)
            np.testing.assert_allclose(obs.position, point, atol=2e-4)  # the controller's parameters: 0.05 mm off
            np.testing.assert_allclose(arm.jacobian(obs.q), tr.ee_jacobian(obs.q, range(6)), atol=5e-4)
            lim = arm.limits()
            assert np.all(lim.lower < obs.q) and np.all(obs.q < lim.upper)
            fault("JOINT_LIMIT_EXCEEDED")
            time.sleep(0.05)
            with pytest.raises(RobotError, match="Joint limit exceeded") as err:
                arm.move(obs.q)
            assert not isinstance(err.value, RobotConnectionError)
        finally:
            with contextlib.suppress(RobotError):  # holding a faulted arm fails; it is released all the same
                arm.close()
        assert arm.arm is None
    with tr.controller(driver_version="1.9"), pytest.raises(DriverFailure, match="major and minor versions of the "
                                                                             "driver and controller firmware must.*"
                                                                             "update the firmware to v1.11"):
        connect(driver="trossen", args={"host": "127.0.0.1", "connect_timeout_s": 2.0}, announce=None)


# ---- end to end: selfid-jax online through trossen-arm against trossen-arm-sim


CONFIG = Path(__file__).resolve().parents[1] / "configs" / "robot" / "online_trossen_sim.yaml"
# Faster than the shipped config, the same checks: a 1 cm star (half the shipped 2 cm) followed at gain 1 with up to
# 1 cm a move (shipped 0.5 and 5 mm): about one move per waypoint, 10 instead of 23 to 25. Each move's trajectory
# takes 0.1 s (shipped 0.2) and a joint within settle_band 5 mrad of its target (shipped 2) that moves less than
# band_tol 2 mrad per 0.1 s (shipped 0.5) is settled: a move takes about 0.5 s instead of 0.7 s (trossen-arm-sim,
# 0.03 rad a joint, the loaded 2-core machine). A sample is unaffected by when it is read: the controller reports
# the joints and the pose of one cycle. The start pose is reached in 0.75 s (shipped 1.5; connecting then takes
# 1.1 s instead of 1.7 s, 2 mrad from it; 0.5 s makes the vendor driver retransmit).
SMALL = ["--set", "path.size=0.01", "--set", "path.gain=1.0", "--set", "path.max_task_step=0.01",
         "--set", "robot.args.move_time_s=0.1", "--set", "robot.args.settle_band=0.005",
         "--set", "robot.args.band_tol=0.002", "--set", "robot.args.start_time_s=0.75"]


@pytest.mark.slow
@pytest.mark.xdist_group("realtime")  # one real-time simulator at a time (test_franka, test_robot_sim too)
def test_online_through_trossen_arm_on_trossen_arm_sim(trossen_sim_available, tmp_path, capsys, monkeypatch):
    """3-D: converges, stops random motion, completes the star; ||J Ĵ - I||_F <= 0.10 against MuJoCo's Jacobian at
    the start pose. 6-D: the simulator killed during self-ID stops the session cleanly (exit 3, a connection
    stop, a stop line in the journal); --resume against a fresh simulator continues the logged samples, converges,
    completes the star and draws the run's figures; ||J Ĵ - I||_F <= 0.30. The driver's reference_error (its model
    from the controller's kinematic parameters) agrees with MuJoCo's. The first two sessions draw no figures (about
    4 s of plotting each, from a log like the third's; the figures are tested in test_online_session and
    test_online_lab)."""
    from selfid_jax.cli import main
    from selfid_jax.sessions import online_figures

    tr = trossen_sim_available
    out3, out6 = tmp_path / "xyz", tmp_path / "6d"
    draw = online_figures.write_figures
    monkeypatch.setattr(online_figures, "write_figures", lambda run_dir: [])
    with tr.trossen_sim(tmp_path / "sim.log"):
        assert main(["online", str(CONFIG), "--out", str(out3), *SMALL, "--quiet"]) == 0
    _, q0 = vendor_sim.converged_then_followed(out3, tr.session_error, 0.10)
    np.testing.assert_allclose(q0, HOME, atol=0.01)  # the driver moved the simulator to its start

    six = ["--set", "selfid.task=x,y,z,rx,ry,rz", *SMALL, "--quiet"]
    with tr.trossen_sim(tmp_path / "sim.log") as sim:
        vendor_sim.killed_during_selfid(lambda: main(["online", str(CONFIG), "--out", str(out6), *six]), sim,
                                        tr.PORT, out6, "UDP")
    capsys.readouterr()
    monkeypatch.setattr(online_figures, "write_figures", draw)
    with tr.trossen_sim(tmp_path / "sim.log"):
        assert main(["online", str(CONFIG), "--out", str(out6), "--resume", *six]) == 0
    vendor_sim.converged_then_followed(out6, tr.session_error, 0.30, reference_tol=0.02, resumed=True)
    assert {f.name for f in (out6 / "figures").iterdir()} >= {"convergence.png", "path.png", "estimate.png"}
