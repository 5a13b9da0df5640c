"""A Franka arm (FR3, Panda) over libfranka, through ``franky-control``: the robot protocol for ``selfid-jax online``.

    pip install "selfid-jax[franka]"          # franky-control, which bundles libfranka
    robot: {driver: "selfid_jax.robot.drivers.franka:Franka", args: {host: 172.16.0.2}}

Actuators are the seven joints, in radians. :meth:`Franka.limits` reads the
joint limits from the arm's own model (the URDF the arm serves) and narrows
each side by ``limit_margin``; the config's ``safety.limits_lower/upper`` and
``max_step`` narrow them further. :meth:`Franka.move` sends an absolute joint
target as one franky ``JointMotion`` (libfranka's joint-position interface,
scaled by ``dynamics``), which returns when the planned trajectory ends, not
when the arm is still; it then reads the joints every ``poll_s`` until the
arm has **settled**: every joint within ``target_tol`` of its target and none
moving more than ``settle_tol`` over the last ``settle_window_s``. An arm that
has not settled after ``settle_timeout_s`` raises :class:`RobotError` (a
``robot_error`` stop): a sample then always pairs two settled poses.
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

Vendor errors become the runner's: franky's ``NetworkException`` (libfranka's
UDP timeout, a refused connection) a :class:`RobotConnectionError` (the
``connection`` stop), any other franky exception (a reflex, a refused
command, an arm in an error state) a :class:`RobotError` (``robot_error``).
The driver never calls ``recover_from_errors``: an arm in an error state is
refused before the first move, and recovering is the user's decision at the
arm. :meth:`Franka.close` stops any motion and disconnects.
"""

from __future__ import annotations

import contextlib
import importlib
import time
import xml.etree.ElementTree as ET
from collections import deque
from collections.abc import Iterator
from typing import Any

import numpy as np

from selfid_jax.robot.protocol import Observation, RobotConnectionError, RobotError, RobotLimits

__all__ = ["Franka", "urdf_joint_limits"]

