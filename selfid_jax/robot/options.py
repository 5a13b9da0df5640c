"""The options of a live session: plain values with their defaults, read by ``run_online`` and ``selfid-jax online``.

:class:`OnlineOptions` (self-ID, safety envelope) and :class:`FollowOptions`
(the path and the follow law's settings) are the one place each online
default is written: the ``selfid-jax online`` config sections
(:mod:`selfid_jax.sessions.online_config`) read their defaults from here, and so does
the envelope (:func:`selfid_jax.robot.safety.envelope`). Importing this
module loads neither numpy nor JAX (the command line parses a config before
either).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:
    import numpy as np

    from selfid_jax.control.task import ControllerParams

__all__ = ["AXIS_NAMES", "DIVERGE_DIST", "MIN_SAMPLES_PER_AXIS", "ONLINE_METHODS",
           "PATH_KINDS", "STALE_S", "FollowOptions", "OnlineOptions"]

ONLINE_METHODS = ("closed_form", "optax")
"""The Eq. 14 refinements the live runner's jitted per-sample step supports."""
STALE_S = 1.0
"""The watchdog's default in seconds (a tracker pose older than this stops the session)."""
DIVERGE_DIST = 0.05
"""The default distance in metres from the path (its position axes) that stops following."""


MIN_SAMPLES_PER_AXIS = 5
"""The default least number of accepted samples before Sec. IV-D may declare convergence, per task axis.

The relative change that Sec. IV-D tests falls faster where the arm has few
redundant joints (the joints' motion outside the task is what each sample's
update fits as noise): on franky-sim's FR3 (7 joints) the 3-D task met it at
19-45 samples, the 6-D task at 10-22, where its error ||J Ĵ - I||_F against
MuJoCo's Jacobian was up to 0.31; from 5 samples per axis (30) it was at most
0.12 (twelve seeds, MuJoCo's kinematics with 0.1 mm noise). 5 per axis leaves
the 3-D task's convergence as it was (15 < 19)."""

AXIS_NAMES = ("x", "y", "z", "rx", "ry", "rz")
"""Names of the task axes, as a path file's header and an estimate file's ``task_axes`` spell them."""
PATH_KINDS = ("star", "waypoints", "csv")
"""What ``FollowOptions.kind`` takes: the shipped star, a list of waypoints, a CSV file of waypoints."""


