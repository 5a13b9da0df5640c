"""One live session's loop: Algorithm 1's random moves, then following with the simulations' control step.

:class:`Session` holds a session's state and runs its two phases against a
:class:`~selfid_jax.robot.protocol.Robot`, logging every read, command,
sample and waypoint to the session's :class:`~selfid_jax.robot.journal.Journal`
as it happens, and raising :class:`Stopped` where a stop is found:

* :meth:`Session.selfid` (Algorithm 1): each random move's sample runs the
  jitted :func:`selfid_jax.robot.steps.sample_step`, the per-sample identification step of
  Algorithm 1 and ``fit`` (:func:`selfid_jax.identify.step.sample_step`).
* :meth:`Session.follow`: each step is :func:`selfid_jax.robot.steps.follow_command`, which is
  :func:`selfid_jax.control.law.command` with
  :func:`~selfid_jax.control.law.inverse_jacobian_law` on the converged
  estimate, the control step of the simulated follow loop
  (:func:`selfid_jax.control.loop.follow_law`) run on the host in float64.
  So a simulated tracking result with the same controller settings
  (:meth:`selfid_jax.robot.options.FollowOptions.controller`) describes what
  the robot does: the waypoint test, the twist clipped per part, the
  per-actuator cap, the limits, the divergence test, and a reading that is
  not fresh makes no command (the simulation's dropout does the same).
  Before the first following move a waypoint the estimate's linear step puts
  far beyond an actuator's limits is refused (``unreachable``); waypoints
  already within tolerance whose successor is too are passed (a densely
  sampled path); each move's tracked change (position, and rotation on a
  task with rotation axes) is held against the estimate's prediction above
  the tracker's noise, measured at rest where following starts, and
  predicted from the actuators' measured motion, so a move the limits
  clipped is held against it too (on a redundant arm, where that motion
  lies within the estimate's range); an actuator held at a limit while the
  waypoint comes no nearer stops as ``unreachable``, naming the joint, its
  limit and whose it is.
* :meth:`Session.replay` folds a logged session back into the state (resume);
  the first reading of the resumed session is tested against where the log
  left the robot (``moved``, in either phase, whatever ``wander`` is).

Messages name actuators 1-based, with the driver's ``joint_names`` where it
has them (:func:`selfid_jax.robot.protocol.joint_labels`).

:func:`selfid_jax.robot.live.run_online` builds and ends a session.
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Callable

import numpy as np

from selfid_jax.identify import estimator
from selfid_jax.robot.journal import Journal, JournalContents, JournalError, floats
from selfid_jax.robot.protocol import Observation, Robot, RobotError, joint_labels
from selfid_jax.robot.quality import Quality, held_out
from selfid_jax.robot.safety import (
    COMMAND_MEMORY,
    Commanded,
    Envelope,
    Sight,
    actuation_target,
    angle_between,
    check_observation,
    linear_reach,
    tracker_noise,
)
from selfid_jax.robot.steps import follow_command, host_step, sample_step, task_difference, waypoint_errors

__all__ = ["NOISE_READS", "STALL_MOVES", "DriverFault", "ResumeError", "Session", "Stop", "Stopped"]

NOISE_READS = 8
"""Tracker readings at rest where following starts: their spread is the noise floor of the following check."""
STALL_MOVES = 10
"""Following moves with an actuator held at a limit and the waypoint no nearer (by ``tol``) that stop (unreachable)."""
OFF_RANGE = 0.05
"""Following: a move the limits clipped whose actuator motion lies more than this fraction of its norm outside the
estimate's range (a redundant arm) is not a sample of the following check (the estimate does not predict it)."""
FAR_MOVES = 10.0
"""Following: an actuator farther than this many of its ``m_a`` from where following started is beyond where the
estimate was identified; the following check failing there names the distant waypoint (unreachable), not the
estimate."""


class Stop(enum.StrEnum):
    """Why a session ended."""

    CONVERGED = "converged"  # self-ID met Sec. IV-D and there is no path to follow
    COMPLETED = "completed"  # the path was followed to its last waypoint
    MAX_SAMPLES = "max_samples"  # self-ID made max_samples random moves without converging
    MAX_STEPS = "max_steps"  # following took max_steps moves without reaching the last waypoint
    STALE = "stale"  # the tracker was older than stale_s (watchdog)
    BOX = "box"  # the tracked position left the task-space box (or the path would)
    LIMITS = "limits"  # a measured actuator position outside the limits
    # following: a waypoint the estimate's linear step puts far beyond an actuator's limits (before any following
    # move), or an actuator held at a limit while the waypoint comes no nearer (STALL_MOVES moves)
    UNREACHABLE = "unreachable"
    DIVERGENCE = "divergence"  # while following, farther than diverge_dist from the path
    MOVED = "moved"  # resumed with the robot away from where the log left it; no move was made
    TRACKER_FROZEN = "tracker_frozen"  # the actuators moved and the tracked pose did not (Sight)
    CLOCK = "clock"  # a tracker stamp ahead of the driver's clock: a future stamp or another clock
    ACTUATOR = "actuator"  # an actuator does not do what it is told (it moved much less than commanded)
    ESTIMATE = "estimate"  # the samples' or the following moves' tracked motion is not predicted (held out)
    CONNECTION = "connection"  # the driver raised RobotConnectionError
    ROBOT_ERROR = "robot_error"  # the driver raised another RobotError (a refused command, a fault)
    DRIVER_ERROR = "driver_error"  # the driver raised an exception that is not a RobotError (a vendor's own)
    ERROR = "error"  # the runner itself failed (a bug): the session stopped with no further command
    INTERRUPTED = "interrupted"  # KeyboardInterrupt or a stop request
    KILLED = "killed"  # in the log only: a second signal ended the process at once (selfid-jax online)


