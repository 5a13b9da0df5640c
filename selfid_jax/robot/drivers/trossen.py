"""A Trossen WidowX AI arm over the vendor's trossen-arm (libtrossen_arm): the robot protocol for selfid-jax online.

    pip install "selfid-jax[trossen]"          # trossen-arm, the vendor's driver around libtrossen_arm
    robot: {driver: trossen, args: {host: 192.168.1.2}}

Actuators are the six arm joints, in radians; the gripper is never commanded
and never self-identified (it stays in the mode the arm has it in: idle,
braked, after the driver connects). :meth:`Trossen.limits` reads the joint
limits from the arm's controller (``get_joint_limits``) and narrows each side
by ``limit_margin``; the config's ``safety.limits_lower/upper`` and
``max_step`` narrow them further. :meth:`Trossen.move` sends an absolute
joint target as one vendor trajectory (``set_arm_positions`` over
``move_time_s``, the controller's quintic interpolation), waits that long,
then reads the joints every ``poll_s`` until the arm has **settled**
(:func:`~selfid_jax.robot.drivers.common.wait_settled`: every joint within
``target_tol`` of its target and none moving more than ``settle_tol`` over
the last ``settle_window_s``; RobotError after ``settle_timeout_s``).
``offset_correction`` (off by default: the WidowX AI compensates gravity, and
trossen-arm-sim's joints stop in a friction band on either side of the target
rather than at a constant offset) commands each target minus the offset its
joint held after the last move, as the Franka driver does.

The arm starts where it stands. ``start`` (six joint angles [rad]) moves it
there over ``start_time_s`` when the driver connects, before the runner reads
it: for a simulator, which starts folded at its joints' lower limits (outside
the narrowed limits, where the runner would stop at once). On a real arm,
place the arm instead; ``start`` is a move the runner's envelope does not see.

The tracked point is the end effector of the configured ``end_effector``
(``tracker: end_effector``): the driver's ``get_robot_output`` gives the
joints and the Cartesian pose (translation and angle-axis, base frame) of
one controller cycle, so a sample pairs a joint motion with exactly the pose
change it made; the pose keeps the stamp of the read at which the
controller's cycle timestamp last advanced (a frozen controller reads
stale). Or an external tracker ``"module:Class"`` with ``tracker_args`` (see
:func:`~selfid_jax.robot.drivers.common.load_tracker`). :meth:`Trossen.jacobian`
is the Jacobian of a MuJoCo model built from the kinematic parameters the
controller holds (``get_joints``: each joint's origin and axis;
``t_flange_tool``), the runner's ``reference_error``; the model is checked
against the controller's own pose at the first reading and refused (None)
if they differ by more than 1 mm.

Vendor errors become the runner's (:class:`~selfid_jax.robot.drivers.common.VendorErrors`):
a ``trossen_arm.RuntimeError`` about the link (``Failed to read UDP
message``, a TCP connection refused or timed out, ``configure`` not reaching
the controller within ``connect_timeout_s``) a
:class:`~selfid_jax.robot.protocol.RobotConnectionError` (the ``connection``
stop); one reporting the controller's error state (``Error occurred: Joint
limit exceeded``) or any other vendor error a
:class:`~selfid_jax.robot.protocol.RobotError` (``robot_error``). The driver
clears an arm's error state only when asked (``clear_error: true`` at
connect): recovering is the user's decision. :meth:`Trossen.close` holds the
joints where they are and calls the vendor's ``cleanup``, which puts them in
idle mode (braked on the arm).

The driver refuses a controller whose firmware major.minor differs from its
own; the ``trossen`` extra pins ``trossen-arm`` to the 1.11 series, which
``trossen-arm-sim`` 0.2 serves (firmware v1.9 to v1.11).
"""

from __future__ import annotations

import contextlib
import re
import time
from typing import Any

import numpy as np

from selfid_jax.robot.drivers.common import (
    CONNECT_TIMEOUT_S,
    ArmClock,
    Hint,
    Settling,
    VendorErrors,
    check_range,
    check_tracker,
    close_tracker,
    corrected_offset,
    import_vendor,
    load_tracker,
    narrow_limits,
    tracker_observation,
    wait_settled,
)
from selfid_jax.robot.protocol import Observation, RobotError, RobotLimits

