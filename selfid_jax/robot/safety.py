"""The live session's safety envelope, its random self-ID draw, and the check of every reading a driver returns.

numpy only, float64: nothing here is traced. :func:`envelope` intersects the
driver's limits with the user's and refuses an empty or malformed one;
:func:`actuation_target` draws self-ID move ``k`` inside it; and
:func:`check_observation` copies and checks a driver's reading before the
session reads it. :mod:`selfid_jax.robot.session` applies them.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from selfid_jax.robot.options import DIVERGE_DIST, STALE_S
from selfid_jax.robot.protocol import Observation, RobotError, RobotLimits, check_limits

__all__ = ["COMMAND_MEMORY", "TOOL_MARGIN", "Commanded", "Envelope", "Sight", "actuation_target", "angle_between",
           "check_observation", "check_path_reach", "check_room", "envelope", "linear_reach", "reach_bound",
           "tracker_noise"]

TOOL_MARGIN = 0.3
"""[m] Where a driver states its arm's reach but not how far the tracked point is beyond the flange: a tool (a hand
and a marker) up to this long is allowed for."""


class Envelope(NamedTuple):
    """The safety envelope of a session (float64 numpy)."""

    lower: np.ndarray  # (n,) lowest actuator target (actuator units): max of the driver's and the user's
    upper: np.ndarray  # (n,) highest actuator target: min of the driver's and the user's
    max_step: np.ndarray  # (n,) largest |target - q| commanded (actuator units), <= the driver's max_step
    box_low: np.ndarray  # (3,) m, lowest tracked position (tracker frame); -inf: unbounded
    box_high: np.ndarray  # (3,) m, highest tracked position; +inf: unbounded
    stale_s: float  # s: a tracker pose older than this stops the session (watchdog)
    diverge_dist: float  # m: while following, farther than this from the path (its position axes) stops


def envelope(limits: RobotLimits, *, lower=None, upper=None, max_step=None, box_low=None, box_high=None,
             stale_s: float = STALE_S, diverge_dist: float = DIVERGE_DIST) -> Envelope:
    """The :class:`Envelope` of a session: the driver's ``limits`` narrowed by the user's (each optional).

    Raises ValueError naming the field when a user value has the wrong shape,
    is not finite (box bounds may be infinite), or leaves an empty range.
    """
    lim = check_limits(limits)
    n = lim.lower.shape[0]

    def vec(name, x, size, default, finite=True):
        if x is None:
            return np.asarray(default, np.float64)
        v = np.broadcast_to(np.asarray(x, np.float64), (size,)).copy() if np.ndim(x) == 0 else \
            np.asarray(x, np.float64)
        if v.shape != (size,):
            raise ValueError(f"{name}: expected {size} values, got shape {np.shape(x)}")
        if (finite and not np.all(np.isfinite(v))) or np.any(np.isnan(v)):
            raise ValueError(f"{name}: every value must be finite, got {v.tolist()}")
        return v

    lo = np.maximum(lim.lower, vec("lower", lower, n, lim.lower))
    hi = np.minimum(lim.upper, vec("upper", upper, n, lim.upper))
    bad = np.flatnonzero(lo >= hi)
    if bad.size:
        i = bad[0]
        raise ValueError(f"limits: actuator {i} has no room: lower {lo[i]:g} >= upper {hi[i]:g} "
                         f"(driver [{lim.lower[i]:g}, {lim.upper[i]:g}] and the user's limits)")
    step = vec("max_step", max_step, n, lim.max_step)
    if np.any(step <= 0):
        raise ValueError(f"max_step: must be > 0, got {step.tolist()}")
    step = np.minimum(step, lim.max_step)
    blo = vec("box_low", box_low, 3, np.full(3, -np.inf), finite=False)
    bhi = vec("box_high", box_high, 3, np.full(3, np.inf), finite=False)
    bad = np.flatnonzero(blo >= bhi)
    if bad.size:
        raise ValueError(f"box_low[{bad[0]}] = {blo[bad[0]]:g} is not below box_high[{bad[0]}] = {bhi[bad[0]]:g}")
    for name, v in (("stale_s", stale_s), ("diverge_dist", diverge_dist)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name}: must be a finite number > 0, got {v!r}")
    return Envelope(lo, hi, step, blo, bhi, float(stale_s), float(diverge_dist))


def check_room(env: Envelope, m_a: np.ndarray, labels: list[str]) -> None:
    """ValueError naming the first actuator whose range ``upper - lower`` (the driver's limits narrowed by the
    user's) is below its self-ID magnitude ``m_a (n,)``: its random moves could not reach ``m_a``, so self-ID
    would fit its column from moves too short to see beside the others' (a confident, wrong estimate).
    ``labels``: the actuators' names in messages (:func:`~selfid_jax.robot.protocol.joint_labels`)."""
    room = env.upper - env.lower
    bad = np.flatnonzero(room < m_a)
    if bad.size:
        i = bad[0]
        raise ValueError(f"limits: {labels[i]} has a range of {room[i]:.4g} ([{env.lower[i]:.6g}, "
                         f"{env.upper[i]:.6g}], the driver's limits narrowed by safety.limits_lower/upper), below "
                         f"its self-ID magnitude m_a = {m_a[i]:.4g}: self-ID cannot move it by m_a and would "
                         "identify its column from moves too short to trust. Widen its limits, or lower m_a for "
                         "it (m_a per actuator); no move was made")


def reach_bound(robot: object) -> tuple[float, str] | None:
    """The farthest apart [m] two positions of the tracked point can be, and how that follows (words), from a
    driver's optional ``reach`` and ``tool_offset``; None where it states no ``reach``.

    ``reach`` [m]: the farthest the arm's flange (or, with ``tool_offset``
    0, the tracked point itself) gets from a point fixed to its base;
    ``tool_offset`` [m]: how far beyond it the tracked point is, where the
    driver knows (else :data:`TOOL_MARGIN`). Each position is within
    ``reach + tool`` of that base point, so two are at most
    ``2 (reach + tool)`` apart. ValueError naming the attribute where one is
    not a finite number (``reach`` > 0, ``tool_offset`` >= 0) or reading it
    fails.
    """
    values = []
    for name in ("reach", "tool_offset"):
        try:
            v = getattr(robot, name, None)
        except Exception as err:  # noqa: BLE001 - a driver's property that fails: one line naming it
            raise ValueError(f"robot {name}: reading the driver's {name} raised {type(err).__name__}: {err}"
                             ) from None
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer))
                              or not math.isfinite(v) or v < 0 or (name == "reach" and v == 0)):
            raise ValueError(f"robot {name}: the driver states {v!r}; expected metres, a finite number "
                             f"{'> 0' if name == 'reach' else '>= 0'}, or None")
        values.append(None if v is None else float(v))
    reach, tool = values
    if reach is None:
        return None
    if tool is None:
        return 2.0 * (reach + TOOL_MARGIN), (f"2 x (the driver's reach {reach:.4g} m + {TOOL_MARGIN:g} m allowed for "
                                             "a tool: the driver states none)")
    return 2.0 * (reach + tool), f"2 x (the driver's reach {reach:.4g} m + its tool offset {tool:.4g} m)"


