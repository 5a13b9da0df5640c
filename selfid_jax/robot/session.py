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
* :meth:`Session.replay` folds a logged session back into the state (resume).

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
from selfid_jax.robot.protocol import Observation, Robot, RobotError
from selfid_jax.robot.quality import Quality, held_out
from selfid_jax.robot.safety import (
    COMMAND_MEMORY,
    Commanded,
    Envelope,
    Sight,
    actuation_target,
    angle_between,
    check_observation,
)
from selfid_jax.robot.steps import follow_command, host_step, sample_step, task_difference

__all__ = ["DriverFault", "ResumeError", "Session", "Stop", "Stopped"]


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
        self.predict: np.ndarray | None = None  # (P, n) pinv of the estimate while following: dq -> predicted dp
        self.position_axes = [a for a in axes if a < 3]  # the task's P position axes, indices into (x, y, z)
        self.residual = (0.0, 0.0, 0)  # following: recent-weighted sums of |dp - predicted dp|, |predicted dp|; moves
        self.pairs: list[tuple[np.ndarray, np.ndarray]] = []  # the accepted samples (dtheta (n,), V (m,))
        self.quality: Quality | None = None
        self.given: tuple[np.ndarray, str] | None = None  # (estimate, source) followed without self-ID, if given

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
            raise Stopped(Stop.LIMITS, f"actuator {i} at {obs.q[i]:.6g}, outside [{env.lower[i]:.6g}, "
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

    def after_move(self, base: Observation, target: np.ndarray, obs: Observation) -> None:
        """The command-following, held-out prediction and motion-versus-sight checks of one move from ``base``
        towards ``target``, read back as ``obs``; raises :class:`Stopped` (``actuator``, ``estimate``,
        ``tracker_frozen``) before any further move."""
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
                raise Stopped(Stop.ACTUATOR, f"actuator {i} moved {100 * ratio[i]:.0f}% of what it was commanded "
                              f"over {c.moves} moves ({c.along[i]:.4g} of {c.commanded[i]:.4g}; follow_min_ratio "
                              f"{opts.follow_min_ratio:g}): stuck, slow or not settled")
        if not obs.valid:
            return
        pred = None if self.predict is None else self.predict @ dq  # (P,) predicted position change [m]
        if pred is not None:  # following: each move is a held-out sample of the estimate
            miss = float(np.linalg.norm((obs.position - base.position)[self.position_axes] - pred))
            r = self.residual
            r = self.residual = (w * r[0] + miss, w * r[1] + float(np.linalg.norm(pred)), r[2] + 1)
            if r[2] >= opts.follow_min_moves and r[0] > opts.follow_max_residual * r[1]:
                raise Stopped(Stop.ESTIMATE, f"the estimate predicts the tracked motion of the last moves with "
                              f"{100 * r[0] / r[1]:.0f}% error (follow_max_residual {opts.follow_max_residual:g}): "
                              "the robot no longer moves as it was self-identified (a changed grasp or load, a "
                              "joint, the tracker's frame); self-identify again")
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
                          f"{self.opts.max_heldout_error:g}); the weakest actuator, {weakest}, moves the point "
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
                raise Stopped(Stop.MOVED, f"actuator {i} is {base.q[i] - self.centre[i]:+.4g} from where self-ID "
                              f"started ({self.centre[i]:.4g}; (wander + 1) m_a = {reach[i]:.4g}): the robot moved "
                              "since the log's last session. No move was made: move it back, or start a new run "
                              "directory")
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
        if self.anchor is None:
            planned = path.offsets(self.axes)
            where = obs.position + path.positions(self.axes)  # the planned waypoints' positions (box check)
            out = np.flatnonzero(np.any((where < env.box_low) | (where > env.box_high), axis=1))
            if out.size:
                raise Stopped(Stop.BOX, f"the path leaves the box at waypoint {out[0] + 1} of {len(planned)} "
                              f"({where[out[0]].round(6).tolist()} m); no following move was made")
            self.anchor, self.offsets, self.waypoint = obs, planned, 0
            self.journal.append({"e": "follow", "p": obs.position, "quat": obs.quaternion, "offsets": planned})
        anchor, offsets = self.anchor, self.offsets
        assert offsets is not None and anchor is not None
        W = offsets.shape[0]
        ctrl = path.controller(env)
        rows = [i for i, a in enumerate(self.axes) if a in self.position_axes]
        self.predict = np.linalg.pinv(Jinv)[rows]  # (P, n): dq -> predicted change of the task's positions
        moved = False  # a reading after a move of this call (not the one following starts or resumes from)
        while True:
            cmd, dist = follow_command(Jinv, offsets, anchor, self.waypoint, obs, ctrl, self.axes)
            if cmd.reached:
                self.journal.append({"e": "waypoint", "reached": self.waypoint})
            self.waypoint = int(cmd.waypoint)
            if moved:
                self.report({"phase": "follow", "step": self.follow_steps, "waypoint": self.waypoint,
                             "waypoints": W, "distance": dist})
            if resumed and not moved and dist > env.diverge_dist:
                raise Stopped(Stop.MOVED, f"the tracked point is {dist:.4g} m from the log's path (diverge_dist "
                              f"{env.diverge_dist:g}): the robot moved since the log's last session. No move was "
                              "made: move it back, or follow a new path from here with this estimate in a new run "
                              "directory (--estimate RUN/inverse_jacobian.npz)")
            moved = True
            if self.waypoint == W:
                raise Stopped(Stop.COMPLETED, f"path followed: {W} waypoints in {self.follow_steps} moves")
            if dist > env.diverge_dist:
                raise Stopped(Stop.DIVERGENCE, f"{dist:.4g} m from the path towards waypoint {self.waypoint + 1} "
                              f"(diverge_dist = {env.diverge_dist:g})")
            if self.follow_steps >= path.steps:
                raise Stopped(Stop.MAX_STEPS, f"waypoint {self.waypoint + 1} of {W} not reached in "
                              f"{path.steps} moves")
            target = np.clip(obs.q + cmd.dq, env.lower, env.upper)
            self.follow_steps += 1
            self.move(target, obs, "follow", self.follow_steps - 1)
            self.sleep(self.opts.settle_s)
            base, obs = obs, self.read("follow")
            if not self.is_fresh(obs):
                self.follow_rejected += 1
                self.journal.append({"e": "rejected", "phase": "follow", "k": self.follow_steps - 1,
                                     "reason": "dropout" if not obs.valid else "stale"})
                obs = self.fresh("follow")
            self.after_move(base, target, obs)

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
                                                self.opts.eps_rel, method=self.opts.method, min_count=self.min_count)
                    self.samples += 1
                    self.pairs.append((floats(rec["dtheta"]), floats(rec["V"])))
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
        conv = int(self.state.converged_at)
        if conv != logged_conv and not (logged_conv < 0 and conv < 0):
            raise ResumeError(f"{self.journal.path}: replaying the log's {replayed} samples gives convergence at "
                              f"{conv}, the log recorded {logged_conv}; it was written by another estimator "
                              "(version, platform) and cannot be continued")
        return replayed
