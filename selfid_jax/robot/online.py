"""Algorithm 1 live on a robot: random actuations, the jitted per-sample estimator step, then an optional path.

:func:`run_online` drives a :class:`~selfid_jax.robot.protocol.Robot` through
one session in a run directory:

1. **Self-ID** (Algorithm 1). From a fresh tracker reading at rest it draws
   ``dtheta ~ uniform(-m_a, m_a)`` per actuator (:func:`actuation_target`),
   commands ``move(q + dtheta)``, waits ``settle_s`` and reads again; the
   sample is ``(q_new - q_old (n,), V (m,))`` with ``V = [p_t - p_{t-1},
   log(R_t R_{t-1}^T)][axes]`` from the two tracker poses
   (:func:`task_difference`, Eq. 1's pose change). A reading with no pose
   (``valid`` False: a dropout) or whose pose is not newer than the reading
   before the move (a stale tracker) is rejected, counted by reason, and
   followed by a fresh reading at rest (no motion) before the next draw.
   Each accepted sample runs the jitted :func:`selfid_jax.robot.fit.step`
   (update Eq. 6-12, guess Eq. 13, refine Eq. 14, record Sec. IV-D), compiled
   once per ``(n, m, method, dtype)`` (:func:`sample_step`). The first time
   the Sec. IV-D test holds (``state.converged_at >= 1``) self-ID stops:
   **no further random move is ever commanded**, in this session or a
   resumed one. So the robot makes exactly ``converged_at + rejected`` random
   moves.
2. **Follow** (optional, ``OnlineOptions.path``): the converged estimate is
   a fixed inverse Jacobian; each step commands ``q + Jinv @ V`` with ``V =
   gain * (waypoint - x)`` capped at ``max_task_step`` (task units), the
   actuator step scaled down to the envelope's ``max_step`` and clipped to
   its limits; the waypoint advances within ``tol``. Without a path the
   session ends at convergence and the robot stays where it is.

The safety envelope (:class:`Envelope`) holds throughout: every commanded
target is inside the actuator limits (the driver's intersected with the
user's) and within ``max_step`` of the measured position; a measured
position outside the limits, a tracked position outside the task-space box,
a tracker older than ``stale_s`` (the watchdog) or, while following, a
distance from the path above ``diverge_dist`` stops the session at once,
with no further command (the robot stays where it is: the runner makes no
motion the user did not ask for, not even a move back).

Every observation, command, sample (accepted or rejected, with the
estimate's change) and stop is appended to ``RUN/session.jsonl`` as it
happens (:mod:`selfid_jax.robot.journal`: one fsynced JSON line each), so a
crash loses at most the line in flight. ``run_online(..., resume=True)``
reads that log (a cut-short last line is dropped and counted), refuses it if
its header disagrees with the options (n, m, axes, m_a, eps, eps_rel, seed,
method, v_tol, dtype: the error names the field), replays the accepted
samples through the same jitted step, so the estimator state is the one the
interrupted session had, and continues: self-ID from the next draw, or,
if the log had converged, straight to following (from the logged path
anchor and the last waypoint reached).

numpy and JAX only: no files other than the log, no pydantic, no runner (the
``selfid-jax online`` command, :mod:`selfid_jax.app.online`, owns the run
directory's lock, the config and the summary files).
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from selfid_jax.control import paths
from selfid_jax.identify import estimator
from selfid_jax.identify.refine import needs_samples
from selfid_jax.math.checks import float_dtype
from selfid_jax.robot import offline as fit
from selfid_jax.robot.journal import Journal, JournalContents, JournalError, floats, read_journal
from selfid_jax.robot.log import pairs_from_time_series, parse_task
from selfid_jax.robot.protocol import Observation, Robot, RobotConnectionError, RobotError, RobotLimits, check_limits

__all__ = ["LOG_FILE", "Envelope", "FollowOptions", "OnlineOptions", "OnlineResult", "ResumeError", "Stop",
           "actuation_target", "envelope", "follow_offsets", "init_state", "quaternion_matrix", "run_online",
           "host_step", "sample_step", "task_difference"]

LOG_FILE = "session.jsonl"
LOG_VERSION = 1
ONLINE_METHODS = ("closed_form", "optax")


class Stop(enum.StrEnum):
    """Why a session ended."""

    CONVERGED = "converged"  # self-ID met Sec. IV-D and there is no path to follow
    COMPLETED = "completed"  # the path was followed to its last waypoint
    MAX_SAMPLES = "max_samples"  # self-ID made max_samples random moves without converging
    MAX_STEPS = "max_steps"  # following took max_steps moves without reaching the last waypoint
    STALE = "stale"  # the tracker was older than stale_s (watchdog)
    BOX = "box"  # the tracked position left the task-space box (or the path would)
    LIMITS = "limits"  # a measured actuator position outside the limits
    DIVERGENCE = "divergence"  # while following, farther than diverge_dist from the path
    CONNECTION = "connection"  # the driver raised RobotConnectionError
    ROBOT_ERROR = "robot_error"  # the driver raised another RobotError (a refused command, a fault)
    INTERRUPTED = "interrupted"  # KeyboardInterrupt or a stop request


class ResumeError(JournalError):
    """A session log that cannot be resumed with these options; the message names the disagreeing field."""


class Envelope(NamedTuple):
    """The safety envelope of a session (float64 numpy)."""

    lower: np.ndarray  # (n,) lowest actuator target (actuator units): max of the driver's and the user's
    upper: np.ndarray  # (n,) highest actuator target: min of the driver's and the user's
    max_step: np.ndarray  # (n,) largest |target - q| commanded (actuator units), <= the driver's max_step
    box_low: np.ndarray  # (3,) m, lowest tracked position (tracker frame); -inf: unbounded
    box_high: np.ndarray  # (3,) m, highest tracked position; +inf: unbounded
    stale_s: float  # s: a tracker pose older than this stops the session (watchdog)
    diverge_dist: float  # task units (m for position axes): farther than this from the path stops following


class FollowOptions(NamedTuple):
    """The path followed with the converged estimate (a star, :func:`selfid_jax.control.paths.star`)."""

    kind: str = "star"
    size: float = 0.02  # m, outer radius of the star (paths.star size); its top point is where following starts
    plane: str = "xy"  # plane of the star: "xy", "xz" or "yz" (both axes must be task axes)
    gain: float = 0.5  # proportional gain on the task error, per move (dimensionless, in (0, 1])
    tol: float = 0.002  # task units: a waypoint is reached when the task error's norm is at most this
    max_task_step: float = 0.005  # task units: cap on ||V|| per move
    steps: int = 500  # most moves while following (Stop.MAX_STEPS)


class OnlineOptions(NamedTuple):
    """Options of one online session (plain values; :func:`run_online` checks them before any motion)."""

    task: str | Sequence = "x,y,z"  # task axes out of x,y,z,rx,ry,rz (selfid_jax.robot.log.parse_task)
    m_a: float | Sequence[float] = 0.05  # self-ID magnitude (actuator units), scalar or (n,)
    eps: float = 0.0  # Sec. IV-D absolute threshold on ||J_t - J_{t-1}||_F (inverse-Jacobian units)
    eps_rel: float = 0.05  # relative threshold, times ||J_t||_F
    max_samples: int = 200  # most random moves (accepted + rejected samples) before Stop.MAX_SAMPLES
    seed: int = 0  # draw k uses numpy's default_rng([seed, k])
    settle_s: float = 0.2  # s waited after each move before reading (motion time + tracker latency)
    poll_s: float = 0.01  # s between reads while waiting for a fresh tracker pose (no motion)
    method: str = "closed_form"  # Eq. 14 refinement: "closed_form" or "optax"
    v_tol: float = 1e-9  # |V_j| below this does not enter the magnitude mean (Eq. 11)
    lower: Sequence[float] | None = None  # (n,) user actuator limits, intersected with the driver's
    upper: Sequence[float] | None = None
    max_step: float | Sequence[float] | None = None  # user cap on |target - q| (actuator units); None: driver's
    box_low: Sequence[float] | None = None  # (3,) m, task-space box on the tracked position; None: unbounded
    box_high: Sequence[float] | None = None
    stale_s: float = 1.0  # s, watchdog
    diverge_dist: float = 0.05  # task units, divergence stop while following
    path: FollowOptions | None = None  # follow this path after convergence; None: stop at convergence


class OnlineResult(NamedTuple):
    """What a session did (counts over the whole log, resumed sessions included)."""

    status: Stop
    detail: str  # one line: what stopped the session
    estimate: np.ndarray  # (n, m) inverse Jacobian after the last accepted sample (Eq. 14); zeros before any
    state: estimator.EstimatorState  # estimator state (numpy leaves)
    converged_at: int  # 1-based accepted-sample index meeting Sec. IV-D, -1 if never
    samples: int  # accepted samples (estimator steps)
    rejected: dict[str, int]  # rejected samples by reason ("dropout", "stale")
    moves: int  # random self-ID moves issued (== samples + sum(rejected), plus one whose outcome a stop lost)
    follow_steps: int  # moves issued while following
    waypoints: int  # waypoints reached
    waypoints_total: int  # waypoints of the path (0 without one)
    replayed: int  # accepted samples replayed from the log on resume (0 for a fresh session)
    truncated: int  # cut-short log lines dropped on resume (0 or 1)
    step_ms: np.ndarray  # (k,) latency of each estimator step run in this session, ms (replays excluded)
    axes: tuple[int, ...]  # task axes into (x, y, z, rx, ry, rz)
    log: Path  # the session log

    @property
    def converged(self) -> bool:
        return self.converged_at > 0


# --------------------------------------------------------------------------- pieces


def quaternion_matrix(quaternion) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of a quaternion ``(w, x, y, z)`` (normalised here; numpy float64)."""
    w, x, y, z = np.asarray(quaternion, np.float64) / np.linalg.norm(quaternion)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def task_difference(obs: Observation, prev: Observation, axes: Sequence[int]) -> np.ndarray:
    """``V (m,) = [p - p_prev, log(R R_prev^T)][axes]`` between two tracker poses (m; rad for rotation axes).

    :func:`selfid_jax.robot.log.pairs_from_time_series` on the two rows, so an
    online sample is exactly what ``fit`` would form from the same time series.
    """
    p = np.stack([prev.position, obs.position])
    R = None if all(a < 3 for a in axes) else np.stack([quaternion_matrix(prev.quaternion),
                                                         quaternion_matrix(obs.quaternion)])
    return pairs_from_time_series(np.zeros((2, 1)), p, R, axes)[1][0]