__all__ = ["HINTS", "Trossen", "kinematic_model", "rotvec_quaternion"]

N_JOINTS = 6  # the arm's joints; the gripper is the controller's seventh
MODEL_TOL_M = 1e-3  # m: the kinematic model's pose must agree with the controller's this well
_NO_OUTPUTS = re.compile(r"Failed to receive initial joint outputs")  # configure: TCP up, no UDP answer in time
_RECONNECT_S = 0.1  # [s] the pause before configuring again after _NO_OUTPUTS
_LINK = re.compile(r"\b(UDP|TCP)\b|initial joint outputs")  # libtrossen_arm's messages about the network link
HINTS = (  # what libtrossen_arm's messages mean for the user, first match wins ({host}: robot.args.host)
    Hint(r"Failed to read TCP message.*(temporarily unavailable|timed out)",
         "the controller at {host} took the connection but did not answer within connect_timeout_s: another client "
         "holds it (a second session, the vendor's demo): end it and run again", ("connect",)),
    Hint(r"Failed to connect|TCP server",
         "no WidowX AI controller answered at {host}: check robot.args.host (the controller's address), that the "
         "controller is powered and on this network; another client connected to it (a second session, the "
         "vendor's demo) also keeps it from answering"),
    Hint(r"firmware|version",
         "the controller's firmware and trossen-arm differ in major.minor version: the trossen extra installs "
         "trossen-arm 1.11; update the firmware to v1.11 or install the trossen-arm of its version"),
    Hint(r"UDP|initial joint outputs",
         "the controller stopped answering: its network link dropped, it was powered off, or the simulator ended; "
         "continue with --resume once it is back"),
    Hint(r"Error occurred",
         "the controller is in an error state (the message says which): clear it at the arm, or, having checked "
         "the arm, connect once with robot.args.clear_error: true"),
)


def rotvec_quaternion(rotvec: np.ndarray) -> np.ndarray:
    """The unit quaternion ``(4,)`` ``(w, x, y, z)`` of a rotation vector ``(3,)`` (angle-axis, rad)."""
    r = np.asarray(rotvec, np.float64)
    theta = float(np.linalg.norm(r))
    scale = np.sin(0.5 * theta) / theta if theta > 1e-8 else 0.5 - theta**2 / 48.0
    return np.concatenate([[np.cos(0.5 * theta)], scale * r])


def _names(kind: Any) -> list[str]:
    """The names a trossen-arm enum (``Model``) or class of standard values (``StandardEndEffector``) offers."""
    members = getattr(kind, "__members__", None)
    if members is not None:
        return sorted(members)
    return sorted(n for n in dir(kind) if not n.startswith("_") and not callable(getattr(kind, n)))