class FollowOptions(NamedTuple):
    """The path followed with the converged estimate and the controller settings of the follow law
    (:meth:`controller`).

    The path (:meth:`offsets`) is one of ``kind``: ``"star"``, the shipped
    star (:func:`selfid_jax.control.paths.star`, ``size`` and ``plane``);
    ``"waypoints"``, the rows of ``waypoints``; ``"csv"``, the rows of the
    CSV file ``file``, whose header names the task axes (``x,y,z``; any
    order). A waypoint is an offset from the pose where following starts in
    task units, one value per task axis: metres for x, y, z and radians for
    rx, ry, rz (a rotation vector, applied to the start orientation).
    """

    kind: str = "star"  # "star", "waypoints" or "csv"
    size: float = 0.02  # m, outer radius of the star (paths.star size); its top point is where following starts
    plane: str = "xy"  # plane of the star: "xy", "xz" or "yz" (both axes must be task axes)
    gain: float = 0.5  # proportional gain on the task error, per move (dimensionless, in (0, 1])
    tol: float = 0.002  # m: a waypoint is reached when the position error's norm is at most this
    max_task_step: float = 0.005  # m: cap on the position part of the commanded twist per move
    steps: int = 500  # most moves while following (Stop.MAX_STEPS)
    rot_tol: float = 0.01  # rad: ... and the rotation error's (tasks with rotation axes; held at the start pose)
    max_rot_step: float = 0.05  # rad: cap on the rotation part of the commanded twist per move
    waypoints: Sequence[Sequence[float]] | None = None  # kind "waypoints": (W, m) offsets, m and rad per task axis
    file: str | None = None  # kind "csv": a CSV file, header the task axes, one waypoint offset per row

    def controller(self, env) -> ControllerParams:
        """The follow law's settings on a robot with envelope ``env``: the simulated loop with this
        :class:`~selfid_jax.control.task.ControllerParams` commands what the robot is commanded."""
        from selfid_jax.control.task import ControllerParams

        return ControllerParams(max_step=self.max_task_step, tol=self.tol, gain=self.gain,
                                max_rot_step=self.max_rot_step, rot_tol=self.rot_tol,
                                diverge_dist=env.diverge_dist, max_dq=env.max_step)

    def positions(self, axes: Sequence[int] = (0, 1, 2)) -> np.ndarray:
        """``(W, 3)`` waypoint position offsets [m] of the path on task ``axes`` (zero on the axes it lacks)."""
        import numpy as np

        planned = self.offsets(axes)
        out = np.zeros((planned.shape[0], 3))
        for j, a in enumerate(axes):
            if a < 3:
                out[:, a] = planned[:, j]
        return out

    def offsets(self, axes: Sequence[int]) -> np.ndarray:
        """Waypoint offsets ``(W, m)`` of the path in task coordinates relative to where following starts.

        ``kind`` star: a star in ``plane``, rotation part zero (the orientation
        is held), restricted to the task axes; both axes of the plane must be
        task axes. ``kind`` waypoints / csv: the rows of ``waypoints`` / of the
        CSV ``file`` (columns in the task's order). Raises ValueError naming
        the option that is out of range (``path.waypoints``, ``path.file``: the
        wrong number of values for the task, a value that is not finite, no
        waypoint, a missing file, a header that does not name the task axes).
        """
        import numpy as np

        from selfid_jax.control import paths

        axes = tuple(int(a) for a in axes)
        if self.kind not in PATH_KINDS:
            raise ValueError(f"path.kind: expected one of {PATH_KINDS}, got {self.kind!r}")
        for name, kind in (("waypoints", "waypoints"), ("file", "csv")):
            if getattr(self, name) is not None and self.kind != kind:
                raise ValueError(f"path.{name}: only used with path.kind {kind!r} (path.kind is {self.kind!r})")
        for name in ("size", "gain", "tol", "max_task_step", "rot_tol", "max_rot_step"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"path.{name}: must be a finite number > 0, got {v!r}")
        if self.gain > 1:
            raise ValueError(f"path.gain: must be in (0, 1] (a larger gain overshoots), got {self.gain!r}")
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"path.steps: must be an integer >= 1, got {self.steps!r}")
        if self.kind == "waypoints":
            return _waypoint_rows("path.waypoints", self.waypoints, axes)
        if self.kind == "csv":
            return _csv_rows(self.file, axes)
        if self.plane not in paths.PLANES:
            raise ValueError(f"path.plane: expected one of {tuple(paths.PLANES)}, got {self.plane!r}")
        missing = [a for a in paths.PLANES[self.plane] if a not in axes]
        if missing:
            raise ValueError(f"path.plane: {self.plane!r} needs task axis {'xyz'[missing[0]]}, not in the task")
        if not self.tol < self.size / 2:
            raise ValueError(f"path.tol ({self.tol:g}) must be below half of path.size ({self.size:g}): waypoints "
                             "would count as reached without moving")
        full = np.asarray(paths.star(size=self.size, plane=self.plane, dim=6), np.float64)
        return full[:, list(axes)]


def _units(axes: Sequence[int]) -> str:
    return ", ".join(f"{AXIS_NAMES[a]} [{'m' if a < 3 else 'rad'}]" for a in axes)


def _waypoint_rows(key: str, rows, axes: tuple[int, ...], where: str = "") -> np.ndarray:
    """``rows`` as a ``(W, m)`` float64 array of waypoint offsets, refused (ValueError naming ``key``) unless each
    row has one finite value per task axis and there is at least one row."""
    import numpy as np

    m = len(axes)
    if rows is None:
        raise ValueError(f"{key}: path.kind {'csv' if key == 'path.file' else 'waypoints'!r} needs it: one row per "
                         f"waypoint, one offset per task axis ({_units(axes)})")
    if isinstance(rows, (str, bytes)) or not isinstance(rows, (Sequence, np.ndarray)):
        raise ValueError(f"{key}: expected a list of rows (one per waypoint), got {type(rows).__name__}")
    if len(rows) < 1:
        raise ValueError(f"{key}: {where}no waypoint; give at least 1 (one row per waypoint)")
    out = np.zeros((len(rows), m))
    for i, row in enumerate(rows):
        try:
            vals = [float(v) for v in row]
        except (TypeError, ValueError):
            raise ValueError(f"{key}: {where}waypoint {i + 1} is not a row of numbers: {row!r}") from None
        if len(vals) != m:
            raise ValueError(f"{key}: {where}waypoint {i + 1} has {len(vals)} values; the task has {m} axes "
                             f"({_units(axes)}), one value each")
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"{key}: {where}waypoint {i + 1} has a value that is not finite: {vals}")
        out[i] = vals
    return out