def check_path_reach(positions: np.ndarray, bound: tuple[float, str] | None) -> None:
    """ValueError naming the first waypoint whose position offset ``positions (W, 3)`` [m] from where following
    starts is longer than ``bound`` (:func:`reach_bound`: no two positions of the tracked point are farther apart),
    with its distance and the bound; nothing where ``bound`` is None."""
    if bound is None:
        return
    d = np.linalg.norm(np.asarray(positions, np.float64), axis=1)  # (W,) m
    far = np.flatnonzero(d > bound[0])
    if far.size:
        w = int(far[0])
        raise ValueError(f"path: waypoint {w + 1} of {d.shape[0]} is {1e3 * d[w]:.4g} mm from where following "
                         f"starts, out of the arm's reach: no two positions of the tracked point are more than "
                         f"{1e3 * bound[0]:.4g} mm apart ({bound[1]}). No move was made: a path within reach")


def linear_reach(Jinv: np.ndarray, offsets: np.ndarray, q: np.ndarray, lower: np.ndarray,
                 upper: np.ndarray) -> tuple[int, int, float] | None:
    """The first waypoint the estimate says needs an actuator beyond its limits, or None.

    ``Jinv (n, m)`` the inverse Jacobian followed with, ``offsets (W, m)`` the
    waypoints' offsets from the start in task units (m; rad for rotation
    axes), ``q (n,)`` the actuators at the start, ``lower``/``upper (n,)``
    the envelope's limits. Following with a fixed estimate moves the
    actuators by ``Jinv V`` for each commanded twist ``V``, so to first order
    it takes them to ``q + Jinv offsets[w]`` at waypoint ``w``; a waypoint
    where an actuator would need more than twice the room its limit leaves in
    that direction is out of reach within the limits (the factor 2 leaves room
    for the linearization's error over the path). Returns ``(w, i, needed
    position of actuator i)`` for the first such waypoint (0-based).
    """
    d = np.asarray(offsets, np.float64) @ np.asarray(Jinv, np.float64).T  # (W, n) linear actuator change
    room = np.where(d > 0, upper - q, q - lower)  # (W, n) room in each move's direction
    hit = np.argwhere(np.abs(d) > 2.0 * np.maximum(room, 0.0))
    if not hit.size:
        return None
    w, i = (int(x) for x in hit[0])
    return w, i, float(q[i] + d[w, i])


