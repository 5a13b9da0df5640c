"""Algorithm 1 live on a robot: random actuations, the jitted per-sample estimator step, then an optional path.

:func:`run_online` drives a :class:`~selfid_jax.robot.protocol.Robot` through
one session in a run directory:

1. **Self-ID** (Algorithm 1). From a fresh tracker reading at rest it draws
   ``dtheta ~ uniform(-m_a, m_a)`` per actuator (:func:`~selfid_jax.robot.safety.actuation_target`),
   commands ``move(q + dtheta)``, waits ``settle_s`` and reads again; the
   sample is ``(q_new - q_old (n,), V (m,))`` with ``V = [p_t - p_{t-1},
   log(R_t R_{t-1}^T)][axes]`` from the two tracker poses
   (:func:`~selfid_jax.robot.steps.task_difference`, Eq. 1's pose change). A reading with no pose
   (``valid`` False: a dropout) or whose pose is not newer than the reading
   before the move (a stale tracker) is rejected, counted by reason, and
   followed by a fresh reading at rest (no motion) before the next draw.
   Each accepted sample runs the jitted
   :func:`selfid_jax.identify.step.sample_step`
   (update Eq. 6-12, guess Eq. 13, refine Eq. 14, record Sec. IV-D), compiled
   once per ``(n, m, method, dtype)`` (:func:`~selfid_jax.robot.steps.sample_step`). The first time
   the Sec. IV-D test holds (``state.converged_at >= 1``) self-ID stops:
   **no further random move is ever commanded**, in this session or a
   resumed one. So the robot makes exactly ``converged_at + rejected`` random
   moves.
2. **Follow** (optional, ``OnlineOptions.path``): the converged estimate is
   a fixed inverse Jacobian, and each step is the simulated follow loop's
   control step (:func:`selfid_jax.control.law.command`, run on the host:
   :func:`selfid_jax.robot.steps.follow_command`) with the controller
   settings :meth:`FollowOptions.controller` builds from the path options and
   the envelope: the waypoint advances within ``tol`` [m] (and ``rot_tol``
   [rad]), the twist is ``gain`` times the error with its position part
   capped at ``max_task_step`` [m] and its rotation part at ``max_rot_step``
   [rad], the actuator step is scaled down to the envelope's ``max_step`` and
   clipped to its limits, and a distance from the path above
   ``diverge_dist`` stops. ``control.follow`` with the same
   :class:`~selfid_jax.control.task.ControllerParams` on a model of the
   robot commands the same targets (``tests/test_online.py``). Without a path
   the session ends at convergence and the robot stays where it is.
   With ``OnlineOptions.estimate`` (an ``.npz`` of ``selfid-jax fit`` or
   of an earlier session, or an ``(n, m)`` array; :func:`given_estimate`
   checks its shape and task axes) there is no self-ID: the path is
   followed with that estimate, which the log records (an ``estimate``
   record: a resume continues with it, and refuses to mix it with a logged
   self-ID).

The safety envelope (:class:`~selfid_jax.robot.safety.Envelope`) holds throughout: every commanded
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

numpy and JAX only: no files other than the log, no pydantic, no runner (an
online session, :func:`selfid_jax.sessions.online_run.run_session`, which the
``selfid-jax online`` command calls, owns the run directory's lock, the config
and the summary files).
"""


from __future__ import annotations

import math
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from selfid_jax.identify import estimator
from selfid_jax.math.checks import check_magnitude, float_dtype
from selfid_jax.robot.journal import Journal, read_journal
from selfid_jax.robot.log import parse_task
from selfid_jax.robot.options import AXIS_NAMES, MIN_SAMPLES_PER_AXIS, ONLINE_METHODS, FollowOptions, OnlineOptions
from selfid_jax.robot.protocol import Robot, RobotConnectionError, RobotError, check_limits, joint_labels
from selfid_jax.robot.quality import Quality, Trust, read_trust, record_flags, record_lines, trust
from selfid_jax.robot.safety import check_path_reach, check_room, envelope, reach_bound
from selfid_jax.robot.session import DriverFault, ResumeError, Session, Stop, Stopped
from selfid_jax.robot.steps import init_state, sample_step