def actuation_target(seed: int, k: int, q: np.ndarray, m_a: np.ndarray, lower: np.ndarray,
                     upper: np.ndarray) -> np.ndarray:
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
    """
    rng = np.random.default_rng([int(seed), int(k)])
    d = rng.uniform(-1.0, 1.0, q.shape[0]) * m_a
    out = (q + d > upper) | (q + d < lower)
    d = np.where(out, -d, d)
    return np.clip(q + d, lower, upper)


def envelope(limits: RobotLimits, *, lower=None, upper=None, max_step=None, box_low=None, box_high=None,
             stale_s: float = 1.0, diverge_dist: float = 0.05) -> Envelope:
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


def follow_offsets(path: FollowOptions, axes: Sequence[int]) -> np.ndarray:
    """Waypoint offsets ``(W, m)`` of the path in task coordinates relative to where following starts.

    A star (:func:`selfid_jax.control.paths.star`) in ``path.plane``, rotation
    part zero (the orientation is held), restricted to the task axes; both
    axes of the plane must be task axes.
    """
    if path.kind != "star":
        raise ValueError(f"path.kind: only 'star' is supported, got {path.kind!r}")
    if path.plane not in paths.PLANES:
        raise ValueError(f"path.plane: expected one of {tuple(paths.PLANES)}, got {path.plane!r}")
    missing = [a for a in paths.PLANES[path.plane] if a not in axes]
    if missing:
        raise ValueError(f"path.plane: {path.plane!r} needs task axis {'xyz'[missing[0]]}, not in the task")
    for name in ("size", "gain", "tol", "max_task_step"):
        v = getattr(path, name)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"path.{name}: must be a finite number > 0, got {v!r}")
    if path.gain > 1:
        raise ValueError(f"path.gain: must be in (0, 1] (a larger gain overshoots), got {path.gain!r}")
    if isinstance(path.steps, bool) or not isinstance(path.steps, int) or path.steps < 1:
        raise ValueError(f"path.steps: must be an integer >= 1, got {path.steps!r}")
    full = np.asarray(paths.star(size=path.size, plane=path.plane, dim=6), np.float64)
    return full[:, list(axes)]


# --------------------------------------------------------------------------- the jitted step

_step = jax.jit(fit.step, static_argnames=("method", "options"))


def init_state(n: int, m: int, *, method: str = "closed_form", v_tol: float = 1e-9, max_samples: int = 200,
               dtype=None) -> estimator.EstimatorState:
    """Empty estimator for a session: no sample buffer unless the refinement needs one (then ``max_samples``)."""
    capacity = max_samples if needs_samples(method) else 0
    return estimator.init(n, m, capacity=capacity, v_tol=v_tol, dtype=float_dtype() if dtype is None else dtype)


def sample_step(state: estimator.EstimatorState, dtheta, V, eps, eps_rel, *, method: str = "closed_form"
                ) -> tuple[estimator.EstimatorState, fit.StepInfo]:
    """One accepted sample ``(dtheta (n,), V (m,))`` through :func:`selfid_jax.robot.fit.step`, jitted.

    ``eps`` and ``eps_rel`` are passed as arrays of the state's dtype, so one
    compilation per ``(n, m, method, dtype)`` serves every threshold and every
    sample of every session in the process. The inputs are cast with numpy
    (``jit`` transfers numpy arguments on its fast path; ``jnp.asarray`` on
    each would cost more than the step itself at batch 1).
    """
    dtype = state.estimate.dtype
    return _step(state, np.asarray(dtheta, dtype), np.asarray(V, dtype), np.asarray(eps, dtype),
                 np.asarray(eps_rel, dtype), method=method, options=())


def host_step(state: estimator.EstimatorState, dtheta, V, eps, eps_rel, *, method: str = "closed_form"
              ) -> tuple[estimator.EstimatorState, fit.StepInfo, int]:
    """:func:`sample_step` and what the online loop reads back: ``(state, info as numpy, converged_at)``.

    One ``device_get`` of the info and ``converged_at`` together: the whole
    per-sample cost of the loop's estimator (``benchmarks/online_step.py``).
    """
    state, info = sample_step(state, dtheta, V, eps, eps_rel, method=method)
    info, conv = jax.device_get((info, state.converged_at))
    return state, info, int(conv)


# --------------------------------------------------------------------------- the session


class _Stopped(Exception):
    """Internal: end the session with ``reason`` (raised where the reason is found, caught in run_online)."""

    def __init__(self, reason: Stop, detail: str):
        super().__init__(detail)
        self.reason, self.detail = reason, detail


def _observation(obs: Any, n: int) -> Observation:
    """The driver's reading as float64 arrays of the protocol's shapes; RobotError if it is malformed."""
    try:
        q = np.asarray(obs.q, np.float64).reshape(-1)
        p = np.asarray(obs.position, np.float64).reshape(-1)
        quat = np.asarray(obs.quaternion, np.float64).reshape(-1)
        t, tt, valid = float(obs.t), float(obs.tracker_t), bool(obs.valid)
    except (AttributeError, TypeError, ValueError) as err:
        raise RobotError(f"driver returned a malformed observation: {err}") from None
    if q.shape != (n,) or p.shape != (3,) or quat.shape != (4,):
        raise RobotError(f"driver returned q {q.shape}, position {p.shape}, quaternion {quat.shape}; "
                         f"expected ({n},), (3,), (4,)")
    if not np.all(np.isfinite(q)) or not (math.isfinite(t) and math.isfinite(tt)):
        raise RobotError(f"driver returned a non-finite actuator position or time (q={q.tolist()}, t={t}, "
                         f"tracker_t={tt})")
    if valid and not (np.all(np.isfinite(p)) and np.all(np.isfinite(quat)) and np.linalg.norm(quat) > 0):
        valid = False  # a "valid" pose with NaN in it is a dropout all the same
    return Observation(t, q, p, quat, tt, valid)


class _Session:
    """One session's loop state; methods raise :class:`_Stopped` to end it."""

    def __init__(self, robot: Robot, opts: OnlineOptions, env: Envelope, axes: tuple[int, ...], m_a: np.ndarray,
                 journal: Journal, stop_requested: Callable[[], bool] | None, sleep: Callable[[float], None]):
        self.robot, self.opts, self.env, self.axes, self.m_a = robot, opts, env, axes, m_a
        self.journal, self.stop_requested, self.sleep = journal, stop_requested, sleep
        self.n = env.lower.shape[0]
        self.last_tracker_t = -math.inf
        self.last_advance_wall = time.monotonic()
        self.last_cmd_t = -math.inf  # driver time of the reading before the last command
        self.state: estimator.EstimatorState | None = None
        self.k = 0  # self-ID draws completed (accepted + rejected samples)
        self.samples = 0
        self.rejected: dict[str, int] = {}
        self.moves = 0
        self.follow_steps = 0
        self.follow_rejected = 0
        self.anchor: Observation | None = None
        self.offsets: np.ndarray | None = None
        self.waypoint = 0
        self.step_ms: list[float] = []

    # ---- robot I/O, each logged as it happens

    def check_interrupt(self) -> None:
        if self.stop_requested is not None and self.stop_requested():
            raise _Stopped(Stop.INTERRUPTED, "stop requested")

    def read(self, phase: str) -> Observation:
        """Read, log, and apply the watchdog, the limits and the box (valid poses only)."""
        obs = _observation(self.robot.read(), self.n)
        now = time.monotonic()
        self.journal.append({"e": "obs", "phase": phase, "t": obs.t, "q": obs.q, "p": obs.position,
                             "quat": obs.quaternion, "tracker_t": obs.tracker_t, "valid": obs.valid})
        if obs.valid and obs.tracker_t > self.last_tracker_t:
            self.last_tracker_t, self.last_advance_wall = obs.tracker_t, now
        # the driver's age of the pose, and a lower bound on it from our clock (the same pose seen since then)
        age = max(obs.t - obs.tracker_t, now - self.last_advance_wall)
        if age > self.env.stale_s:
            raise _Stopped(Stop.STALE, f"tracker pose {age:.3f} s old (stale_s = {self.env.stale_s:g} s)")
        env = self.env
        out = np.flatnonzero((obs.q < env.lower) | (obs.q > env.upper))
        if out.size:
            i = out[0]
            raise _Stopped(Stop.LIMITS, f"actuator {i} at {obs.q[i]:.6g}, outside [{env.lower[i]:.6g}, "
                           f"{env.upper[i]:.6g}]")
        if obs.valid:
            out = np.flatnonzero((obs.position < env.box_low) | (obs.position > env.box_high))
            if out.size:
                i = out[0]
                raise _Stopped(Stop.BOX, f"tracked {'xyz'[i]} = {obs.position[i]:.6g} m, outside the box "
                               f"[{env.box_low[i]:.6g}, {env.box_high[i]:.6g}]")
        return obs

    def fresh(self, phase: str) -> Observation:
        """Read without moving until the pose is valid and newer than the last command (or the watchdog stops)."""
        while True:
            self.check_interrupt()
            obs = self.read(phase)
            if obs.valid and obs.tracker_t > self.last_cmd_t:
                return obs
            self.sleep(self.opts.poll_s)

    def move(self, target: np.ndarray, base: Observation, phase: str, k: int) -> None:
        """Log and command ``target``; refuses (a bug) one outside the envelope."""
        env = self.env
        if np.any(target < env.lower) or np.any(target > env.upper) or \
                np.any(np.abs(target - base.q) > env.max_step * (1 + 1e-12)):
            raise RuntimeError(f"internal: target {target.tolist()} from {base.q.tolist()} is outside the envelope")
        self.check_interrupt()
        self.journal.append({"e": "move", "phase": phase, "k": k, "target": target, "from": base.q})
        self.last_cmd_t = base.t
        self.robot.move(target)

    # ---- the estimator

    def step(self, dtheta: np.ndarray, V: np.ndarray):
        assert self.state is not None
        t0 = time.perf_counter()
        state, info, conv = host_step(self.state, dtheta, V, self.opts.eps, self.opts.eps_rel,
                                      method=self.opts.method)
        self.step_ms.append(1e3 * (time.perf_counter() - t0))
        self.state = state
        self.samples += 1
        return info, conv

    # ---- Algorithm 1

    def selfid(self) -> None:
        opts = self.opts
        base = self.fresh("selfid")
        while True:
            if self.k >= opts.max_samples:
                raise _Stopped(Stop.MAX_SAMPLES, f"not converged after {self.k} random moves (max_samples)")
            target = actuation_target(opts.seed, self.k, base.q, self.m_a, self.env.lower, self.env.upper)
            self.moves += 1  # counted as issued: a command whose call raised may or may not have moved the robot
            self.move(target, base, "selfid", self.k)
            self.sleep(opts.settle_s)
            obs = self.read("selfid")
            k, self.k = self.k, self.k + 1
            reason = None if obs.valid and obs.tracker_t > base.t else ("dropout" if not obs.valid else "stale")
            if reason is not None:
                self.rejected[reason] = self.rejected.get(reason, 0) + 1
                self.journal.append({"e": "sample", "k": k, "accepted": False, "reason": reason})
                base = self.fresh("selfid")
                continue
            dtheta, V = obs.q - base.q, task_difference(obs, base, self.axes)
            info, conv = self.step(dtheta, V)
            self.journal.append({"e": "sample", "k": k, "accepted": True, "dtheta": dtheta, "V": V,
                                 "estimator_accepted": bool(info.accepted), "delta": float(info.delta),
                                 "threshold": float(info.threshold), "converged_at": conv,
                                 "step_ms": self.step_ms[-1]})
            base = obs
            if conv > 0:
                self.journal.append({"e": "converged", "converged_at": conv,
                                     "estimate": np.asarray(self.state.estimate) if self.state else None})
                return

    # ---- following

    def follow(self, path: FollowOptions) -> None:
        assert self.state is not None
        env = self.env
        Jinv = np.asarray(self.state.estimate, np.float64)
        if not np.all(np.isfinite(Jinv)):
            raise _Stopped(Stop.DIVERGENCE, "the estimate is not finite; nothing to follow with")
        obs = self.fresh("follow")
        if self.anchor is None:
            planned = follow_offsets(path, self.axes)
            full = np.asarray(paths.star(size=path.size, plane=path.plane, dim=3), np.float64)
            where = obs.position + full
            out = np.flatnonzero(np.any((where < env.box_low) | (where > env.box_high), axis=1))
            if out.size:
                raise _Stopped(Stop.BOX, f"the path leaves the box at waypoint {out[0] + 1} of {len(planned)} "
                               f"({where[out[0]].round(6).tolist()} m); no following move was made")
            self.anchor, self.offsets, self.waypoint = obs, planned, 0
            self.journal.append({"e": "follow", "p": obs.position, "quat": obs.quaternion, "offsets": planned})
        anchor, offsets = self.anchor, self.offsets
        assert offsets is not None and anchor is not None
        W = offsets.shape[0]
        while True:
            x = task_difference(obs, anchor, self.axes)
            while self.waypoint < W and np.linalg.norm(offsets[self.waypoint] - x) <= path.tol:
                self.journal.append({"e": "waypoint", "reached": self.waypoint})
                self.waypoint += 1
            if self.waypoint == W:
                raise _Stopped(Stop.COMPLETED, f"path followed: {W} waypoints in {self.follow_steps} moves")
            a = offsets[self.waypoint - 1] if self.waypoint else np.zeros_like(x)
            b = offsets[self.waypoint]
            seg = b - a
            s = np.clip(np.dot(x - a, seg) / max(np.dot(seg, seg), 1e-300), 0.0, 1.0)
            dist = float(np.linalg.norm(x - (a + s * seg)))
            if dist > env.diverge_dist:
                raise _Stopped(Stop.DIVERGENCE, f"{dist:.4g} from the path towards waypoint {self.waypoint + 1} "
                               f"(diverge_dist = {env.diverge_dist:g})")
            if self.follow_steps >= path.steps:
                raise _Stopped(Stop.MAX_STEPS, f"waypoint {self.waypoint + 1} of {W} not reached in "
                               f"{path.steps} moves")
            V = path.gain * (b - x)
            norm = np.linalg.norm(V)
            if norm > path.max_task_step:
                V = V * (path.max_task_step / norm)
            dq = Jinv @ V
            scale = np.max(np.abs(dq) / env.max_step)
            if scale > 1:
                dq = dq / scale
            target = np.clip(obs.q + dq, env.lower, env.upper)
            self.follow_steps += 1
            self.move(target, obs, "follow", self.follow_steps - 1)
            self.sleep(self.opts.settle_s)
            base_t = obs.t
            obs = self.read("follow")
            if not (obs.valid and obs.tracker_t > base_t):
                self.follow_rejected += 1
                obs = self.fresh("follow")

    # ---- resume

    def replay(self, log: JournalContents) -> int:
        """Fold the log's accepted samples into the state (the same jitted step); return how many."""
        assert self.state is not None
        logged_conv = -1
        replayed = 0
        for rec in log.records:
            e = rec["e"]
            if e == "sample":
                self.k = max(self.k, int(rec["k"]) + 1)
                if rec["accepted"]:
                    self.state, _ = sample_step(self.state, floats(rec["dtheta"]), floats(rec["V"]), self.opts.eps,
                                                self.opts.eps_rel, method=self.opts.method)
                    self.samples += 1
                    replayed += 1
                    logged_conv = int(rec["converged_at"])
                else:
                    self.rejected[rec["reason"]] = self.rejected.get(rec["reason"], 0) + 1
            elif e == "move":
                if rec["phase"] == "selfid":
                    self.moves += 1
                else:
                    self.follow_steps += 1
            elif e == "follow":
                q = np.zeros(self.n)
                self.anchor = Observation(0.0, q, floats(rec["p"]), floats(rec["quat"]), 0.0, True)
                self.offsets = np.array([floats(r) for r in rec["offsets"]])
                self.waypoint = 0
            elif e == "waypoint":
                self.waypoint = int(rec["reached"]) + 1
        conv = int(self.state.converged_at)
        if conv != logged_conv and not (logged_conv < 0 and conv < 0):
            raise ResumeError(f"{self.journal.path}: replaying the log's {replayed} samples gives convergence at "
                              f"{conv}, the log recorded {logged_conv}; it was written by another estimator "
                              "(version, platform) and cannot be continued")
        return replayed


