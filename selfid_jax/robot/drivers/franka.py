"""A Franka arm (FR3, Panda) over libfranka, through ``franky-control``: the robot protocol for ``selfid-jax online``.

    pip install "selfid-jax[franka]"          # franky-control, which bundles libfranka
    robot: {driver: franka, args: {host: 172.16.0.2}}     # or "selfid_jax.robot.drivers.franka:Franka"

Actuators are the seven joints, in radians. :meth:`Franka.limits` reads the
joint limits from the arm's own model (the URDF the arm serves) and narrows
each side by ``limit_margin``; the config's ``safety.limits_lower/upper`` and
``max_step`` narrow them further. :meth:`Franka.move` sends an absolute joint
target as one franky ``JointMotion`` (libfranka's joint-position interface,
scaled by ``dynamics``), which returns when the planned trajectory ends, not
when the arm is still; it then reads the joints every ``poll_s`` until the
arm has **settled**: every joint within ``target_tol`` of its target and
moving less than ``settle_tol`` over the last ``settle_window_s``, or, within
``settle_band`` (2 mrad) of its target, less than ``band_tol`` (0.5 mrad):
franky-sim's joint 7 creeps back and forth in a stick-slip band of about
±1.8 mrad for seconds after a move, more than ``settle_tol`` in one window of
five, and one session in 16 used to stop on it. An arm that has not settled
after ``settle_timeout_s`` raises :class:`RobotError` (a ``robot_error``
stop) naming the joint, how far off it is and how far it still moves: a
sample then always pairs two settled poses.
A joint controller holds a joint a little off its setpoint under load
(franky-sim's FR3 holds joint 7 1.7 mrad below it, whatever the move): the
runner asks for a target measured from where the joints are, so an
uncorrected offset would add itself to every move and walk the joint away.
With ``offset_correction`` (on by default) the driver commands ``target``
minus the offset each joint held at the end of its last move (each at most
``target_tol``), so the joints land on the runner's target; the runner pairs
measured joints with measured poses either way.

The tracked point is the arm's own end-effector pose (``tracker:
end_effector``: the flange and the end effector configured at the arm) or
its flange (``tracker: flange``), in the base frame, computed by the arm's
kinematic model (libfranka's ``Model.pose``, 0.06 ms) at the joints of the
same reading, so a sample pairs a joint motion with exactly the pose change
it made. (franky-sim's ``O_T_EE`` follows the commanded joints, which joint 7
misses by up to 1.8 mrad: 10 % error in each sample's rz.) Or an external tracker (a
motion-capture body on the object) given as ``tracker: "module:Class"`` with
``tracker_args``, an object whose ``read()`` returns ``(t, position (3,) [m],
quaternion (4,) (w, x, y, z) or None, valid)`` with ``t`` from
``time.monotonic()`` and whose ``close()``, if any, releases it. Every
observation is stamped with ``time.monotonic()`` when the joints are read;
the arm's own pose keeps the stamp of the read at which the arm's clock last
advanced, so an arm whose state stops updating gives a stale pose (the
runner's ``stale`` stop) rather than a fresh-looking one.

Connecting prints nothing itself (``selfid_jax.robot.drivers.connect``
says "connecting to franka at HOST ..." first) and ends after
``connect_timeout_s`` (5 s) with a :class:`RobotConnectionError`: libfranka
itself waits as long as another client holds the arm (franky-sim answers
one client at a time) and about a minute for an address where nothing
answers. Vendor errors become the runner's: franky's ``NetworkException``
(libfranka's UDP timeout, a refused connection) a
:class:`RobotConnectionError` (the ``connection`` stop), any other franky
exception (a reflex, a refused command, an arm in an error state) a
:class:`RobotError` (``robot_error``), each with libfranka's message and our
hint of what it means beside it (:data:`HINTS`: a wrong address, FCI not
activated, another client, a reflex, a kernel without real time).
The driver never calls ``recover_from_errors``: an arm in an error state is
refused before the first move, and recovering is the user's decision at the
arm. :meth:`Franka.close` stops any motion and disconnects. The parts every
vendor's driver shares (argument checks, limits, settling, the arm's clock,
vendor errors, an external tracker) are :mod:`selfid_jax.robot.drivers.common`'s.
"""

from __future__ import annotations

import functools
import time
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np