__all__ = ["ACCEPT_FLAGGED", "LOG_FILE", "EstimateFile", "OnlineResult", "close_robot", "given_estimate",
           "read_estimate", "run_online", "trust_lines"]

LOG_FILE = "session.jsonl"
LOG_VERSION = 2  # 2: following logs rejected readings; the follow law is control.law.command


class OnlineResult(NamedTuple):
    """What a session did (counts over the whole log, resumed sessions included)."""

    status: Stop
    detail: str  # one line: what stopped the session
    estimate: np.ndarray  # (n, m) inverse Jacobian after the last accepted sample (Eq. 14); zeros before any
    state: estimator.EstimatorState  # estimator state (numpy leaves)
    converged_at: int  # 1-based accepted-sample index meeting Sec. IV-D, -1 if never
    samples: int  # accepted samples (estimator steps)
    rejected: dict[str, int]  # rejected self-ID samples by reason ("dropout", "stale")
    moves: int  # random self-ID moves issued (== samples + sum(rejected), plus one whose outcome a stop lost)
    follow_steps: int  # moves issued while following
    follow_rejected: int  # readings after a following move with no fresh pose (no command was made from them)
    waypoints: int  # waypoints reached
    waypoints_total: int  # waypoints of the path (0 without one)
    replayed: int  # accepted samples replayed from the log on resume (0 for a fresh session)
    truncated: int  # cut-short log lines dropped on resume (0 or 1)
    step_ms: np.ndarray  # (k,) latency of each estimator step run in this session, ms (replays excluded)
    quality: Quality | None  # the converged samples' held-out error and actuator effects; None before convergence
    axes: tuple[int, ...]  # task axes into (x, y, z, rx, ry, rz)
    log: Path  # the session log
    track: np.ndarray = np.zeros(0)  # (s,) m, path distance after each following move (the log's, resumes included)
    selfid_s: float = 0.0  # s of wall time in self-ID (moves, reads, estimator; every session of the log)
    follow_s: float = 0.0  # s of wall time following the path (every session of the log)
    estimate_source: str | None = None  # where a given estimate came from (OnlineOptions.estimate); None: self-ID
    reference: np.ndarray | None = None  # (6, n) the driver's model Jacobian (Robot.jacobian) where self-ID started,
    #   or, following with a given estimate, where following started
    trust: Trust | None = None  # the converged samples' trust figures and warnings (quality.trust); None before
    given_trust: dict | None = None  # a given estimate's file: its quality.trust_record; None for a file without one
    given_converged_at: int | None = None  # a given estimate's file: its convergence sample (None: not recorded)
    close_error: str | None = None  # closing the driver after the stop failed: that failure, one line (None: closed)

    @property
    def reference_error(self) -> float | None:
        """``||J Ĵ - I||_F``: the estimate against the driver's model Jacobian ``J`` (its task rows) where self-ID
        started (following with a given estimate: where following started); None without a reference."""
        if self.reference is None:
            return None
        J = self.reference[list(self.axes)]
        return float(np.linalg.norm(J @ self.estimate - np.eye(J.shape[0])))

    @property
    def converged(self) -> bool:
        return self.converged_at > 0


def min_samples(opts: OnlineOptions, m: int) -> int:
    """The least accepted samples before Sec. IV-D counts: ``opts.min_samples``, or
    :data:`~selfid_jax.robot.options.MIN_SAMPLES_PER_AXIS` per task axis."""
    return MIN_SAMPLES_PER_AXIS * m if opts.min_samples is None else int(opts.min_samples)