def _header(n: int, m: int, axes, m_a: np.ndarray, opts: OnlineOptions, dtype) -> dict[str, Any]:
    return {"e": "header", "version": LOG_VERSION, "n": n, "m": m, "axes": list(axes), "m_a": m_a.tolist(),
            "eps": float(opts.eps), "eps_rel": float(opts.eps_rel), "seed": int(opts.seed), "method": opts.method,
            "v_tol": float(opts.v_tol), "dtype": np.dtype(dtype).name}


def _check_header(path: Path, logged: dict[str, Any], expected: dict[str, Any]) -> None:
    for key, want in expected.items():
        if key == "e":
            continue
        got = logged.get(key, "(missing)")
        if got != want:
            raise ResumeError(f"{path}: cannot resume: the log's {key} is {got!r}, this session's is {want!r}; "
                              "use the log's value or start a new run directory")


def _check_options(opts: OnlineOptions, n: int) -> tuple[tuple[int, ...], np.ndarray]:
    axes = parse_task(opts.task)
    if axes is None:
        raise ValueError("task: give the task axes, e.g. 'x,y,z'")
    m_a = np.asarray(opts.m_a, np.float64)
    if m_a.ndim == 0:
        m_a = np.full(n, float(m_a))
    if m_a.shape != (n,):
        raise ValueError(f"m_a: expected a number or {n} values (one per actuator), got shape {m_a.shape}")
    if not np.all(np.isfinite(m_a)) or np.any(m_a <= 0):
        raise ValueError(f"m_a: every value must be finite and > 0, got {m_a.tolist()}")
    estimator.check_thresholds(opts.eps, opts.eps_rel)
    if opts.method not in ONLINE_METHODS:
        raise ValueError(f"method: expected one of {ONLINE_METHODS} (the per-sample step is jitted), got "
                         f"{opts.method!r}")
    for name in ("max_samples", "seed"):
        v = getattr(opts, name)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (1 if name == "max_samples" else 0):
            raise ValueError(f"{name}: expected an integer >= {1 if name == 'max_samples' else 0}, got {v!r}")
    for name, lo in (("settle_s", 0.0), ("poll_s", 1e-6)):
        v = getattr(opts, name)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= lo):
            raise ValueError(f"{name}: expected a finite number of seconds >= {lo:g}, got {v!r}")
    return axes, m_a