def tracker_noise(positions: np.ndarray, rotvecs: np.ndarray) -> tuple[float, float]:
    """Standard deviation per axis of ``k`` tracker readings of a pose at rest: ``(position [m], rotation [rad])``.

    ``positions (k, 3)`` m; ``rotvecs (k, 3)`` rad, each reading's orientation
    as a rotation vector relative to one of them (small angles). The pooled
    sample standard deviation over the three axes (``k - 1`` degrees of
    freedom each); ``k >= 2``.
    """
    out = []
    for x in (np.asarray(positions, np.float64), np.asarray(rotvecs, np.float64)):
        k = x.shape[0]
        out.append(float(np.sqrt(np.sum((x - x.mean(axis=0)) ** 2) / (3 * (k - 1)))))
    return out[0], out[1]


def actuation_target(seed: int, k: int, q: np.ndarray, m_a: np.ndarray, lower: np.ndarray,
                     upper: np.ndarray, centre: np.ndarray | None = None, wander: float | None = None) -> np.ndarray:
    """Target ``(n,)`` of random self-ID move ``k``: ``q + dtheta``, ``dtheta_i ~ uniform(-m_a_i, m_a_i)``, in limits.

    ``dtheta`` comes from ``numpy.random.default_rng([seed, k])``, so draw ``k``
    is the same in an interrupted and a resumed session. Where ``q_i +
    dtheta_i`` falls outside ``[lower_i, upper_i]`` the move is **reflected**
    (``q_i - dtheta_i``): ``|dtheta_i|`` keeps its uniform distribution on
    ``[0, m_a_i]`` and only its sign depends on the position, which the
    estimator does not mind (Eq. 6 pairs the sign of each actuation with the
    sign of the pose change it caused). Only where both directions leave the
    limits (a range narrower than ``2 m_a_i`` around ``q_i``) is the target
    clipped, which shortens that move. Clipping alone would pile the
    distribution up at the limit with short moves.

    With ``centre (n,)`` and ``wander``, a draw that would end farther than
    ``wander m_a_i`` from ``centre_i``, and farther than its reflection would,
    is reflected the same way (before the limits): the walk stays within
    ``wander m_a`` of the centre, or returns towards it.
    """
    rng = np.random.default_rng([int(seed), int(k)])
    d = rng.uniform(-1.0, 1.0, q.shape[0]) * m_a
    if centre is not None and wander is not None:
        far, back = np.abs(q + d - centre), np.abs(q - d - centre)
        d = np.where((far > wander * m_a) & (back < far), -d, d)
    out = (q + d > upper) | (q + d < lower)
    d = np.where(out, -d, d)
    return np.clip(q + d, lower, upper)