def _header(n: int, m: int, axes, m_a: np.ndarray, opts: OnlineOptions, dtype) -> dict[str, Any]:
    return {"e": "header", "version": LOG_VERSION, "n": n, "m": m, "axes": list(axes), "m_a": m_a.tolist(),
            "eps": float(opts.eps), "eps_rel": float(opts.eps_rel), "seed": int(opts.seed), "method": opts.method,
            "v_tol": float(opts.v_tol), "dtype": np.dtype(dtype).name,
            "wander": None if opts.wander is None else float(opts.wander), "min_samples": min_samples(opts, m)}


OLDER_LOGS = {"wander": None, "min_samples": 0}
"""What a log written before these header keys did: an unbounded walk, the paper's Sec. IV-D from the start."""


def _check_header(path: Path, logged: dict[str, Any], expected: dict[str, Any]) -> None:
    for key, want in expected.items():
        if key == "e":
            continue
        got = logged.get(key, OLDER_LOGS.get(key, "(missing)"))
        if got != want:
            raise ResumeError(f"{path}: cannot resume: the log's {key} is {got!r}, this session's is {want!r}; "
                              "use the log's value or start a new run directory")


def _check_path(path: Path, logged, follow: FollowOptions | None, axes) -> None:
    """ResumeError unless a session whose log started following resumes with the same path (its waypoints)."""
    if logged is None or follow is None:
        return
    planned = follow.offsets(axes)
    if planned.shape != logged.shape or not np.allclose(planned, logged, rtol=0, atol=1e-12):
        raise ResumeError(f"{path}: cannot resume: the log started following a path of {logged.shape[0]} waypoints "
                          f"(extent {np.ptp(logged, axis=0).round(6).tolist()} m), this session's path differs "
                          "(path.kind, path.size, path.plane, path.waypoints or the rows of path.file); resume "
                          "with the logged path, or start a new run directory")


class EstimateFile(NamedTuple):
    """An estimate file (``inverse_jacobian.npz`` of ``selfid-jax fit`` or ``selfid-jax online``) as read."""

    estimate: np.ndarray  # (n, m) inverse Jacobian, float64
    task_axes: list[str]  # the task axes it serves, e.g. ["x", "y", "z"]
    trust: dict | None  # its quality.trust_record (figures, warnings, report); None: written before files carried one
    converged_at: int | None  # the sample at which its self-ID converged (Sec. IV-D), None where not recorded


NPZ_EXPECTED = "expected the inverse_jacobian.npz that selfid-jax fit or selfid-jax online writes"


