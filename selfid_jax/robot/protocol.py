"""The robot protocol: what a driver for a real (or virtual) arm or hand implements, and nothing more.

A driver reads a timestamped actuator position and tracker pose
(:meth:`Robot.read`), commands an absolute actuator target (:meth:`Robot.move`),
reports its limits (:meth:`Robot.limits`) and closes (:meth:`Robot.close`).
Everything else (drawing actuations within ``m_a`` and the limits, the
estimator, the convergence test, the safety envelope, the log) belongs to the
online runner (:mod:`selfid_jax.robot.live`), so a driver stays a few lines
over the vendor's API. numpy in, numpy out; no JAX here.

Units: actuator positions in the actuator's own units (rad for revolute
joints, m for prismatic ones); tracker positions in metres in the tracker's
(world, camera) frame; orientations as unit quaternions ``(w, x, y, z)``;
times in seconds on the driver's monotonic clock.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np

__all__ = ["Observation", "RobotLimits", "Robot", "RobotError", "RobotConnectionError", "check_limits", "joint_labels"]


class RobotError(RuntimeError):
    """A driver could not do what it was asked (a refused command, a fault the robot reported)."""


class RobotConnectionError(RobotError):
    """The connection to the robot was lost or timed out: the runner stops, nothing more is commanded."""


class Observation(NamedTuple):
    """One reading of the robot and its tracker.

    ``t`` is when the actuator positions were read; ``tracker_t`` is when the
    tracker pose was measured (older than ``t`` by the tracker's latency; it
    does not advance while the marker is lost). ``valid`` is False when the
    tracker reports no pose (a dropout): ``position``/``quaternion`` then hold
    the last good pose or NaN and must not be used.
    """

    t: float  # s, time of the actuator reading
    q: np.ndarray  # (n,) actuator positions (rad or m)
    position: np.ndarray  # (3,) tracked point, m, tracker frame
    quaternion: np.ndarray  # (4,) (w, x, y, z) orientation of the tracked body, tracker frame
    tracker_t: float  # s, time of the tracker measurement
    valid: bool  # False on a tracker dropout


class RobotLimits(NamedTuple):
    """What a robot allows: ``(n,)`` position limits and the largest single commanded step (actuator units)."""

    lower: np.ndarray  # (n,) lowest actuator position
    upper: np.ndarray  # (n,) highest actuator position
    max_step: np.ndarray  # (n,) largest |target - q| the robot accepts in one move


@runtime_checkable
class Robot(Protocol):
    """A driver. ``move`` returns once the command is sent (not when the motion ends); the runner waits its
    settle time and then calls ``read``. Any method may raise :class:`RobotConnectionError`."""

    def limits(self) -> RobotLimits:
        """The actuator limits (constant for a session)."""
        ...

    def read(self) -> Observation:
        """The latest actuator positions and tracker pose."""
        ...

    def move(self, target: np.ndarray) -> None:
        """Command the actuators towards the absolute position ``target (n,)``."""
        ...

    def close(self) -> None:
        """Stop the robot where it is and release the connection (idempotent)."""
        ...

    # Optional: a driver with a kinematic model of its arm may also define
    #     jacobian(q (n,)) -> (6, n)
    # the model's Jacobian of the tracked point at joints q: rows x, y, z [m per actuator unit] and rx, ry, rz
    # [rad per actuator unit] (the angular velocity), in the tracker's frame, or None where it has no model of
    # the tracked point (an external tracker). The runner calls it once, where
    # self-ID starts, logs it and reports the estimate against it (summary.json reference_error, the estimate
    # figure). It never moves the robot.
    #
    # Optional: a driver may also have an attribute
    #     joint_names: a sequence of n strings, the vendor's names of the actuators in order
    # which the runner's messages use beside the 1-based joint number (joint_labels).
    #
    # Optional: a driver may state its arm's reach, as attributes
    #     reach: the farthest [m] its flange (the tracked point, with tool_offset 0) gets from a point fixed to its base
    #     tool_offset: how far [m] beyond the flange the tracked point is, where the driver knows it
    # The runner then refuses, before any motion, a waypoint farther from the tracked point than two positions of it
    # can be apart (safety.reach_bound: 2 (reach + tool_offset), with safety.TOOL_MARGIN for an unstated offset).


def check_limits(limits: RobotLimits, n: int | None = None) -> RobotLimits:
    """``limits`` as float64 ``(n,)`` arrays, with ``lower < upper`` and ``max_step > 0`` everywhere, finite.

    A single number among them applies to every actuator (``n`` from the
    others, or the given ``n``); all three single numbers are refused (the
    number of actuators would be a guess). Raises ValueError naming the field
    and actuator otherwise (a driver's limits are checked before any motion).
    """
    arrays = [np.asarray(x, np.float64) for x in limits]
    if n is None:
        sizes = {x.shape[0] for x in arrays if x.ndim == 1}
        if not sizes:
            raise ValueError("robot limits: lower, upper and max_step are all single numbers; give at least one "
                             "of them per actuator, shape (n,) (the others then apply to every actuator)")
        if len(sizes) > 1:
            raise ValueError("robot limits: lower, upper and max_step have different lengths "
                             f"{tuple(x.shape for x in arrays)}; give one value per actuator")
        n = sizes.pop()
    lower, upper, step = (np.full(n, float(x)) if x.ndim == 0 else x for x in arrays)
    for name, x in (("lower", lower), ("upper", upper), ("max_step", step)):
        if x.shape != (n,):
            raise ValueError(f"robot limits: {name} has shape {x.shape}, expected ({n},)")
        bad = np.flatnonzero(~np.isfinite(x))
        if bad.size:
            raise ValueError(f"robot limits: {name}[{bad[0]}] is {x[bad[0]]}, must be finite")
    bad = np.flatnonzero(lower >= upper)
    if bad.size:
        i = bad[0]
        raise ValueError(f"robot limits: actuator {i} has lower {lower[i]} >= upper {upper[i]}")
    bad = np.flatnonzero(step <= 0)
    if bad.size:
        raise ValueError(f"robot limits: max_step[{bad[0]}] is {step[bad[0]]}, must be > 0")
    return RobotLimits(lower, upper, step)


def joint_labels(robot: object, n: int) -> list[str]:
    """How the runner's messages name actuator ``i`` (0-based) of ``robot``: ``"joint i+1"``, 1-based as drivers
    and vendors count, followed by the driver's name in brackets where it has ``joint_names`` (``n`` distinct
    non-empty strings; anything else is ignored): e.g. ``"joint 2 (shoulder_lift_joint)"``."""
    try:
        names = getattr(robot, "joint_names", None)
        names = None if names is None or isinstance(names, (str, bytes)) else [str(x) for x in names]
    except Exception:  # noqa: BLE001 - a driver's property that fails: number the joints, the names are cosmetic
        names = None
    if names is not None and (len(names) != n or len(set(names)) != n or not all(x.strip() for x in names)):
        names = None
    return [f"joint {i + 1}" + ("" if names is None else f" ({names[i]})") for i in range(n)]