class ResumeError(JournalError):
    """A session log that cannot be resumed with these options; the message names the disagreeing field."""


class DriverFault(Exception):
    """A driver's ``read`` or ``move`` raised something other than a RobotError (``kind`` names its type)."""

    def __init__(self, call: str, err: BaseException):
        super().__init__(f"{call}() raised {type(err).__name__}: {err}")
        self.kind = type(err).__name__


class Stopped(Exception):
    """End the session with ``reason`` (raised where the reason is found, caught in ``run_online``)."""

    def __init__(self, reason: Stop, detail: str):
        super().__init__(detail)
        self.reason, self.detail = reason, detail


# --------------------------------------------------------------------------- the session


class Session:
    """One session's loop state; its methods raise :class:`Stopped` to end it.

    ``opts`` is the session's :class:`selfid_jax.robot.options.OnlineOptions`
    (read for ``seed``, ``max_samples``, ``settle_s``, ``poll_s``, ``eps``,
    ``eps_rel``, ``method``), ``env`` its checked :class:`Envelope`, ``axes``
    its task axes and ``m_a (n,)`` its self-ID magnitude.
    """

    def __init__(self, robot: Robot, opts, env: Envelope, axes: tuple[int, ...], m_a: np.ndarray,
                 journal: Journal, stop_requested: Callable[[], bool] | None, sleep: Callable[[float], None],
                 progress: Callable[[dict], None] | None = None):
        self.robot, self.opts, self.env, self.axes, self.m_a = robot, opts, env, axes, m_a
        self.journal, self.stop_requested, self.sleep = journal, stop_requested, sleep
        self.progress = progress  # called with one event (a dict) after each self-ID sample and following move
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
        self.follow_rejected = 0  # readings after a following move that were not fresh (no command from them)
        self.anchor: Observation | None = None
        self.offsets: np.ndarray | None = None
        self.min_count = 0  # accepted samples before Sec. IV-D counts (live.min_samples)
        self.centre: np.ndarray | None = None  # (n,) actuators where self-ID started (the wander's centre)
        self.reference: np.ndarray | None = None  # (6, n) the driver's model Jacobian at the centre, if it has one
        self.waypoint = 0
        self.step_ms: list[float] = []
        self.clock_offset = math.inf  # min over readings of (runner's monotonic clock - driver's clock) [s]
        self.sight: Sight | None = None
        self.commanded = Commanded(np.zeros(self.n), np.zeros(self.n))
        self.predict: np.ndarray | None = None  # (m, n) pinv of the estimate while following: dq -> predicted V
        self.span: np.ndarray | None = None  # (n, n) following: Jinv pinv(Jinv), the projection onto its range
        self.position_axes = [a for a in axes if a < 3]  # the task's P position axes, indices into (x, y, z)
        self.residual = (0.0, 0.0, 0)  # following: recent-weighted sums of |dp - predicted dp|, |predicted dp|; moves
        self.pairs: list[tuple[np.ndarray, np.ndarray]] = []  # the accepted samples (dtheta (n,), V (m,))
        self.quality: Quality | None = None
        self.given: tuple[np.ndarray, str] | None = None  # (estimate, source) followed without self-ID, if given
        self.labels = joint_labels(robot, self.n)  # how messages name the actuators: "joint 1 (name)", 1-based
        # resumed: where the log left the robot, (q (n,), p (3,) or None, the last target (n,) or None), tested
        # once at the first reading of this session (the moved stop)
        self.left: tuple[np.ndarray, np.ndarray | None, np.ndarray | None] | None = None
        self.noise = (0.0, 0.0)  # following: the tracker's noise per axis at rest, (position m, rotation rad)
        self.scale = 1.0  # following: m per rad, max_task_step / max_rot_step (rotation against position)
        self.stall: list | None = None  # following: [waypoint, best error, moves without progress] while pinned
        self.follow_q: np.ndarray | None = None  # (n,) the actuators where following started (from the log)
        self.pinned: tuple[tuple[int, bool], ...] = ()  # following: (actuator, upper?) the last move held at a limit

    # ---- robot I/O, each logged as it happens

    def _call(self, name: str, *args):
        """``robot.<name>(*args)``; an exception other than RobotError (or KeyboardInterrupt) becomes a DriverFault."""
        try:
            return getattr(self.robot, name)(*args)
        except RobotError:
            raise
        except Exception as err:  # a vendor's TimeoutError, ValueError, OSError...: a logged stop, not a traceback
            raise DriverFault(name, err) from err

    def report(self, event: dict) -> None:
        """Hand ``event`` to the progress callback, if any (after the event is logged)."""
        if self.progress is not None:
            self.progress(event)

    def check_interrupt(self) -> None:
        if self.stop_requested is not None and self.stop_requested():
            raise Stopped(Stop.INTERRUPTED, "stop requested")

    def read(self, phase: str) -> Observation:
        """Read, log, and apply the watchdog, the limits and the box (valid poses only)."""
        obs = check_observation(self._call("read"), self.n, rotation=any(a >= 3 for a in self.axes))
        now = time.monotonic()
        self.journal.append({"e": "obs", "phase": phase, "t": obs.t, "q": obs.q, "p": obs.position,
                             "quat": obs.quaternion, "tracker_t": obs.tracker_t, "valid": obs.valid})
        ahead = obs.tracker_t - obs.t
        if ahead > self.env.stale_s:
            raise Stopped(Stop.CLOCK, f"the tracker's stamp {obs.tracker_t:.6f} s is {ahead:.6g} s ahead of the "
                          f"driver's clock {obs.t:.6f} s: a future stamp, or the tracker and the encoders on two "
                          "clocks (stamp both on one, e.g. time.monotonic())")
        if obs.valid and obs.tracker_t > self.last_tracker_t:
            self.last_tracker_t, self.last_advance_wall = obs.tracker_t, now
        # the pose's age on the runner's clock: the driver's clock mapped by its smallest offset seen (so the
        # transport's delay beyond its fastest counts), and a lower bound from our clock (the same pose seen since)
        self.clock_offset = min(self.clock_offset, now - obs.t)
        age = max(now - self.clock_offset - obs.tracker_t, now - self.last_advance_wall)
        if age > self.env.stale_s:
            raise Stopped(Stop.STALE, f"tracker pose {age:.3f} s old (stale_s = {self.env.stale_s:g} s)")
        env = self.env
        out = np.flatnonzero((obs.q < env.lower) | (obs.q > env.upper))
        if out.size:
            i = out[0]
            raise Stopped(Stop.LIMITS, f"{self.labels[i]} at {obs.q[i]:.6g}, outside [{env.lower[i]:.6g}, "
                          f"{env.upper[i]:.6g}]")
        if obs.valid:
            out = np.flatnonzero((obs.position < env.box_low) | (obs.position > env.box_high))
            if out.size:
                i = out[0]
                raise Stopped(Stop.BOX, f"tracked {'xyz'[i]} = {obs.position[i]:.6g} m, outside the box "
                              f"[{env.box_low[i]:.6g}, {env.box_high[i]:.6g}]")
        return obs

    def is_fresh(self, obs: Observation) -> bool:
        """Whether ``obs`` has a pose taken after the last command (valid and newer than the reading before it)."""
        return obs.valid and obs.tracker_t > self.last_cmd_t

    def fresh(self, phase: str) -> Observation:
        """Read without moving until the pose is valid and newer than the last command (or the watchdog stops)."""
        while True:
            self.check_interrupt()
            obs = self.read(phase)
            if self.is_fresh(obs):
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
        self._call("move", target.copy())  # a copy: the driver may keep or change what it is handed

    # ---- after each move: did the actuators do it, did the tracker see it

    def after_move(self, base: Observation, target: np.ndarray, obs: Observation, clipped: bool = False) -> None:
        """The command-following, held-out prediction and motion-versus-sight checks of one move from ``base``
        towards ``target``, read back as ``obs``; raises :class:`Stopped` (``actuator``, ``estimate``,
        ``tracker_frozen``) before any further move.

        While following, the move is a held-out sample of the estimate: the
        tracked change ``V`` (position and, for a task with rotation axes,
        rotation) against ``pinv(estimate) dq``, each part's miss less its
        noise floor (3 sigma of the difference of two readings, from the
        tracker's noise measured at rest), rotation weighed by ``scale`` m/rad.
        The prediction is of the actuators' measured motion ``dq``, so a move
        whose command the limits ``clipped`` is a sample too: what was
        commanded after clipping, as made. ``pinv(estimate) dq`` is the
        estimate's forward map only on the estimate's range (all of ``dq``
        for ``n == m``); on a redundant arm a clipped move whose ``dq`` lies
        more than :data:`OFF_RANGE` (a fraction of ``|dq|``) outside it is
        not a sample (the estimate says nothing of that part's motion; a
        joint held at a limit is named by the limits' own test).
        """
        opts, dq, d = self.opts, obs.q - base.q, target - base.q
        c, w = self.commanded, COMMAND_MEMORY  # recent moves weigh most: a joint that sticks later is seen too
        c = self.commanded = Commanded(w * c.commanded + np.abs(d), w * c.along + dq * np.sign(d), c.moves + 1)
        if c.moves >= opts.follow_min_moves:
            ratio = c.along / np.maximum(c.commanded, 1e-300)
            # a shortfall under half a self-ID move is a deadband or a stick-slip band swallowing small commands of
            # either sign (franky-sim's FR3 joint 7 holds +-1.8 mrad), not a stuck actuator
            short = c.commanded - c.along > 0.5 * self.m_a
            bad = np.flatnonzero((c.commanded > 0) & (ratio < opts.follow_min_ratio) & short)
            if bad.size:
                i = bad[0]
                raise Stopped(Stop.ACTUATOR, f"{self.labels[i]} moved {100 * ratio[i]:.0f}% of what it was commanded "
                              f"over {c.moves} moves ({c.along[i]:.4g} of {c.commanded[i]:.4g}; follow_min_ratio "
                              f"{opts.follow_min_ratio:g}): stuck, slow or not settled")
        if not obs.valid:
            return
        full = None if self.predict is None else self.predict @ dq  # (m,) predicted task change [m, rad]
        P = len(self.position_axes)
        pred = None if full is None else full[:P]  # (P,) predicted position change [m]
        if full is not None and (not clipped or self.predicts(dq)):  # following: a held-out sample of the estimate
            V = task_difference(obs, base, self.axes)
            (sp, sr), R = self.noise, full.shape[0] - P
            miss_p = max(0.0, float(np.linalg.norm(V[:P] - full[:P])) - 3.0 * sp * math.sqrt(2 * P))
            miss_r = max(0.0, float(np.linalg.norm(V[P:] - full[P:])) - 3.0 * sr * math.sqrt(2 * R)) if R else 0.0
            miss = math.hypot(miss_p, self.scale * miss_r)
            size = math.hypot(float(np.linalg.norm(full[:P])), self.scale * float(np.linalg.norm(full[P:])))
            r = self.residual
            r = self.residual = (w * r[0] + miss, w * r[1] + size, r[2] + 1)
            if r[2] >= opts.follow_min_moves and r[0] > opts.follow_max_residual * r[1]:
                self.far_first(obs, 100 * r[0] / max(r[1], 1e-300))
                raise Stopped(Stop.ESTIMATE, f"the estimate predicts the tracked motion of the last moves with "
                              f"{100 * r[0] / max(r[1], 1e-300):.0f}% error beyond the tracker's noise "
                              f"(follow_max_residual {opts.follow_max_residual:g}; noise {1e3 * sp:.3g} mm"
                              + (f", {sr:.3g} rad" if R else "") + " per axis, measured at rest): the robot no "
                              "longer moves as it was self-identified (a changed grasp or load, a joint, the "
                              "tracker's frame); self-identify again")
        sight = self.sight if self.sight is not None else Sight(base.position, base.quaternion)
        if np.linalg.norm(obs.position - sight.p) > opts.seen_min or \
                angle_between(obs.quaternion, sight.quat) > opts.seen_min_rad:
            self.sight = Sight(obs.position, obs.quaternion)
            return
        moved = sight.moved + float(np.max(np.abs(dq)))
        predicted = sight.predicted + (0.0 if pred is None else float(np.linalg.norm(pred)))
        self.sight = sight._replace(moved=moved, predicted=predicted, moves=sight.moves + 1)
        limit = self.frozen_motion
        if moved > limit or predicted > opts.frozen_dist:
            what = (f"{moved:.4g} of actuator motion (frozen_motion {limit:.4g})" if moved > limit else
                    f"{1e3 * predicted:.3g} mm of predicted motion (frozen_dist {1e3 * opts.frozen_dist:.3g} mm)")
            raise Stopped(Stop.TRACKER_FROZEN, f"the tracked pose moved less than {1e3 * opts.seen_min:.3g} mm and "
                          f"{opts.seen_min_rad:g} rad over {sight.moves + 1} moves and {what}: the tracker does "
                          "not see the arm move")

    @property
    def frozen_motion(self) -> float:
        """Actuator motion [actuator units] with no seen change that stops: the option, or 3 max(m_a)."""
        v = self.opts.frozen_motion
        return 3.0 * float(np.max(self.m_a)) if v is None else float(v)

    def predicts(self, dq: np.ndarray) -> bool:
        """Whether the estimate followed with predicts the task motion of actuator motion ``dq (n,)``: its part
        outside the estimate's range (``(I - Jinv pinv(Jinv)) dq``) is at most :data:`OFF_RANGE` of ``|dq|``."""
        assert self.span is not None
        off = float(np.linalg.norm(dq - self.span @ dq))
        return off <= OFF_RANGE * float(np.linalg.norm(dq))

    def check_quality(self) -> None:
        """After convergence, before any following move: the held-out error of the samples (:func:`held_out`),
        logged; above ``max_heldout_error`` the session stops (estimate)."""
        D, V = (np.array([p[i] for p in self.pairs], np.float64) for i in (0, 1))
        q = self.quality = held_out(D.reshape(len(self.pairs), self.n), V.reshape(len(self.pairs), -1),
                                    float(np.max(self.m_a)))
        self.journal.append({"e": "quality", "heldout_error": q.heldout_error, "effect": q.effect,
                             "samples": q.samples})
        if q.heldout_error > self.opts.max_heldout_error:  # NaN (too few samples) passes: nothing to hold out
            weakest = int(np.argmin(q.effect))
            raise Stopped(Stop.ESTIMATE, f"the samples' tracked motion is predicted from the actuators' with "
                          f"{100 * q.heldout_error:.0f}% held-out error (max_heldout_error "
                          f"{self.opts.max_heldout_error:g}); the weakest actuator, {self.labels[weakest]}, moves "
                          "the point "
                          f"{q.effect[weakest]:.3g} per max(m_a) move: settle_s too short for the tracker's latency, "
                          "an actuator that does not act, or a tracker that is not on the robot")

    # ---- the estimator

    def step(self, dtheta: np.ndarray, V: np.ndarray):
        assert self.state is not None
        t0 = time.perf_counter()
        state, info, conv = host_step(self.state, dtheta, V, self.opts.eps, self.opts.eps_rel,
                                      method=self.opts.method, min_count=self.min_count)
        self.step_ms.append(1e3 * (time.perf_counter() - t0))
        self.state = state
        self.samples += 1
        self.pairs.append((np.array(dtheta, np.float64), np.array(V, np.float64)))
        return info, conv

    def reference_jacobian(self, q: np.ndarray) -> np.ndarray | None:
        """The driver's model Jacobian ``(6, n)`` at ``q`` (rows x, y, z, rx, ry, rz; m and rad per actuator unit),
        checked, or None where the driver has no model of the tracked point; DriverFault if it is neither."""
        J = self._call("jacobian", q.copy())
        if J is None:
            return None
        try:
            J = np.array(J, np.float64)
            ok = J.shape == (6, self.n) and bool(np.all(np.isfinite(J)))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise DriverFault("jacobian", ValueError(f"expected a finite (6, {self.n}) array, got {J!r}"))
        return J

    # ---- Algorithm 1

    def selfid(self) -> None:
        opts = self.opts
        base = self.fresh("selfid")
        if self.centre is None:
            self.centre = base.q.copy()
            self.journal.append({"e": "centre", "q": self.centre})
            if callable(getattr(self.robot, "jacobian", None)):  # a driver with a model: the estimate's reference
                self.reference = self.reference_jacobian(self.centre)
                if self.reference is not None:
                    self.journal.append({"e": "reference", "q": self.centre, "jacobian": self.reference})
        elif opts.wander is not None:  # resumed: self-ID continues around where it started, not elsewhere
            reach = (opts.wander + 1.0) * self.m_a
            far = np.flatnonzero(np.abs(base.q - self.centre) > reach)
            if far.size:
                i = far[0]
                raise Stopped(Stop.MOVED, f"{self.labels[i]} is {base.q[i] - self.centre[i]:+.4g} from where "
                              f"self-ID started (it was at {self.centre[i]:.4g} then; (wander + 1) m_a = "
                              f"{reach[i]:.4g} allowed): the robot moved since the log's last session. No move was "
                              "made: move it back, or start a new run directory")
            self.left = None  # the centre's test is the one self-ID needs (it may go on anywhere near the centre)
        self.check_left(base, "start a new run directory")
        while True:
            if self.k >= opts.max_samples:
                raise Stopped(Stop.MAX_SAMPLES, f"not converged after {self.k} random moves (max_samples)")
            target = actuation_target(opts.seed, self.k, base.q, self.m_a, self.env.lower, self.env.upper,
                                      self.centre, opts.wander)
            self.moves += 1  # counted as issued: a command whose call raised may or may not have moved the robot
            self.move(target, base, "selfid", self.k)
            self.sleep(opts.settle_s)
            obs = self.read("selfid")
            self.after_move(base, target, obs)
            k, self.k = self.k, self.k + 1
            reason = None if obs.valid and obs.tracker_t > base.t else ("dropout" if not obs.valid else "stale")
            if reason is not None:
                self.rejected[reason] = self.rejected.get(reason, 0) + 1
                self.journal.append({"e": "sample", "k": k, "accepted": False, "reason": reason})
                self.report({"phase": "selfid", "move": k + 1, "sample": self.samples, "accepted": False,
                             "reason": reason})
                base = self.fresh("selfid")
                continue
            dtheta, V = obs.q - base.q, task_difference(obs, base, self.axes)
            info, conv = self.step(dtheta, V)
            self.journal.append({"e": "sample", "k": k, "accepted": True, "dtheta": dtheta, "V": V,
                                 "estimator_accepted": bool(info.accepted), "delta": float(info.delta),
                                 "threshold": float(info.threshold), "converged_at": conv,
                                 "step_ms": self.step_ms[-1]})
            self.report({"phase": "selfid", "move": k + 1, "sample": self.samples, "accepted": True,
                         "estimator_accepted": bool(info.accepted), "delta": float(info.delta),
                         "threshold": float(info.threshold), "converged_at": conv})
            base = obs
            if conv > 0:
                self.journal.append({"e": "converged", "converged_at": conv,
                                     "estimate": np.asarray(self.state.estimate) if self.state else None})
                return

    # ---- following

    def follow(self, path, estimate: np.ndarray | None = None) -> None:
        """Follow ``path`` (:class:`selfid_jax.robot.options.FollowOptions`) with the converged estimate, or with
        ``estimate (n, m)`` where given (no self-ID)."""
        assert self.state is not None
        env = self.env
        Jinv = np.asarray(self.state.estimate if estimate is None else estimate, np.float64)
        if not np.all(np.isfinite(Jinv)):
            raise Stopped(Stop.DIVERGENCE, "the estimate is not finite; nothing to follow with")
        obs = self.fresh("follow")
        resumed = self.anchor is not None
        if not resumed:
            self.check_left(obs, self.new_path_hint(), path)
        self.scale = path.max_task_step / path.max_rot_step
        self.pinned, self.stall = (), None
        if self.anchor is None:
            planned = path.offsets(self.axes)
            where = obs.position + path.positions(self.axes)  # the planned waypoints' positions (box check)
            out = np.flatnonzero(np.any((where < env.box_low) | (where > env.box_high), axis=1))
            if out.size:
                raise Stopped(Stop.BOX, f"the path leaves the box at waypoint {out[0] + 1} of {len(planned)} "
                              f"({where[out[0]].round(6).tolist()} m); no following move was made")
            far = linear_reach(Jinv, planned, obs.q, env.lower, env.upper)
            if far is not None:
                w, i, need = far
                raise Stopped(Stop.UNREACHABLE, f"waypoint {w + 1} of {len(planned)} ({self.offset_text(planned[w])} "
                              f"from where following starts) is out of reach within the limits: the estimate moves "
                              f"{self.labels[i]} from {obs.q[i]:.4g} to about {need:.4g} for it, more than twice the "
                              f"room to its {self.limit_text(i, need > obs.q[i])}. No following move was made: "
                              "a nearer path, or wider limits")
            self.anchor, self.offsets, self.waypoint = obs, planned, 0
            self.follow_q = obs.q.copy()
            self.journal.append({"e": "follow", "p": obs.position, "quat": obs.quaternion, "offsets": planned,
                                 "q": obs.q})
        anchor, offsets = self.anchor, self.offsets
        assert offsets is not None and anchor is not None
        W = offsets.shape[0]
        ctrl = path.controller(env)
        self.predict = np.linalg.pinv(Jinv)  # (m, n): dq -> predicted change of the task's pose (m, rad)
        self.span = Jinv @ self.predict  # (n, n): projection onto the estimate's range (I where n == m)
        obs = self.measure_noise(obs)
        moved = False  # a reading after a move of this call (not the one following starts or resumes from)
        while True:
            e_p, e_r = waypoint_errors(offsets, anchor, obs, self.axes)
            within = (e_p <= ctrl.tol) & (e_r <= ctrl.rot_tol)  # (W,) the law's waypoint test at this reading
            while self.waypoint + 1 < W and within[self.waypoint] and within[self.waypoint + 1]:
                # a waypoint within tolerance whose successor is too is passed here (a densely sampled path):
                # the law reaches one waypoint per move, and a move towards one already reached is noise
                self.journal.append({"e": "waypoint", "reached": self.waypoint})
                self.waypoint += 1
            cmd, dist = follow_command(Jinv, offsets, anchor, self.waypoint, obs, ctrl, self.axes)
            if cmd.reached:
                self.journal.append({"e": "waypoint", "reached": self.waypoint})
            self.waypoint = int(cmd.waypoint)
            if moved:
                self.report({"phase": "follow", "step": self.follow_steps, "waypoint": self.waypoint,
                             "waypoints": W, "distance": dist})
            if resumed and not moved:
                if dist > env.diverge_dist:
                    raise Stopped(Stop.MOVED, f"the tracked point is {dist:.4g} m from the log's path (diverge_dist "
                                  f"{env.diverge_dist:g}): the robot moved since the log's last session. No move "
                                  f"was made: move it back, or {self.new_path_hint()}")
                self.check_left(obs, self.new_path_hint(), path)
            moved = True
            if self.waypoint == W:
                raise Stopped(Stop.COMPLETED, f"path followed: {W} waypoints in {self.follow_steps} moves")
            wc = min(self.waypoint, W - 1)
            err = math.hypot(float(e_p[wc]), self.scale * float(e_r[wc]))  # to the waypoint pursued [m]
            if dist > env.diverge_dist:
                self.limits_first(err, W, f"the tracked point went {dist:.4g} m from the path (diverge_dist)")
                raise Stopped(Stop.DIVERGENCE, f"{dist:.4g} m from the path towards waypoint {self.waypoint + 1} "
                              f"(diverge_dist = {env.diverge_dist:g})")
            if self.follow_steps >= path.steps:
                self.limits_first(err, W, f"max_steps ({path.steps} moves) ran out")
                raise Stopped(Stop.MAX_STEPS, f"waypoint {self.waypoint + 1} of {W} not reached in "
                              f"{path.steps} moves")
            raw = obs.q + cmd.dq
            target = np.clip(raw, env.lower, env.upper)
            cut = np.abs(raw - target)  # (n,) the part of each actuator's step the limits removed
            self.pinned = tuple((int(i), bool(cmd.dq[i] > 0)) for i in np.flatnonzero(cut > 0.5 * np.abs(cmd.dq)))
            self.track_stall(err, W, path.tol)
            clipped = float(np.linalg.norm(cut)) > 0.05 * float(np.linalg.norm(cmd.dq))
            self.follow_steps += 1
            self.move(target, obs, "follow", self.follow_steps - 1)
            self.sleep(self.opts.settle_s)
            base, obs = obs, self.read("follow")
            if not self.is_fresh(obs):
                self.follow_rejected += 1
                self.journal.append({"e": "rejected", "phase": "follow", "k": self.follow_steps - 1,
                                     "reason": "dropout" if not obs.valid else "stale"})
                obs = self.fresh("follow")
            self.after_move(base, target, obs, clipped)

    # ---- following: what the limits, the tracker's noise and a resumed session's robot allow

    def limit_text(self, i: int, up: bool) -> str:
        """``"upper limit 1.5 (the user's limits_upper)"``: actuator ``i``'s limit in that direction, and whose."""
        user = self.opts.upper if up else self.opts.lower
        value = (self.env.upper if up else self.env.lower)[i]
        mine = user is not None and float(np.broadcast_to(np.asarray(user, np.float64), (self.n,))[i]) == value
        return (f"{'upper' if up else 'lower'} limit {value:.4g} (" +
                (f"the user's safety.limits_{'upper' if up else 'lower'}" if mine else "the driver's") + ")")

    def offset_text(self, offset: np.ndarray) -> str:
        """A waypoint offset's size in words: ``"123 mm"``, ``"0.3 rad"``, or both."""
        P = len(self.position_axes)
        parts = [f"{1e3 * float(np.linalg.norm(offset[:P])):.4g} mm"] if P else []
        if offset.shape[0] > P and float(np.linalg.norm(offset[P:])) > 0:
            parts.append(f"{float(np.linalg.norm(offset[P:])):.4g} rad")
        return " and ".join(parts) if parts else "0 mm"

    def stall_text(self, err: float, W: int) -> str:
        assert self.offsets is not None
        w = min(self.waypoint, W - 1)
        held = ", ".join(f"{self.labels[i]} is held at its {self.limit_text(i, up)}" for i, up in self.pinned)
        return (f"waypoint {w + 1} of {W} ({self.offset_text(self.offsets[w])} from where following started) is "
                f"out of reach within the limits: {held}, and the pose is still {1e3 * err:.3g} mm from it")

    def track_stall(self, err: float, W: int, tol: float) -> None:
        """Count the moves with an actuator held at a limit (``self.pinned``) in which the waypoint pursued came
        no nearer than ``tol`` [m] of its best; at :data:`STALL_MOVES` stop (unreachable) before the move."""
        if not self.pinned:
            self.stall = None
            return
        s = self.stall
        if s is None or s[0] != self.waypoint:
            s = self.stall = [self.waypoint, err, 0]
        elif err < s[1] - tol:
            s[1], s[2] = err, 0
        else:
            s[2] += 1
        if s[2] >= STALL_MOVES:
            raise Stopped(Stop.UNREACHABLE, f"{self.stall_text(err, W)} after {STALL_MOVES} moves with no "
                          "progress. No further move was made: a nearer path, or wider limits")

    def far_first(self, obs: Observation, error_pct: float) -> None:
        """Before an estimate stop while following: where an actuator is more than :data:`FAR_MOVES` of its m_a
        from where following started, the estimate is being used far from where it was identified, towards a
        waypoint that far: the stop names the waypoint (unreachable)."""
        if self.follow_q is None or self.offsets is None:
            return
        far = np.abs(obs.q - self.follow_q) / self.m_a
        i = int(np.argmax(far))
        if far[i] <= FAR_MOVES:
            return
        W = self.offsets.shape[0]
        w = min(self.waypoint, W - 1)
        raise Stopped(Stop.UNREACHABLE, f"waypoint {w + 1} of {W} ({self.offset_text(self.offsets[w])} from where "
                      f"following started) looks out of reach: following has moved {self.labels[i]} by "
                      f"{obs.q[i] - self.follow_q[i]:+.4g} ({far[i]:.0f} m_a) towards it, and this far from where "
                      f"the estimate was identified it predicts the motion with {error_pct:.0f}% error (an inverse "
                      "Jacobian holds near the pose it was identified at). No further move was made: a nearer "
                      "path, or self-ID nearer to it")

    def limits_first(self, err: float, W: int, what: str) -> None:
        """Before a divergence or max_steps stop: where the last move was held at a limit, that is the cause
        (unreachable), named with what would have stopped."""
        if self.pinned:
            raise Stopped(Stop.UNREACHABLE, f"{self.stall_text(err, W)}; {what} while it was held there")

    def measure_noise(self, obs: Observation) -> Observation:
        """The tracker's noise per axis at rest, from ``obs`` and further readings with new poses
        (:data:`NOISE_READS` in all, no motion), logged (a ``noise`` record) and kept as ``self.noise`` (position
        m, rotation rad); returns the last reading."""
        ps, rs, last = [obs.position], [np.zeros(3)], obs
        while len(ps) < NOISE_READS:
            self.check_interrupt()
            new = self.read("follow")
            if new.valid and new.tracker_t > last.tracker_t:
                ps.append(new.position)
                rs.append(task_difference(new, obs, (3, 4, 5)))
                last = new
            else:
                self.sleep(self.opts.poll_s)
        self.noise = tracker_noise(np.array(ps), np.array(rs))
        self.journal.append({"e": "noise", "position": self.noise[0], "rotation": self.noise[1], "reads": len(ps)})
        return last

    def new_path_hint(self) -> str:
        """What a ``moved`` stop while following suggests: a new path from here, with the estimate this session
        actually has (the given one's source, or the one this run directory's self-ID wrote)."""
        if self.given is not None:
            src = self.given[1]
            where = "the same estimate array" if src == "array" else f"--estimate {src}"
        else:
            where = f"--estimate {self.journal.path.parent / 'inverse_jacobian.npz'}"
        return f"follow a new path from here with this estimate in a new run directory ({where})"

    def check_left(self, obs: Observation, hint: str, path=None) -> None:
        """Once, at a resumed session's first reading ``obs``: ``moved`` where an actuator is more than its
        ``m_a`` outside the range between where the log last read it and its last target (a move in flight),
        or, while following (``path``), the tracked point more than ``2 max_task_step + tol`` from where the log
        last saw it. No move was made."""
        if self.left is None:
            return
        q, p, target = self.left
        self.left = None
        lo, hi = (q, q) if target is None else (np.minimum(q, target), np.maximum(q, target))
        off = np.maximum(obs.q - hi, lo - obs.q)
        bad = np.flatnonzero(off > self.m_a)
        if bad.size:
            i = bad[0]
            raise Stopped(Stop.MOVED, f"{self.labels[i]} is {obs.q[i] - q[i]:+.4g} from where the log left it "
                          f"(it was at {q[i]:.4g}; m_a = {self.m_a[i]:.4g} allowed): the robot moved since the log's "
                          f"last session. No move was made: move it back, or {hint}")
        if path is not None and p is not None and obs.valid:
            d, allowed = float(np.linalg.norm(obs.position - p)), 2 * path.max_task_step + path.tol
            if d > allowed:
                raise Stopped(Stop.MOVED, f"the tracked point is {1e3 * d:.4g} mm from where the log left it "
                              f"({1e3 * allowed:.3g} mm allowed: 2 max_task_step + tol): the robot moved since "
                              f"the log's last session. No move was made: move it back, or {hint}")

    # ---- resume

    def replay(self, log: JournalContents) -> int:
        """Fold the log's accepted samples into the state (the same jitted step); return how many."""
        assert self.state is not None
        logged_conv = -1
        replayed = 0
        # the last reading's q and p (valid ones only) and the last target, and the three as the session began
        left_q: np.ndarray | None = None
        left_p: np.ndarray | None = None
        left_target: np.ndarray | None = None
        before: tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None] = (None, None, None)
        for rec in log.records:
            e = rec["e"]
            if e == "session":
                before = (left_q, left_p, left_target)
            elif e == "stop" and rec.get("reason") == Stop.MOVED.value:  # it made no move: where it found the
                left_q, left_p, left_target = before  # robot is not where the log left it (that stopped it)
            elif e == "obs":
                left_q = floats(rec["q"])
                left_p = floats(rec["p"]) if rec.get("valid") else left_p
            elif e == "move":
                left_target = floats(rec["target"])
            if e == "sample":
                self.k = max(self.k, int(rec["k"]) + 1)
                if rec["accepted"]:
                    self.state, _ = sample_step(self.state, floats(rec["dtheta"]), floats(rec["V"]), self.opts.eps,
                                                self.opts.eps_rel, method=self.opts.method, min_count=self.min_count)
                    self.samples += 1
                    self.pairs.append((floats(rec["dtheta"]), floats(rec["V"])))
                    replayed += 1
                    logged_conv = int(rec["converged_at"])
                else:
                    self.rejected[rec["reason"]] = self.rejected.get(rec["reason"], 0) + 1
            if e == "move":
                if rec["phase"] == "selfid":
                    self.moves += 1
                else:
                    self.follow_steps += 1
            elif e == "follow":
                q = np.zeros(self.n)
                self.anchor = Observation(0.0, q, floats(rec["p"]), floats(rec["quat"]), 0.0, True)
                self.offsets = np.array([floats(r) for r in rec["offsets"]])
                self.follow_q = floats(rec["q"]) if rec.get("q") is not None else None
                self.waypoint = 0
            elif e == "centre":
                self.centre = floats(rec["q"])
            elif e == "reference":
                self.reference = np.array([floats(r) for r in rec["jacobian"]])
            elif e == "waypoint":
                self.waypoint = int(rec["reached"]) + 1
            elif e == "rejected":
                self.follow_rejected += 1
            elif e == "estimate":  # following with a given estimate (no self-ID)
                est = rec["estimate"]
                self.given = (np.array([floats(r) for r in est]).reshape(len(est), -1), str(rec["source"]))
        if left_q is not None:
            self.left = (left_q, left_p, left_target)
        conv = int(self.state.converged_at)
        if conv != logged_conv and not (logged_conv < 0 and conv < 0):
            raise ResumeError(f"{self.journal.path}: replaying the log's {replayed} samples gives convergence at "
                              f"{conv}, the log recorded {logged_conv}; it was written by another estimator "
                              "(version, platform) and cannot be continued")
        return replayed