def read_estimate(path: str | Path) -> EstimateFile:
    """Read an estimate file: ``inverse_jacobian`` ``(n, m)``, ``task_axes`` and, where it carries one, its trust
    record (:func:`selfid_jax.robot.quality.read_trust`).

    Raises ValueError starting with the file's name and saying what was
    expected: no such file, not an npz (a zip archive: a text, YAML or
    ``.npy`` file is refused without reading it as one), no
    ``inverse_jacobian`` or ``task_axes`` entry, an unreadable trust entry.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file ({NPZ_EXPECTED})")
    try:
        with path.open("rb") as f:
            head = f.read(4)
    except OSError as err:
        raise ValueError(f"{path}: cannot be read ({err.strerror or err})") from None
    if head != b"PK\x03\x04":  # an .npz is a zip archive; anything else is not read (numpy would try pickle)
        raise ValueError(f"{path}: not an .npz file ({NPZ_EXPECTED})")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in ("inverse_jacobian", "task_axes") if k not in z.files]
            if missing:
                raise ValueError(f"{path}: has no {missing[0]!r} entry ({NPZ_EXPECTED})")
            est = np.array(z["inverse_jacobian"], np.float64)
            axes = [str(a) for a in np.atleast_1d(z["task_axes"]).tolist()]
            try:
                record = read_trust(z)
            except ValueError as err:
                raise ValueError(f"{path}: {err}") from None
            conv = int(z["converged_at"]) if "converged_at" in z.files else None
    except ValueError as err:
        if str(err).startswith(str(path)):
            raise
        raise ValueError(f"{path}: cannot be read as an .npz ({' '.join(str(err).split())}; {NPZ_EXPECTED})"
                         ) from None
    except Exception as err:  # noqa: BLE001 - a corrupt archive: one message naming it
        raise ValueError(f"{path}: cannot be read as an .npz ({type(err).__name__}: {err}; {NPZ_EXPECTED})"
                         ) from None
    if record is not None and isinstance(record.get("converged_at"), int):
        conv = int(record["converged_at"])
    return EstimateFile(est, axes, record, conv)


ACCEPT_FLAGGED = "accept_flagged_estimate=True"
"""How :func:`run_online`'s caller follows with a flagged estimate file (the command line's is
``--accept-flagged-estimate``)."""


def trust_lines(path: str | Path, read: EstimateFile, *, accept_flagged: bool = False,
                accept: str = ACCEPT_FLAGGED) -> list[str]:
    """The lines that show an estimate file's trust figures (``read``: its :func:`read_estimate`), or a refusal.

    A file whose trust record is flagged (:func:`selfid_jax.robot.quality.record_flags`: trust warnings, or not
    converged) raises ValueError starting with ``path`` and naming each flag and ``accept`` (how to follow with it
    anyway), unless ``accept_flagged``; then a last line says it is followed despite them. A file written before
    estimate files carried a trust record is accepted, and its line says so.
    """
    record = read.trust
    if record is None:
        return [f"estimate {path}: carries no trust figures (written before estimate files carried them); "
                "followed unchecked"]
    made = f"{record.get('source', '?')} of {record.get('log', '?')}"
    head, *rest = record_lines(record)
    flags = record_flags(record)
    if flags and not accept_flagged:
        raise ValueError(f"{path}: flagged, not followed ({made}: {head}): {'; '.join(flags)}. Self-identify again, "
                         f"or follow with it anyway with {accept}")
    return [f"estimate {path} ({made}): {head}", *(f"  {x}" for x in rest),
            *([f"  {accept}: following with it despite {len(flags)} flag(s)"] if flags else [])]


def given_estimate(value, n: int, axes: tuple[int, ...], *, read: EstimateFile | None = None
                   ) -> tuple[np.ndarray, str]:
    """``(estimate (n, m), source)`` of ``OnlineOptions.estimate``: an ``.npz`` file of ``selfid-jax fit`` or
    ``selfid-jax online`` (``inverse_jacobian`` and ``task_axes``; :func:`read_estimate`) or an ``(n, m)`` array
    (source ``"array"``).

    Raises ValueError naming the file (or ``estimate``) and what differs: no
    such file, not an npz, a missing key, task axes other than ``axes``, a
    shape other than ``(n, m)`` (``n`` the robot's actuators, ``m`` the
    task's axes), a value that is not finite. ``read``: the file's
    :func:`read_estimate`, where the caller has already read it.
    """
    m = len(axes)
    names = ",".join(AXIS_NAMES[a] for a in axes)
    if isinstance(value, (str, Path)):
        path = Path(value)
        where, source = f"estimate: {path}", str(path)
        if read is None:
            read = _read_given(path)
        est, logged = read.estimate, read.task_axes
        if logged != [AXIS_NAMES[a] for a in axes]:
            raise ValueError(f"{where}: its task axes are {','.join(logged)}, the task is {names} (selfid.task); "
                             "an estimate serves only the task it was identified for")
    else:
        where, source = "estimate", "array"
        try:
            est = np.array(value, np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{where}: not an array of numbers: {err}") from None
    if est.shape != (n, m):
        raise ValueError(f"{where}: the inverse Jacobian is {est.shape}, expected ({n}, {m}): {n} actuators (the "
                         f"robot's limits) by {m} task axes ({names})")
    if not np.all(np.isfinite(est)):
        raise ValueError(f"{where}: the inverse Jacobian has values that are not finite")
    return est, source


def _read_given(path: str | Path) -> EstimateFile:
    """:func:`read_estimate` of the given estimate, its errors prefixed ``estimate:``."""
    try:
        return read_estimate(path)
    except ValueError as err:
        raise ValueError(f"estimate: {err}") from None


def _check_estimate(path: Path, session: Session, given: tuple[np.ndarray, str] | None
                    ) -> tuple[np.ndarray, str] | None:
    """The estimate a resumed session follows with: the log's (an ``estimate`` record) or ``given``; ResumeError
    where the log self-identified and an estimate is given, or the log's given estimate differs from this one."""
    logged = session.given
    if given is not None and session.k > 0:
        raise ResumeError(f"{path}: cannot resume with the estimate from {given[1]}: the log self-identified "
                          f"({session.k} random moves, {session.samples} samples); following with a given estimate "
                          "would mix the two. Resume without the estimate, or start a new run directory")
    if given is not None and logged is not None and (
            logged[0].shape != given[0].shape or not np.allclose(logged[0], given[0], rtol=0, atol=1e-12)):
        raise ResumeError(f"{path}: cannot resume: the log follows with the estimate from {logged[1]}, this "
                          f"session's from {given[1]} differs; resume with the logged one (or none: the log keeps "
                          "it), or start a new run directory")
    return logged if logged is not None else given


def _check_options(opts: OnlineOptions, n: int) -> tuple[tuple[int, ...], np.ndarray]:
    axes = parse_task(opts.task)
    if axes is None:
        raise ValueError("task: give the task axes, e.g. 'x,y,z'")
    m_a = np.asarray(check_magnitude("m_a", np.asarray(opts.m_a, np.float64), n), np.float64)
    m_a = np.broadcast_to(m_a, (n,)).copy()
    estimator.check_thresholds(opts.eps, opts.eps_rel)
    if opts.method not in ONLINE_METHODS:
        raise ValueError(f"method: expected one of {ONLINE_METHODS} (the per-sample step is jitted), got "
                         f"{opts.method!r}")
    for name in ("max_samples", "seed"):
        v = getattr(opts, name)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (1 if name == "max_samples" else 0):
            raise ValueError(f"{name}: expected an integer >= {1 if name == 'max_samples' else 0}, got {v!r}")
    for name in ("seen_min", "seen_min_rad", "frozen_dist", "follow_min_ratio", "follow_max_residual",
                 "max_heldout_error") + \
            (("frozen_motion",) if opts.frozen_motion is not None else ()):
        v = getattr(opts, name)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name}: must be a finite number > 0, got {v!r}")
    if opts.wander is not None and not (isinstance(opts.wander, (int, float)) and math.isfinite(opts.wander)
                                        and opts.wander >= 0.5):
        raise ValueError(f"wander: must be a number >= 0.5 (multiples of m_a) or None, got {opts.wander!r}")
    if opts.follow_min_ratio > 1:
        raise ValueError(f"follow_min_ratio: must be in (0, 1], got {opts.follow_min_ratio!r}")
    v = opts.min_samples
    if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0):
        raise ValueError(f"min_samples: expected an integer >= 0 or None, got {v!r}")
    v = opts.follow_min_moves
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise ValueError(f"follow_min_moves: expected an integer >= 1, got {v!r}")
    for name, lo in (("settle_s", 0.0), ("poll_s", 1e-6)):
        v = getattr(opts, name)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= lo):
            raise ValueError(f"{name}: expected a finite number of seconds >= {lo:g}, got {v!r}")
    return axes, m_a