def run_online(robot: Robot, options: OnlineOptions, run_dir: str | Path, *, resume: bool = False,
               stop_requested: Callable[[], bool] | None = None,
               sleep: Callable[[float], None] = time.sleep) -> OnlineResult:
    """Self-identify the robot's inverse Jacobian live (Algorithm 1), then follow ``options.path`` with it.

    ``robot``: a connected driver (:class:`~selfid_jax.robot.protocol.Robot`);
    it is closed when the session ends, however it ends. ``run_dir``: where
    the session log (``session.jsonl``) is appended; created if missing.
    ``resume``: continue the session logged there (see the module docstring);
    without it a run directory that already holds a log is refused.
    ``stop_requested``: polled before every read and command; True ends the
    session as :attr:`Stop.INTERRUPTED` (a signal handler sets it);
    KeyboardInterrupt does the same. ``sleep``: the settle/poll wait.

    Returns an :class:`OnlineResult`; the session's stop is its ``status``
    (a safety stop is a result, not an exception).

    A start position outside the limits or the box, or a path that would
    leave the box, ends the session before any motion with that status.

    Every error below is raised before any motion, and the robot is closed first.

    Raises:
      ValueError: an option out of range (the message names it), or ``m_a``
        above the envelope's ``max_step``.
      ResumeError: the log disagrees with the options (names the field), or
        ``resume`` without a log / a log without ``resume``.
      JournalError: the log is corrupt.
      OSError: the log cannot be written.
    """
    run_dir = Path(run_dir)
    log_path = run_dir / LOG_FILE
    journal: Journal | None = None
    session: _Session | None = None
    status, detail = Stop.INTERRUPTED, "not started"
    replayed = truncated = 0
    try:
        limits = robot.limits()
        n = check_limits(limits).lower.shape[0]
        axes, m_a = _check_options(options, n)
        env = envelope(limits, lower=options.lower, upper=options.upper, max_step=options.max_step,
                       box_low=options.box_low, box_high=options.box_high, stale_s=options.stale_s,
                       diverge_dist=options.diverge_dist)
        big = np.flatnonzero(m_a > env.max_step)
        if big.size:
            i = big[0]
            raise ValueError(f"m_a: {m_a[i]:g} for actuator {i} exceeds the largest step allowed, "
                             f"{env.max_step[i]:g} (max_step: the driver's or the user's); lower m_a")
        if options.path is not None:
            follow_offsets(options.path, axes)
        m = len(axes)
        dtype = float_dtype()
        header = _header(n, m, axes, m_a, options, dtype)
        run_dir.mkdir(parents=True, exist_ok=True)
        contents = None
        if resume:
            if not log_path.exists():
                raise ResumeError(f"{log_path}: no session log to resume; run without resume to start one")
            contents = read_journal(log_path)
            _check_header(log_path, contents.header, header)
            truncated = contents.truncated
            journal = Journal(log_path, good_bytes=contents.good_bytes)
        else:
            if log_path.exists():
                raise ResumeError(f"{log_path}: the run directory already holds a session log; resume it or "
                                  "choose another run directory")
            journal = Journal(log_path)
            journal.append(header)
        session = _Session(robot, options, env, axes, m_a, journal, stop_requested, sleep)
        session.state = init_state(n, m, method=options.method, v_tol=options.v_tol,
                                   max_samples=options.max_samples, dtype=dtype)
        # compile the step now, before any motion, so the first sample does not stall the loop (result discarded)
        jax.block_until_ready(sample_step(session.state, np.zeros(n), np.zeros(m), options.eps, options.eps_rel,
                                          method=options.method))
        if contents is not None:
            replayed = session.replay(contents)
        journal.append({"e": "session", "resume": resume, "replayed": replayed, "truncated": truncated,
                        "wall_time": time.time(), "lower": env.lower, "upper": env.upper, "max_step": env.max_step,
                        "box_low": env.box_low, "box_high": env.box_high, "stale_s": env.stale_s})
        session.last_advance_wall = time.monotonic()  # the watchdog's clock starts now, not before the replay
        try:
            if int(session.state.converged_at) < 1:
                session.selfid()
            if options.path is None:
                raise _Stopped(Stop.CONVERGED, f"converged at sample {int(session.state.converged_at)}; "
                               "no path to follow, the robot stays where it is")
            session.follow(options.path)
        except _Stopped as stop:
            status, detail = stop.reason, stop.detail
        except RobotConnectionError as err:
            status, detail = Stop.CONNECTION, f"connection lost: {err}"
        except RobotError as err:
            status, detail = Stop.ROBOT_ERROR, f"the robot refused or faulted: {err}"
        except KeyboardInterrupt:
            status, detail = Stop.INTERRUPTED, "interrupted (KeyboardInterrupt)"
        journal.append({"e": "stop", "reason": status.value, "detail": detail})
    finally:
        try:
            robot.close()
        except Exception:  # noqa: BLE001 - closing a lost connection may fail; the session is over either way
            pass
        if journal is not None:
            journal.close()
    assert session is not None and session.state is not None
    state = jax.device_get(session.state)
    path_total = 0 if session.offsets is None else int(session.offsets.shape[0])
    return OnlineResult(
        status=status, detail=detail, estimate=np.asarray(state.estimate), state=state,
        converged_at=int(state.converged_at), samples=session.samples, rejected=dict(session.rejected),
        moves=session.moves, follow_steps=session.follow_steps, waypoints=session.waypoint,
        waypoints_total=path_total, replayed=replayed, truncated=truncated,
        step_ms=np.asarray(session.step_ms, np.float64), axes=axes, log=log_path)