def _csv_rows(file: str | None, axes: tuple[int, ...]) -> np.ndarray:
    """The waypoint offsets of a CSV file (header: the task axes in any order), as ``(W, m)`` in the task's order."""
    from pathlib import Path

    import numpy as np

    key = "path.file"
    if file is None:
        raise ValueError(f"{key}: path.kind 'csv' needs a CSV file: a header naming the task axes "
                         f"({','.join(AXIS_NAMES[a] for a in axes)}), then one waypoint offset per row "
                         f"({_units(axes)})")
    path = Path(file)
    if not path.is_file():
        raise ValueError(f"{key}: {path}: no such file")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{key}: {path}: cannot be read: {err}") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    want = [AXIS_NAMES[a] for a in axes]
    header = [h.strip().lower() for h in lines[0].split(",")] if lines else []
    if sorted(header) != sorted(want) or len(set(header)) != len(header):
        raise ValueError(f"{key}: {path}: the header {','.join(header) or '(none)'} does not name the task axes "
                         f"{','.join(want)} (one column each, any order; units: {_units(axes)})")
    rows = [[v.strip() for v in ln.split(",")] for ln in lines[1:]]
    data = _waypoint_rows(key, rows, axes, where=f"{path}: ")
    return np.ascontiguousarray(data[:, [header.index(name) for name in want]])


class OnlineOptions(NamedTuple):
    """Options of one online session (plain values; :func:`run_online` checks them before any motion).

    The defaults here are the ones ``selfid-jax online`` uses too (its config
    sections read them from this class).
    """

    task: str | Sequence = "x,y,z"  # task axes out of x,y,z,rx,ry,rz (selfid_jax.robot.log.parse_task)
    m_a: float | Sequence[float] = 0.03  # self-ID magnitude (actuator units), scalar or (n,)
    eps: float = 0.0  # Sec. IV-D absolute threshold on ||J_t - J_{t-1}||_F (inverse-Jacobian units)
    eps_rel: float = 0.05  # relative threshold, times ||J_t||_F
    max_samples: int = 200  # most random moves (accepted + rejected samples) before Stop.MAX_SAMPLES
    # Sec. IV-D counts only from this many accepted samples on; None: MIN_SAMPLES_PER_AXIS per task axis
    min_samples: int | None = None
    seed: int = 0  # draw k uses numpy's default_rng([seed, k])
    # self-ID keeps each actuator within wander * m_a of where self-ID started (a draw that would take it farther
    # is reflected); None: an unbounded random walk. The estimate averages the Jacobian over the poses self-ID
    # visits: a walk drifts about m_a sqrt(k) in k moves, and on franky-sim's FR3 a 6-D task's error against the
    # start pose's Jacobian fell from 0.17-0.62 (unbounded) to 0.07-0.23 (wander 1), the 3-D task's from 0.09-0.20
    # to 0.01-0.03 (MuJoCo's own kinematics, six seeds each)
    wander: float | None = 1.0
    settle_s: float = 0.2  # s waited after each move before reading (motion time + tracker latency)
    poll_s: float = 0.01  # s between reads while waiting for a fresh tracker pose (no motion)
    method: str = "closed_form"  # Eq. 14 refinement: "closed_form" or "optax"
    v_tol: float = 1e-9  # |V_j| below this does not enter the magnitude mean (Eq. 11)
    lower: Sequence[float] | None = None  # (n,) user actuator limits, intersected with the driver's
    upper: Sequence[float] | None = None
    max_step: float | Sequence[float] | None = None  # user cap on |target - q| (actuator units); None: driver's
    box_low: Sequence[float] | None = None  # (3,) m, task-space box on the tracked position; None: unbounded
    box_high: Sequence[float] | None = None
    stale_s: float = STALE_S  # s, watchdog
    diverge_dist: float = DIVERGE_DIST  # m, divergence stop while following (distance to the path's positions)
    # motion versus sight: a tracked pose that moved less than seen_min [m] and seen_min_rad [rad] while the
    # actuators moved frozen_motion [actuator units; None: 3 max(m_a)] in all, or (following) while the estimate
    # predicts frozen_dist [m] of motion, stops the session (tracker_frozen)
    seen_min: float = 1e-5
    seen_min_rad: float = 1e-4
    frozen_motion: float | None = None
    frozen_dist: float = 0.005
    # command following: an actuator whose measured motion along its commands (recent moves weigh most) is below
    # follow_min_ratio of the commanded, and short of it by more than half its m_a, after follow_min_moves moves,
    # stops the session (actuator)
    follow_min_ratio: float = 0.5
    follow_min_moves: int = 5
    # held out while following: the position change pinv(estimate) predicts for each move's measured dq against
    # the tracked one; recent-weighted error above follow_max_residual times the predicted motion stops (estimate)
    follow_max_residual: float = 0.75
    # at convergence: the leave-one-out error of the tracked motion predicted from the actuators' (forward least
    # squares over the samples) above this stops before following (estimate)
    max_heldout_error: float = 0.5
    path: FollowOptions | None = None  # follow this path after convergence; None: stop at convergence
    # follow with this estimate instead of self-identifying (no random move at all): an .npz of `selfid-jax fit` or
    # an earlier `selfid-jax online` (keys inverse_jacobian (n, m) and task_axes), or an (n, m) array; needs a path
    estimate: str | Any | None = None