def check_observation(obs: Any, n: int, *, rotation: bool = True) -> Observation:
    """The driver's reading as new float64 arrays of the protocol's shapes; RobotError if it is malformed.

    The arrays are copies (a driver may reuse and update its own). A
    quaternion of None (a position-only tracker) reads as the identity where
    the task has no rotation axes (``rotation`` False). ``valid``
    must be a real boolean (``"False"`` or NaN is a RobotError naming it, not
    a valid reading). A reading flagged valid whose pose is not finite, or
    whose quaternion is zero, is a dropout (``valid`` False).
    """
    try:
        q = np.array(obs.q, np.float64).reshape(-1)
        p = np.array(obs.position, np.float64).reshape(-1)
        if obs.quaternion is None and not rotation:  # a position-only tracker, for a task without rotation axes
            quat = np.array([1.0, 0.0, 0.0, 0.0])
        elif obs.quaternion is None:
            raise RobotError("driver returned quaternion None (a position-only tracker), but the task has rotation "
                             "axes: track the orientation, or give a position-only task")
        else:
            quat = np.array(obs.quaternion, np.float64).reshape(-1)
        t, tt, valid = float(obs.t), float(obs.tracker_t), obs.valid
    except (AttributeError, TypeError, ValueError) as err:
        raise RobotError(f"driver returned a malformed observation: {err}") from None
    if not isinstance(valid, (bool, np.bool_)):  # bool("False") and bool(nan) are True: no coercion
        raise RobotError(f"driver returned valid={valid!r} ({type(valid).__name__}); expected True or False")
    valid = bool(valid)
    if q.shape != (n,) or p.shape != (3,) or quat.shape != (4,):
        raise RobotError(f"driver returned q {q.shape}, position {p.shape}, quaternion {quat.shape}; "
                         f"expected ({n},), (3,), (4,)")
    if not np.all(np.isfinite(q)) or not (math.isfinite(t) and math.isfinite(tt)):
        raise RobotError(f"driver returned a non-finite actuator position or time (q={q.tolist()}, t={t}, "
                         f"tracker_t={tt})")
    if valid and not (np.all(np.isfinite(p)) and np.all(np.isfinite(quat)) and np.linalg.norm(quat) > 0):
        valid = False  # a "valid" pose with NaN in it is a dropout all the same
    return Observation(t, q, p, quat, tt, valid)


# --------------------------------------------------------------------------- after each move


class Sight(NamedTuple):
    """What the runner has seen since the tracked pose last changed (the motion-versus-sight check).

    A change is seen when the tracked position moves more than ``seen_min``
    [m] or the orientation more than ``seen_min_rad`` from ``p``/``quat``;
    until then ``moved`` sums the measured actuator motion ``max_i |dq_i|``
    of every move [actuator units] and ``predicted`` the position change an
    estimate predicts for them, ``||pinv(Jinv) dq||`` [m] (while following).
    """

    p: np.ndarray  # (3,) m, the tracked position when a change was last seen
    quat: np.ndarray  # (4,) its quaternion (w, x, y, z)
    moved: float = 0.0  # actuator units of measured motion since
    predicted: float = 0.0  # m of position change the estimate predicts since (following only)
    moves: int = 0  # moves since


def angle_between(qa: np.ndarray, qb: np.ndarray) -> float:
    """Angle [rad] between two orientations given as quaternions (w, x, y, z), any norm."""
    c = abs(float(np.dot(qa, qb))) / (float(np.linalg.norm(qa)) * float(np.linalg.norm(qb)))
    return 2.0 * math.acos(min(1.0, c))


COMMAND_MEMORY = 0.8
"""Weight of the previous moves in the command-following sums, per move (an effective memory of about 5 moves)."""


class Commanded(NamedTuple):
    """Per actuator, the commanded and the measured motion of the recent moves (the command-following check)."""

    commanded: np.ndarray  # (n,) sum of |target_i - q_i| over the moves, each older one times COMMAND_MEMORY
    along: np.ndarray  # (n,) the same sum of the measured motion along each command, (q'_i - q_i) sign(target_i - q_i)
    moves: int = 0