def run_online(robot: Robot, options: OnlineOptions, run_dir: str | Path, *, resume: bool = False,
               stop_requested: Callable[[], bool] | None = None,
               sleep: Callable[[float], None] = time.sleep,
               progress: Callable[[dict[str, Any]], None] | None = None,
               accept_flagged_estimate: bool = False) -> OnlineResult:
    """Self-identify the robot's inverse Jacobian live (Algorithm 1), then follow ``options.path`` with it.

    ``robot``: a connected driver (:class:`~selfid_jax.robot.protocol.Robot`);
    it is closed when the session ends, however it ends; a ``close()`` that
    raises does not replace the session's stop or error: it is the result's
    ``close_error`` (and the log's ``close`` record), or a note on the error
    raised. ``run_dir``: where
    the session log (``session.jsonl``) is appended; created if missing.
    ``resume``: continue the session logged there (see the module docstring);
    without it a run directory that already holds a log is refused.
    ``stop_requested``: polled before every read and command; True ends the
    session as :attr:`Stop.INTERRUPTED` (a signal handler sets it);
    KeyboardInterrupt does the same. ``sleep``: the settle/poll wait.
    ``progress``: called with one event (a dict, after it is logged) as the
    session goes: ``{"phase": "selfid", "move", "sample", "accepted", "delta",
    "threshold", "converged_at"}`` after each self-ID draw (``move`` counts
    draws, ``sample`` accepted samples; ``delta`` is ``||J_t - J_{t-1}||_F``,
    ``threshold`` Sec. IV-D's; a rejected draw has ``"reason"`` instead of the
    estimator's fields), ``{"phase": "follow", "step", "waypoint",
    "waypoints", "distance"}`` after each following move (waypoints reached
    out of the path's, the path distance [m]), and ``{"phase": "stop",
    "status", "detail"}`` once at the end. It runs in the loop: keep it quick.
    ``accept_flagged_estimate``: follow with an ``options.estimate`` file
    whose trust record is flagged (:func:`trust_lines`: trust warnings, or
    not converged), which is otherwise refused (the command line's
    ``--accept-flagged-estimate``).

    Returns an :class:`OnlineResult`; the session's stop is its ``status``
    (a :class:`selfid_jax.robot.session.Stop`: a safety stop is a result,
    not an exception).

    A start position outside the limits or the box, or a path that would
    leave the box, ends the session before any motion with that status. A
    waypoint farther from where following starts than any two positions of
    the tracked point can be apart (a driver that states its ``reach``:
    :func:`~selfid_jax.robot.safety.reach_bound`) is refused (ValueError)
    before any motion, self-ID's included.

    Every error below is raised before any motion, and the robot is closed first.

    Raises:
      ValueError: an option out of range (the message names it), ``m_a``
        above the envelope's ``max_step``, or a given estimate file that is
        not one, serves another task or is flagged (unless accepted).
      ResumeError: the log disagrees with the options (names the field), or
        ``resume`` without a log / a log without ``resume``.
      JournalError: the log is corrupt.
      OSError: the log cannot be written.
    """
    run_dir = Path(run_dir)
    log_path = run_dir / LOG_FILE
    journal: Journal | None = None
    session: Session | None = None
    status, detail = Stop.INTERRUPTED, "not started"
    replayed = truncated = 0
    track: list[float] = []  # this session's path distances after each following move [m]
    wall = {"selfid_s": 0.0, "follow_s": 0.0}  # this session's wall times per phase
    earlier = {"selfid_s": 0.0, "follow_s": 0.0}  # the log's earlier sessions'

    def on_event(event: dict[str, Any]) -> None:
        if event["phase"] == "follow":
            track.append(float(event["distance"]))
            assert journal is not None
            journal.append({"e": "track", "step": event["step"], "waypoint": event["waypoint"],
                            "distance": event["distance"]})
        if progress is not None:
            progress(event)

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
        if options.estimate is None:  # self-ID will move each actuator by up to m_a: its range must allow that
            check_room(env, m_a, joint_labels(robot, n))
        if options.path is not None:  # its waypoints, and none beyond the arm's reach (where the driver states it)
            options.path.offsets(axes)
            check_path_reach(options.path.positions(axes), reach_bound(robot))
        given_file = _read_given(options.estimate) if isinstance(options.estimate, (str, Path)) else None
        given = None if options.estimate is None else given_estimate(options.estimate, n, axes, read=given_file)
        if given is not None and given_file is not None:  # a flagged file is refused unless the caller accepts it
            try:
                trust_lines(given[1], given_file, accept_flagged=accept_flagged_estimate)
            except ValueError as err:
                raise ValueError(f"estimate: {err}") from None
        if given is not None and options.path is None:
            raise ValueError("estimate: following with a given estimate needs a path (path); without one there "
                             "is nothing to do")
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
            for rec in contents.records:
                if rec["e"] == "track":
                    track.append(float(rec["distance"]))
                elif rec["e"] == "times":
                    for key in earlier:
                        earlier[key] += float(rec.get(key) or 0.0)
            journal = Journal(log_path, good_bytes=contents.good_bytes)
        else:
            if log_path.exists():
                raise ResumeError(f"{log_path}: the run directory already holds a session log; resume it or "
                                  "choose another run directory")
            journal = Journal(log_path)
            journal.append(header)
            if given is not None:
                journal.append(_estimate_record(given, given_file))
        session = Session(robot, options, env, axes, m_a, journal, stop_requested, sleep, on_event)
        session.min_count = min_samples(options, m)
        session.state = init_state(n, m, method=options.method, v_tol=options.v_tol,
                                   max_samples=options.max_samples, dtype=dtype)
        # compile the step now, before any motion, so the first sample does not stall the loop (result discarded)
        jax.block_until_ready(sample_step(session.state, np.zeros(n), np.zeros(m), options.eps, options.eps_rel,
                                          min_count=session.min_count,
                                          method=options.method))
        if contents is not None:
            replayed = session.replay(contents)
            _check_path(log_path, session.offsets, options.path, axes)
            logged_given = session.given
            given = _check_estimate(log_path, session, given)
            if given is not None and options.path is None:
                raise ResumeError(f"{log_path}: cannot resume: the log follows with the estimate from {given[1]} "
                                  "and this session has no path; give the path")
            if given is not None and logged_given is None:
                journal.append(_estimate_record(given, given_file))
            elif logged_given is not None:  # the log's estimate: its file's trust as logged when it was given
                rec = next(r for r in contents.records if r["e"] == "estimate")
                given_file = EstimateFile(logged_given[0], [], rec.get("trust"), rec.get("converged_at"))
        session.given = given
        journal.append({"e": "session", "resume": resume, "replayed": replayed, "truncated": truncated,
                        "wall_time": time.time(), "lower": env.lower, "upper": env.upper, "max_step": env.max_step,
                        "box_low": env.box_low, "box_high": env.box_high, "stale_s": env.stale_s})
        session.last_advance_wall = time.monotonic()  # the watchdog's clock starts now, not before the replay
        kind = trace = None
        phase, t0 = "selfid_s", time.monotonic()
        try:
            if given is not None and options.path is not None:  # follow with it: no self-ID, no random move
                phase, t0 = "follow_s", time.monotonic()
                _follow_reference(session)
                session.follow(options.path, given[0])
            if int(session.state.converged_at) < 1:
                session.selfid()
            session.check_quality()
            if options.path is None:
                raise Stopped(Stop.CONVERGED, f"converged at sample {int(session.state.converged_at)}; "
                              "no path to follow, the robot stays where it is")
            wall[phase] += time.monotonic() - t0
            phase, t0 = "follow_s", time.monotonic()
            session.follow(options.path)
        except Stopped as stop:
            status, detail = stop.reason, stop.detail
        except RobotConnectionError as err:
            status, detail = Stop.CONNECTION, f"connection lost: {err}"
        except RobotError as err:
            status, detail = Stop.ROBOT_ERROR, f"the robot refused or faulted: {err}"
        except DriverFault as err:
            status, detail, kind = Stop.DRIVER_ERROR, f"the driver failed: {err}", err.kind
        except KeyboardInterrupt:
            status, detail = Stop.INTERRUPTED, "interrupted (KeyboardInterrupt)"
        except Exception as err:  # noqa: BLE001 - a bug of the runner's own: still a logged stop, no further command
            status, detail, kind = Stop.ERROR, f"internal error: {type(err).__name__}: {err}", type(err).__name__
            trace = traceback.format_exc()
        wall[phase] += time.monotonic() - t0
        extra = {k: v for k, v in (("kind", kind), ("traceback", trace)) if v is not None}
        journal.append({"e": "times", **wall})  # this session's wall time per phase [s], just before its stop
        journal.append({"e": "stop", "reason": status.value, "detail": detail, **extra})
        if progress is not None:
            progress({"phase": "stop", "status": status.value, "detail": detail})
    except BaseException as err:  # refused before any motion (or interrupted outside the loop): still closed
        _finish(robot, journal, err)
        raise
    closing = _finish(robot, journal)
    assert session is not None and session.state is not None
    state = jax.device_get(session.state)
    estimate = np.asarray(state.estimate) if session.given is None else session.given[0]
    figures = None
    if session.quality is not None:  # the converged samples: their figures and warnings, actuators by the driver's
        figures = trust(session.quality, estimate, sum(session.rejected.values()), session.k,
                        names=joint_labels(robot, session.n))
    if session.given is None:
        given_file = None
    path_total = 0 if session.offsets is None else int(session.offsets.shape[0])
    return OnlineResult(
        status=status, detail=detail, estimate=estimate, state=state,
        converged_at=int(state.converged_at), samples=session.samples, rejected=dict(session.rejected),
        moves=session.moves, follow_steps=session.follow_steps, follow_rejected=session.follow_rejected,
        waypoints=session.waypoint, waypoints_total=path_total, replayed=replayed, truncated=truncated,
        step_ms=np.asarray(session.step_ms, np.float64), quality=session.quality, axes=axes, log=log_path,
        track=np.asarray(track, np.float64), selfid_s=earlier["selfid_s"] + wall["selfid_s"],
        follow_s=earlier["follow_s"] + wall["follow_s"],
        estimate_source=None if session.given is None else session.given[1], reference=session.reference,
        trust=figures, given_trust=None if given_file is None else given_file.trust,
        given_converged_at=None if given_file is None else given_file.converged_at, close_error=closing)