def kinematic_model(joints: list[tuple[Any, Any, Any]], t_flange_tool: Any) -> Any:
    """A MuJoCo model of the arm from the controller's kinematic parameters, its tool at the site ``tool``.

    ``joints``: per arm joint ``(axis (6,), origin_xyz (3,) [m], origin_rpy
    (3,) [rad])`` as trossen-arm's ``Joint`` gives them: the unit twist
    (angular, linear) in the joint frame, and the joint frame in its parent's
    (URDF roll-pitch-yaw, MuJoCo's ``XYZ`` sequence). ``t_flange_tool (6,)``:
    the tool frame in the last joint's frame (translation [m], angle-axis
    [rad]). ValueError for a joint that is not a rotation about its frame's
    origin.
    """
    import mujoco

    spec = mujoco.MjSpec()
    body = spec.worldbody
    for i, (axis, xyz, rpy) in enumerate(joints):
        twist = np.asarray(list(axis), np.float64)
        if twist.shape != (6,) or np.linalg.norm(twist[3:]) > 1e-9 or abs(np.linalg.norm(twist[:3]) - 1.0) > 1e-6:
            raise ValueError(f"joint {i + 1}'s axis {twist.tolist()} is not a unit rotation about its origin")
        quat = np.zeros(4)
        mujoco.mju_euler2Quat(quat, np.asarray(list(rpy), np.float64), "XYZ")
        body = body.add_body(name=f"link_{i + 1}", pos=list(xyz), quat=quat, mass=1.0, inertia=[1e-3] * 3,
                             explicitinertial=True)
        body.add_joint(name=f"joint_{i}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=twist[:3])
    tool = np.asarray(list(t_flange_tool), np.float64)
    body.add_site(name="tool", pos=tool[:3], quat=rotvec_quaternion(tool[3:]))
    return spec.compile()


class Trossen:
    """The robot protocol (:class:`~selfid_jax.robot.protocol.Robot`) over a Trossen WidowX AI arm at ``host``.

    The arguments are the config's ``robot.args``.

    Args:
        host: the arm controller's address (``127.0.0.1`` for ``trossen-arm-sim``).
        model: trossen-arm's ``Model`` name (``wxai_v0``; ``vxai_v0_right``,
            ``vxai_v0_left``).
        end_effector: trossen-arm's ``StandardEndEffector`` name
            (``wxai_v0_follower``, ``wxai_v0_leader``, ``wxai_v0_base``, ...): the
            tool frame the Cartesian pose is of.
        move_time_s: [s] the duration of each move's trajectory.
        max_step: largest joint step one move may command [rad] (the
            runner's cap is the smaller of this and the config's).
        limit_margin: [rad] each joint limit of the controller is narrowed by
            this before the config narrows it further.
        start: six joint angles [rad] to move to when connecting, or None
            (see the module's docstring).
        start_time_s: [s] the duration of that move.
        settle_tol, settle_window_s, target_tol, settle_timeout_s, poll_s, settle_band, band_tol:
            when a move is over (:class:`~selfid_jax.robot.drivers.common.Settling`).
        connect_timeout_s: [s] the longest wait for the controller at connect.
        clear_error: clear the controller's error state when connecting.
        tracker: ``end_effector`` or ``"module:Class"`` of an external
            tracker; ``tracker_args``: its keyword arguments.
        offset_correction: command each target minus the offset its joint
            held after the last move.
        trossen_arm: the ``trossen_arm`` module or a stand-in with its names
            (tests); None imports ``trossen_arm``.
    """

    ARGUMENT_NOTES = {"port": "the controller's ports are fixed (TCP 50001, UDP 50000): robot.args.host is all it "
                              "needs"}

    def __init__(self, host: str, *, model: str = "wxai_v0", end_effector: str = "wxai_v0_follower",
                 move_time_s: float = 0.3, max_step: float = 0.05, limit_margin: float = 0.05,
                 start: list[float] | None = None, start_time_s: float = 3.0, settle_tol: float = 2e-4,
                 settle_window_s: float = 0.1, target_tol: float = 0.01, settle_timeout_s: float = 3.0,
                 poll_s: float = 0.01, settle_band: float = 2e-3, band_tol: float = 5e-4,
                 connect_timeout_s: float = CONNECT_TIMEOUT_S, clear_error: bool = False,
                 tracker: str = "end_effector", tracker_args: dict[str, Any] | None = None,
                 offset_correction: bool = False, trossen_arm: Any = None):
        self.move_time_s = check_range("Trossen", "move_time_s", move_time_s, 0.0, 10.0)
        self.max_step = check_range("Trossen", "max_step", max_step, 0.0, 0.5)
        self.limit_margin = check_range("Trossen", "limit_margin", limit_margin, 0.0, 0.5, include_lo=True,
                                        include_hi=False, unit="rad")
        if not isinstance(host, str) or not host.strip():
            raise ValueError(f"Trossen: host must be the arm controller's address (e.g. 192.168.1.2), got {host!r}")
        self.settling = Settling(settle_tol, settle_window_s, target_tol, settle_timeout_s, poll_s, settle_band,
                                 band_tol).check("Trossen")
        connect_timeout_s = check_range("Trossen", "connect_timeout_s", connect_timeout_s, 0.0, 600.0)
        start_time_s = check_range("Trossen", "start_time_s", start_time_s, 0.0, 60.0)
        start_q = None if start is None else self._target(start, "start")
        check_tracker("Trossen", tracker, tracker_args, ("end_effector",))
        ta = trossen_arm
        if ta is None:
            ta = import_vendor("trossen_arm", driver="Trossen", package="trossen-arm", extra="trossen")
        for arg, kind, name in (("model", "Model", model), ("end_effector", "StandardEndEffector", end_effector)):
            choices = _names(getattr(ta, kind))
            if name not in choices:
                raise ValueError(f"Trossen: {arg} must be one of trossen_arm.{kind}'s {choices}, got {name!r}")
        self.ta, self.host = ta, host
        self.tracker: Any = load_tracker(tracker, tracker_args)
        self.offset_correction = bool(offset_correction)
        self.offset = np.zeros(N_JOINTS)  # [rad] measured minus commanded, at the end of the last move
        self.closed = False
        self._clock = ArmClock()
        self._model: Any = None  # the kinematic model (kinematic_model), built at the first jacobian()
        self._vendor = VendorErrors("Trossen", host, (ta.RuntimeError, ta.LogicError),
                                    lambda err: bool(_LINK.search(str(err))), HINTS)
        self.arm: Any = None
        try:
            with self._vendor("connect"):
                arm = self._configure(getattr(ta.Model, model), getattr(ta.StandardEndEffector, end_effector),
                                      bool(clear_error), connect_timeout_s)
                joints = int(arm.get_num_joints())
                if joints != N_JOINTS + 1:
                    raise RobotError(f"Trossen at {host}: the controller reports {joints} joints, expected "
                                     f"{N_JOINTS} arm joints and a gripper")
                arm.set_arm_modes(ta.Mode.position)
            if start_q is not None:
                with self._vendor("start"):
                    arm.set_arm_positions(start_q.tolist(), start_time_s, False)
                time.sleep(start_time_s)
                wait_settled(lambda: self._state()[:2], start_q, self.settling, driver="Trossen",
                             monotonic=time.monotonic, sleep=time.sleep)
        except BaseException:
            self._release()
            raise

    def _configure(self, model: Any, end_effector: Any, clear_error: bool, timeout_s: float) -> Any:
        """``self.arm``, returned: a vendor driver configured against the controller at ``self.host`` within
        ``timeout_s`` [s].

        libtrossen_arm's ``configure`` bounds only the TCP connection by its timeout: a controller that takes the
        connection but sends no joint outputs within the library's own retransmissions (under a second) fails it
        (:data:`_NO_OUTPUTS`), as a controller that is starting, or a simulator on a busy machine, can. Such a
        failure is tried again with a fresh vendor driver, the failed one cleaned up, until ``timeout_s`` has passed
        since the first try; any other failure, or this one after the deadline, is raised with ``self.arm`` the
        failed driver (the caller releases it). No motion is commanded here."""
        ta = self.ta
        deadline = time.monotonic() + timeout_s
        while True:
            arm = self.arm = ta.TrossenArmDriver()
            try:
                arm.configure(model, end_effector, self.host, clear_error, max(deadline - time.monotonic(), 0.1))
                return arm
            except ta.RuntimeError as err:
                if not _NO_OUTPUTS.search(str(err)) or time.monotonic() + _RECONNECT_S >= deadline:
                    raise
            self.arm = None
            with contextlib.suppress(ta.RuntimeError, ta.LogicError):
                arm.cleanup()
            time.sleep(_RECONNECT_S)

    @staticmethod
    def _target(target: Any, what: str = "target") -> np.ndarray:
        q = np.asarray(target, np.float64)
        if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
            raise RobotError(f"Trossen: {what} must be {N_JOINTS} finite joint angles, got {np.ravel(q).tolist()}")
        return q

    def _check_open(self) -> None:
        if self.closed:
            raise RobotError("the Trossen driver is closed")

    def limits(self) -> RobotLimits:
        """The controller's arm joint limits narrowed by ``limit_margin``, and ``max_step``, all ``(6,)`` [rad]."""
        self._check_open()
        with self._vendor("get_joint_limits"):
            limits = list(self.arm.get_joint_limits())[:N_JOINTS]
        if len(limits) != N_JOINTS:
            raise RobotError(f"Trossen at {self.host}: the controller gives {len(limits)} joint limits, expected "
                             f"{N_JOINTS}")
        return narrow_limits("Trossen", [x.position_min for x in limits], [x.position_max for x in limits],
                             self.limit_margin, self.max_step)

    def _state(self) -> tuple[float, np.ndarray, np.ndarray, float]:
        """One controller cycle: (our monotonic stamp [s], joints (6,) [rad], pose (6,) [m, rad angle-axis], the
        pose's stamp [s])."""
        with self._vendor("read"):
            out = self.arm.get_robot_output()
            q = np.array(list(out.joint.arm.positions), np.float64)
            pose = np.array(list(out.cartesian.positions), np.float64)
            arm_t = float(out.header.timestamp) * 1e-6
        now = time.monotonic()
        if q.shape != (N_JOINTS,) or pose.shape != (6,):
            raise RobotError(f"Trossen at {self.host}: the controller's output has {q.size} arm joints and a "
                             f"{pose.size}-element pose, expected {N_JOINTS} and 6")
        return now, q, pose, self._clock.stamp(arm_t, now)

    def read(self) -> Observation:
        """Joints and the tracked pose of one controller cycle, stamped on ``time.monotonic()``."""
        self._check_open()
        now, q, pose, pose_t = self._state()
        if self.tracker is not None:
            return tracker_observation(self.tracker, now, q)
        return Observation(now, q, pose[:3], rotvec_quaternion(pose[3:]), pose_t, True)

    def model_pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The kinematic model's tool pose at joints ``q (6,)`` [rad]: position (3,) [m] and rotation (3, 3), base
        frame."""
        import mujoco

        model = self._kinematics()
        data = mujoco.MjData(model)
        data.qpos[:] = self._target(q, "q")
        mujoco.mj_kinematics(model, data)
        return data.site_xpos[0].copy(), data.site_xmat[0].reshape(3, 3).copy()

    def jacobian(self, q: np.ndarray) -> np.ndarray | None:
        """The kinematic model's Jacobian ``(6, 6)`` of the tool at joints ``q (6,)`` [rad]: linear [m/rad] over
        angular [rad/rad] velocity, base frame; the runner's reference. None for an external tracker, or where the
        model does not reproduce the controller's pose (see the module's docstring)."""
        import mujoco

        self._check_open()
        if self.tracker is not None:
            return None
        _, q_now, pose, _ = self._state()
        position, _ = self.model_pose(q_now)
        if np.linalg.norm(position - pose[:3]) > MODEL_TOL_M:
            return None
        model = self._kinematics()
        data = mujoco.MjData(model)
        data.qpos[:] = self._target(q, "q")
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
        mujoco.mj_jacSite(model, data, jacp, jacr, 0)
        return np.vstack([jacp, jacr])

    def _kinematics(self) -> Any:
        if self._model is None:
            self._check_open()
            with self._vendor("get_joints"):
                joints = [(j.axis, j.origin_xyz, j.origin_rpy) for j in list(self.arm.get_joints())[:N_JOINTS]]
                tool = self.arm.get_end_effector().t_flange_tool
            try:
                self._model = kinematic_model(joints, tool)
            except ValueError as err:
                raise RobotError(f"Trossen at {self.host}: no kinematic model: {err}") from err
        return self._model

    def move(self, target: np.ndarray) -> None:
        """Move the joints to ``target (6,)`` [rad] and return once the arm has settled there (or raise)."""
        self._check_open()
        target = self._target(target)
        command = target - self.offset if self.offset_correction else target
        with self._vendor("move"):
            self.arm.set_arm_positions(command.tolist(), self.move_time_s, False)
        time.sleep(self.move_time_s)
        q = wait_settled(lambda: self._state()[:2], target, self.settling, driver="Trossen",
                         monotonic=time.monotonic, sleep=time.sleep)
        if self.offset_correction:
            self.offset = corrected_offset(self.offset, q, target, self.settling.target_tol)

    def _release(self) -> None:
        """The vendor's cleanup (joints idle, link closed); it logs, rather than raises, what fails on a lost link."""
        arm, self.arm = self.arm, None
        if arm is not None:
            try:
                with self._vendor("cleanup"):
                    arm.cleanup()
            finally:
                close_tracker(self.tracker)

    def close(self) -> None:
        """Hold the joints where they are, release the arm (the vendor's cleanup) and the external tracker
        (idempotent)."""
        if self.closed:
            return
        self.closed = True
        try:
            with self._vendor("stop"):
                q = np.array(list(self.arm.get_arm_positions()), np.float64)
                self.arm.set_arm_positions(q.tolist(), 0.0, False)
        finally:
            self._release()