from selfid_jax.robot.drivers.common import (
    CONNECT_TIMEOUT_S,
    ArmClock,
    Hint,
    Settling,
    VendorErrors,
    call_within,
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

__all__ = ["HINTS", "Franka", "urdf_joint_limits"]

N_JOINTS = 7
REACH = 0.855
"""[m] Franka's stated maximum reach of the FR3 and the Panda (855 mm, to the flange): :attr:`Franka.reach`."""

HINTS = (  # what libfranka's messages mean for the user, first match wins ({host}: robot.args.host)
    Hint(r"FCI refused|enable FCI",
         "nothing at {host} accepts libfranka's connection on port 1337: check that robot.args.host is the arm's "
         "FCI address, that the arm is on with its joints unlocked and FCI activated in Desk, and, for franky-sim, "
         "that it runs and listens at that address"),
    Hint(r"host not found|resolve",
         "{host} is not a known host name: check robot.args.host (the arm's FCI address, e.g. 172.16.0.2)"),
    Hint(r"TCP connection got interrupted|connection timeout|timed out|unreachable",
         "{host} does not answer: check robot.args.host, that the arm is on and this computer is on its network "
         "(a cable to the arm's control box, an address on its subnet)"),
    Hint(r"realtime|real-time|SCHED_FIFO",
         "this computer runs no real-time kernel: set robot.args.realtime: false for a simulator or a bench test; "
         "a real arm needs a real-time kernel (libfranka's docs)"),
    Hint(r"incompatible|version",
         "libfranka (franky-control) and the arm's system version do not match: install the franky-control "
         "built for the arm's version"),
    Hint(r"reflex",
         "the arm stopped itself (a collision or a limit reflex): clear the error at the arm (Desk, or the "
         "pilot's buttons) and check the joints' clearance before a new session; this driver never recovers by "
         "itself"),
    Hint(r"rejected|not possible in the current mode|user stop",
         "the arm refused the command: its user stop is pressed, its joints are locked, FCI is not active, or "
         "another client controls it"),
    Hint(r"UDP",
         "the arm stopped sending its state: its network link dropped, it was switched off, or the simulator "
         "ended; continue with --resume once it is back"),
)


def urdf_joint_limits(urdf: str, n: int = N_JOINTS) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The position limits ``(lower (n,), upper (n,))`` [rad] and names of the first ``n`` revolute joints of a URDF.

    Joints are taken in the order the URDF lists them (the arm's joint 1 to
    ``n``). Raises ValueError naming what is missing: too few revolute joints,
    or a joint without ``<limit lower upper>``.
    """
    root = ET.fromstring(urdf)
    lower: list[float] = []
    upper: list[float] = []
    names: list[str] = []
    for joint in root.iter("joint"):
        if joint.get("type") != "revolute" or len(names) == n:
            continue
        limit = joint.find("limit")
        name = joint.get("name", "?")
        if limit is None or limit.get("lower") is None or limit.get("upper") is None:
            raise ValueError(f"the arm's URDF gives joint {name!r} no <limit lower upper>")
        lower.append(float(limit.get("lower", "nan")))
        upper.append(float(limit.get("upper", "nan")))
        names.append(name)
    if len(names) < n:
        raise ValueError(f"the arm's URDF has {len(names)} revolute joints ({names}), expected {n}")
    return np.array(lower), np.array(upper), names


def _silent_arm(host: str) -> str:
    """What an arm that did not answer libfranka's connect in time means: a TCP connection to its port 1337 that
    opens (within 1 s) is an arm that takes connections but serves another client; one that does not, an address
    where nothing answers."""
    import socket

    try:
        with socket.create_connection((host, 1337), timeout=1.0):
            pass
    except OSError:
        return (f"nothing at {host} answers on libfranka's port 1337: check robot.args.host (the arm's FCI "
                "address), that the arm is on and this computer is on its network")
    return (f"{host} takes connections on port 1337 but does not answer as an arm: another client holds the arm "
            "(a second session, a franky or libfranka program: end it and run again), or robot.args.host is not the "
            "arm's FCI address (raise robot.args.connect_timeout_s only for an arm that is slow to answer)")


class Franka:
    """The robot protocol (:class:`~selfid_jax.robot.protocol.Robot`) over a Franka arm at ``host``.

    The arguments are the config's ``robot.args``.

    Args:
        host: the arm's FCI address (``127.0.0.1`` for ``franky-sim``).
        dynamics: franky's relative dynamics factor in (0, 1] for every move:
            the fraction of the arm's velocity, acceleration and jerk limits
            a move may use.
        max_step: largest joint step one move may command [rad] (the
            runner's cap is the smaller of this and the config's).
        limit_margin: [rad] each joint limit of the arm's model is narrowed
            by this before the config narrows it further.
        settle_tol: [rad] a joint that moved more than this over the last
            ``settle_window_s`` is still moving.
        settle_window_s: [s] the window of that test.
        target_tol: [rad] a settled joint is within this of its target.
        settle_timeout_s: [s] after the move returns, the longest wait for
            the arm to settle; then :class:`RobotError`.
        poll_s: [s] between joint reads while settling.
        settle_band: [rad] within this of its target a joint may still
            creep (a stick-slip band) ...
        band_tol: [rad] ... by at most this per ``settle_window_s``.
        connect_timeout_s: [s] the longest wait for the arm to accept the
            connection (libfranka waits while another client holds the arm);
            then :class:`RobotConnectionError`.
        realtime: False to connect without a real-time kernel
            (``RealtimeConfig.Ignore``: a simulator, or a test bench); a real
            arm should run on a real-time kernel.
        tracker: ``end_effector``, ``flange`` or ``"module:Class"`` of an
            external tracker (see the module's docstring).
        tracker_args: keyword arguments of the external tracker's class.
        offset_correction: command each target minus the offset its joint
            held after the last move (see the module's docstring).
        franky: the ``franky`` module or a stand-in with its names (tests);
            None imports ``franky``.
    """

    ARGUMENT_NOTES = {"port": "libfranka always uses the arm's port 1337: robot.args.host is all it needs"}

    def __init__(self, host: str, *, dynamics: float = 0.1, max_step: float = 0.05, limit_margin: float = 0.05,
                 settle_tol: float = 2e-4, settle_window_s: float = 0.1, target_tol: float = 0.01,
                 settle_timeout_s: float = 3.0, poll_s: float = 0.01, settle_band: float = 2e-3,
                 band_tol: float = 5e-4, connect_timeout_s: float = CONNECT_TIMEOUT_S, realtime: bool = True,
                 tracker: str = "end_effector", tracker_args: dict[str, Any] | None = None,
                 offset_correction: bool = True, franky: Any = None):
        if not isinstance(host, str) or not host.strip():
            raise ValueError(f"Franka: host must be the arm's FCI address (e.g. 172.16.0.2), got {host!r}")
        check_range("Franka", "dynamics", dynamics, 0.0, 1.0)
        check_range("Franka", "max_step", max_step, 0.0, 0.5)
        connect_timeout_s = check_range("Franka", "connect_timeout_s", connect_timeout_s, 0.0, 600.0, unit="s")
        self.settling = Settling(settle_tol, settle_window_s, target_tol, settle_timeout_s, poll_s, settle_band,
                                 band_tol).check("Franka")
        check_range("Franka", "limit_margin", limit_margin, 0.0, 0.5, include_lo=True, include_hi=False, unit="rad")
        check_tracker("Franka", tracker, tracker_args, ("end_effector", "flange"))
        if franky is None:
            franky = import_vendor("franky", driver="Franka", package="franky-control", extra="franka")
        self.franky, self.host = franky, host
        self.dynamics, self.max_step, self.limit_margin = float(dynamics), float(max_step), float(limit_margin)
        self.tracker_kind = tracker
        self.tracker: Any = load_tracker(tracker, tracker_args)
        self.offset_correction = bool(offset_correction)
        self.offset = np.zeros(N_JOINTS)  # [rad] measured minus commanded, at the end of the last move
        self.closed = False
        self._clock = ArmClock()  # the arm's clock at the last read, and our stamp of the read it advanced at
        self._pose_t = -np.inf  # [s] the stamp of the last read's pose
        self._vendor = VendorErrors("Franka", host, franky.Exception,
                                    lambda err: isinstance(err, franky.NetworkException), HINTS)
        realtime_config = franky.RealtimeConfig.Enforce if realtime else franky.RealtimeConfig.Ignore
        with self._vendor("connect"):
            self.robot = call_within(functools.partial(franky.Robot, host, realtime_config=realtime_config),
                                     connect_timeout_s, what=f"Franka connect at {host}",
                                     hint=functools.partial(_silent_arm, host))
            self.robot.relative_dynamics_factor = self.dynamics

    @property
    def reach(self) -> float | None:
        """[m] The arm's stated reach (:data:`REACH`) where the tracked point is on the arm (``end_effector`` or
        ``flange``; the runner allows a tool beyond it: no ``tool_offset``); None with an external tracker, whose
        point may be anywhere on what the arm holds (the protocol's optional ``reach``)."""
        return REACH if self.tracker is None else None

    def _check_open(self) -> None:
        if self.closed:
            raise RobotError("the Franka driver is closed")

    def limits(self) -> RobotLimits:
        """The joint limits of the arm's model narrowed by ``limit_margin``, and ``max_step``, all ``(7,)`` [rad]."""
        self._check_open()
        with self._vendor("model_urdf"):
            urdf = self.robot.model_urdf
        try:
            lower, upper, _ = urdf_joint_limits(urdf)
        except (ValueError, ET.ParseError) as err:
            raise RobotError(f"Franka at {self.host}: the arm's model gives no joint limits: {err}") from err
        return narrow_limits("Franka", lower, upper, self.limit_margin, self.max_step)

    def _state(self) -> tuple[float, np.ndarray, Any]:
        """The arm's state now: (our monotonic stamp [s], joints (7,) [rad], franky's RobotState)."""
        with self._vendor("read"):
            state = self.robot.state
        now = time.monotonic()
        self._pose_t = self._clock.stamp(float(state.time.to_sec()), now)
        return now, np.array(state.q, np.float64), state

    def read(self) -> Observation:
        """Joints and the tracked pose, both stamped on ``time.monotonic()`` (see the module's docstring)."""
        self._check_open()
        now, q, state = self._state()
        if self.tracker is not None:
            return tracker_observation(self.tracker, now, q)
        frame = self.franky.Frame.EndEffector if self.tracker_kind == "end_effector" else self.franky.Frame.Flange
        with self._vendor("model pose"):
            pose = self.robot.model.pose(frame, q, state.F_T_EE, state.EE_T_K)
        xyzw = np.asarray(pose.quaternion, np.float64)  # franky orders a quaternion (x, y, z, w)
        return Observation(now, q, np.array(pose.translation, np.float64), xyzw[[3, 0, 1, 2]], self._pose_t, True)

    def jacobian(self, q: np.ndarray) -> np.ndarray | None:
        """The arm's model Jacobian ``(6, 7)`` of the tracked point at joints ``q (7,)`` [rad]: libfranka's zero
        Jacobian (linear [m/rad] over angular [rad/rad] velocity, base frame) of the end effector or flange; the
        runner's reference for the estimate. None for an external tracker (the arm has no model of it)."""
        self._check_open()
        if self.tracker is not None:
            return None
        _, _, state = self._state()
        frame = self.franky.Frame.EndEffector if self.tracker_kind == "end_effector" else self.franky.Frame.Flange
        with self._vendor("model zero_jacobian"):
            return np.array(self.robot.model.zero_jacobian(frame, np.asarray(q, np.float64), state.F_T_EE,
                                                           state.EE_T_K), np.float64)

    def move(self, target: np.ndarray) -> None:
        """Move the joints to ``target (7,)`` [rad] and return once the arm has settled there (or raise)."""
        self._check_open()
        target = np.asarray(target, np.float64)
        if target.shape != (N_JOINTS,) or not np.all(np.isfinite(target)):
            raise RobotError(f"Franka: target must be 7 finite joint angles, got {target.tolist()}")
        franky = self.franky
        with self._vendor("move"):
            if self.robot.has_errors:
                raise RobotError(f"Franka at {self.host} reports errors {self.robot.state.current_errors}: "
                                 "clear them at the arm (this driver does not recover from errors by itself)")
            command = target - self.offset if self.offset_correction else target
            self.robot.move(franky.JointMotion(franky.JointState(command.tolist())))
        q = wait_settled(lambda: self._state()[:2], target, self.settling, driver="Franka",
                         monotonic=time.monotonic, sleep=time.sleep)
        if self.offset_correction:
            self.offset = corrected_offset(self.offset, q, target, self.settling.target_tol)

    def close(self) -> None:
        """Stop any motion, release the external tracker and disconnect (idempotent)."""
        if self.closed:
            return
        self.closed = True
        try:
            with self._vendor("stop"):
                self.robot.stop()
        finally:
            self.robot = None
            close_tracker(self.tracker)