def close_robot(robot: Robot) -> str | None:
    """``robot.close()``; None, or where it raised (a lost connection, a vendor's disconnect failing) one line saying
    so, raising nothing: a session's stop, or the error that ended it, stays the cause the user is told."""
    try:
        robot.close()
    except Exception as err:  # noqa: BLE001 - any driver's own: reported beside the cause, never in its place
        return f"closing the driver afterwards also failed: {type(err).__name__}: {' '.join(str(err).split())}"
    return None


def _finish(robot: Robot, journal: Journal | None, err: BaseException | None = None) -> str | None:
    """Close the robot (:func:`close_robot`), then the log; a close that failed is logged (a ``close`` record) and
    added to ``err``'s notes where an error is ending the call. Returns the close failure's line, or None."""
    note = close_robot(robot)
    if journal is not None:
        if note is not None:
            try:
                journal.append({"e": "close", "error": note})
            except (OSError, ValueError):  # a log that cannot be written (ValueError: closed) keeps what it has
                pass
        journal.close()
    if note is not None and err is not None:
        err.add_note(note)
    return note


def _estimate_record(given: tuple[np.ndarray, str], file: EstimateFile | None) -> dict[str, Any]:
    """The log's ``estimate`` record of a given estimate: it, its source and its file's trust record and convergence
    sample (None where the file has none), so a resumed session reports them without the file."""
    return {"e": "estimate", "source": given[1], "estimate": given[0],
            "trust": None if file is None else file.trust, "converged_at": None if file is None else file.converged_at}


def _follow_reference(session: Session) -> None:
    """Following with a given estimate from the start: the driver's model Jacobian where following starts (one read,
    no motion), logged as the ``reference`` record, so the estimate is reported against it; nothing where the
    driver has no model, or the log has a reference or started following already."""
    if session.reference is not None or session.anchor is not None or \
            not callable(getattr(session.robot, "jacobian", None)):
        return
    obs = session.fresh("follow")
    J = session.reference_jacobian(obs.q)
    if J is not None:
        session.reference = J
        session.journal.append({"e": "reference", "q": obs.q, "jacobian": J, "at": "follow"})