N_JOINTS = 7


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

    def __init__(self, host: str, *, dynamics: float = 0.1, max_step: float = 0.05, limit_margin: float = 0.05,
                 settle_tol: float = 2e-4, settle_window_s: float = 0.1, target_tol: float = 0.01,
                 settle_timeout_s: float = 3.0, poll_s: float = 0.01, realtime: bool = True,
                 tracker: str = "end_effector", tracker_args: dict[str, Any] | None = None,
                 offset_correction: bool = True, franky: Any = None):
        for name, value, lo, hi in (("dynamics", dynamics, 0.0, 1.0), ("max_step", max_step, 0.0, 0.5),
                                    ("settle_tol", settle_tol, 0.0, 0.1), ("target_tol", target_tol, 0.0, 0.5),
                                    ("settle_window_s", settle_window_s, 0.0, 10.0),
                                    ("settle_timeout_s", settle_timeout_s, 0.0, 600.0), ("poll_s", poll_s, 0.0, 1.0)):
            if not (isinstance(value, int | float) and lo < float(value) <= hi):
                raise ValueError(f"Franka: {name} must be in ({lo:g}, {hi:g}], got {value!r}")
        if not (isinstance(limit_margin, int | float) and 0.0 <= limit_margin < 0.5):
            raise ValueError(f"Franka: limit_margin must be in [0, 0.5) rad, got {limit_margin!r}")
        if tracker not in ("end_effector", "flange") and ":" not in tracker:
            raise ValueError(f"Franka: tracker must be 'end_effector', 'flange' or 'module:Class', got {tracker!r}")
        if tracker_args and ":" not in tracker:
            raise ValueError("Franka: tracker_args are for an external tracker ('module:Class')")
        if franky is None:
            try:
                franky = importlib.import_module("franky")
            except ImportError as err:
                raise RobotError("the Franka driver needs franky-control: pip install \"selfid-jax[franka]\" "
                                 f"({err})") from err
        self.franky, self.host = franky, host
        self.dynamics, self.max_step, self.limit_margin = float(dynamics), float(max_step), float(limit_margin)
        self.settle_tol, self.settle_window_s, self.target_tol = float(settle_tol), float(settle_window_s), \
            float(target_tol)
        self.settle_timeout_s, self.poll_s = float(settle_timeout_s), float(poll_s)
        self.tracker_kind = tracker
        self.tracker: Any = None
        if ":" in tracker:
            module, name = tracker.split(":", 1)
            self.tracker = getattr(importlib.import_module(module), name)(**(tracker_args or {}))
        self.offset_correction = bool(offset_correction)
        self.offset = np.zeros(N_JOINTS)  # [rad] measured minus commanded, at the end of the last move
        self.closed = False
        self._robot_t = -np.inf  # the arm's clock [s] at the last read, and our stamp of the read it advanced at
        self._pose_t = -np.inf
        realtime_config = franky.RealtimeConfig.Enforce if realtime else franky.RealtimeConfig.Ignore
        with self._vendor("connect"):
            self.robot = franky.Robot(host, realtime_config=realtime_config)
            self.robot.relative_dynamics_factor = self.dynamics

    @contextlib.contextmanager
    def _vendor(self, call: str) -> Iterator[None]:
        """Turn franky's exceptions inside the block into the runner's (a lost link, or any other fault)."""
        try:
            yield
        except self.franky.NetworkException as err:
            raise RobotConnectionError(f"Franka {call} at {self.host}: {err}") from err
        except self.franky.Exception as err:
            raise RobotError(f"Franka {call} at {self.host}: {type(err).__name__}: {err}") from err

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
        return RobotLimits(lower + self.limit_margin, upper - self.limit_margin, np.full(N_JOINTS, self.max_step))

    def _state(self) -> tuple[float, np.ndarray, Any]:
        """The arm's state now: (our monotonic stamp [s], joints (7,) [rad], franky's RobotState)."""
        with self._vendor("read"):
            state = self.robot.state
        now = time.monotonic()
        robot_t = float(state.time.to_sec())
        if robot_t != self._robot_t:
            self._robot_t, self._pose_t = robot_t, now
        return now, np.array(state.q, np.float64), state

    def read(self) -> Observation:
        """Joints and the tracked pose, both stamped on ``time.monotonic()`` (see the module's docstring)."""
        self._check_open()
        now, q, state = self._state()
        if self.tracker is not None:
            t, position, quaternion, valid = self.tracker.read()
            quat = None if quaternion is None else np.asarray(quaternion, np.float64)  # None: position only
            return Observation(now, q, np.asarray(position, np.float64), quat, float(t), bool(valid))  # type: ignore[arg-type]
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
        q = self._settle(target)
        if self.offset_correction:  # half of each landing error: a constant offset goes, friction's sign flips average
            self.offset = np.clip(self.offset + 0.5 * (q - target), -self.target_tol, self.target_tol)

    def _settle(self, target: np.ndarray) -> np.ndarray:
        """Read the joints every ``poll_s`` until settled at ``target`` and return them (7,) [rad]; RobotError after
        ``settle_timeout_s``."""
        start = time.monotonic()
        window: deque[tuple[float, np.ndarray]] = deque()
        while True:
            now, q, _ = self._state()
            window.append((now, q))
            while len(window) > 2 and now - window[1][0] >= self.settle_window_s:
                window.popleft()  # keep one reading at least settle_window_s old: the spread spans the window
            full = len(window) >= 2 and now - window[0][0] >= self.settle_window_s
            qs = np.array([x for _, x in window])
            spread = qs.max(axis=0) - qs.min(axis=0)
            off = np.abs(q - target)
            if full and spread.max() <= self.settle_tol and off.max() <= self.target_tol:
                return q
            if now - start > self.settle_timeout_s:
                i = int(np.argmax(np.maximum(off / self.target_tol, spread / self.settle_tol)))
                raise RobotError(f"Franka: joint {i + 1} did not settle within {self.settle_timeout_s:g} s: "
                                 f"{off[i]:.3g} rad from its target (target_tol {self.target_tol:g}), moved "
                                 f"{spread[i]:.3g} rad in the last {self.settle_window_s:g} s (settle_tol "
                                 f"{self.settle_tol:g})")
            time.sleep(self.poll_s)

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
            if self.tracker is not None and hasattr(self.tracker, "close"):
                self.tracker.close()
