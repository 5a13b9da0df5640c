"""The options of a live session: plain values with their defaults, read by ``run_online`` and ``selfid-jax online``.

:class:`OnlineOptions` (self-ID, safety envelope) and :class:`FollowOptions`
(the path and the follow law's settings) are the one place each online
default is written: the ``selfid-jax online`` config sections
(:mod:`selfid_jax.commands.online`) read their defaults from here, and so does
the envelope (:func:`selfid_jax.robot.safety.envelope`). Importing this
module loads neither numpy nor JAX (the command line parses a config before
either).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:
    import numpy as np

    from selfid_jax.control.task import ControllerParams

__all__ = ["DIVERGE_DIST", "ONLINE_METHODS", "STALE_S", "FollowOptions", "OnlineOptions"]

ONLINE_METHODS = ("closed_form", "optax")
"""The Eq. 14 refinements the live runner's jitted per-sample step supports."""
STALE_S = 1.0
"""The watchdog's default in seconds (a tracker pose older than this stops the session)."""
DIVERGE_DIST = 0.05
"""The default distance in metres from the path (its position axes) that stops following."""


class FollowOptions(NamedTuple):
    """The path followed with the converged estimate (a star, :func:`selfid_jax.control.paths.star`) and the
    controller settings of the follow law (:meth:`controller`)."""

    kind: str = "star"
    size: float = 0.02  # m, outer radius of the star (paths.star size); its top point is where following starts
    plane: str = "xy"  # plane of the star: "xy", "xz" or "yz" (both axes must be task axes)
    gain: float = 0.5  # proportional gain on the task error, per move (dimensionless, in (0, 1])
    tol: float = 0.002  # m: a waypoint is reached when the position error's norm is at most this
    max_task_step: float = 0.005  # m: cap on the position part of the commanded twist per move
    steps: int = 500  # most moves while following (Stop.MAX_STEPS)
    rot_tol: float = 0.01  # rad: ... and the rotation error's (tasks with rotation axes; held at the start pose)
    max_rot_step: float = 0.05  # rad: cap on the rotation part of the commanded twist per move

    def controller(self, env) -> ControllerParams:
        """The follow law's settings on a robot with envelope ``env``: the simulated loop with this
        :class:`~selfid_jax.control.task.ControllerParams` commands what the robot is commanded."""
        from selfid_jax.control.task import ControllerParams

        return ControllerParams(max_step=self.max_task_step, tol=self.tol, gain=self.gain,
                                max_rot_step=self.max_rot_step, rot_tol=self.rot_tol,
                                diverge_dist=env.diverge_dist, max_dq=env.max_step)

    def positions(self) -> np.ndarray:
        """``(W, 3)`` waypoint position offsets [m] (the full star in its plane)."""
        import numpy as np

        from selfid_jax.control import paths

        return np.asarray(paths.star(size=self.size, plane=self.plane, dim=3), np.float64)

    def offsets(self, axes: Sequence[int]) -> np.ndarray:
        """Waypoint offsets ``(W, m)`` of the path in task coordinates relative to where following starts.

        A star in ``plane``, rotation part zero (the orientation is held),
        restricted to the task axes; both axes of the plane must be task axes.
        Raises ValueError naming the option that is out of range.
        """
        import numpy as np

        from selfid_jax.control import paths

        if self.kind != "star":
            raise ValueError(f"path.kind: only 'star' is supported, got {self.kind!r}")
        if self.plane not in paths.PLANES:
            raise ValueError(f"path.plane: expected one of {tuple(paths.PLANES)}, got {self.plane!r}")
        missing = [a for a in paths.PLANES[self.plane] if a not in axes]
        if missing:
            raise ValueError(f"path.plane: {self.plane!r} needs task axis {'xyz'[missing[0]]}, not in the task")
        for name in ("size", "gain", "tol", "max_task_step", "rot_tol", "max_rot_step"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"path.{name}: must be a finite number > 0, got {v!r}")
        if self.gain > 1:
            raise ValueError(f"path.gain: must be in (0, 1] (a larger gain overshoots), got {self.gain!r}")
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"path.steps: must be an integer >= 1, got {self.steps!r}")
        if not self.tol < self.size / 2:
            raise ValueError(f"path.tol ({self.tol:g}) must be below half of path.size ({self.size:g}): waypoints "
                             "would count as reached without moving")
        full = np.asarray(paths.star(size=self.size, plane=self.plane, dim=6), np.float64)
        return full[:, list(axes)]


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
    # follow_min_ratio of the commanded, after follow_min_moves moves, stops the session (actuator)
    follow_min_ratio: float = 0.5
    follow_min_moves: int = 5
    # held out while following: the position change pinv(estimate) predicts for each move's measured dq against
    # the tracked one; recent-weighted error above follow_max_residual times the predicted motion stops (estimate)
    follow_max_residual: float = 0.75
    # at convergence: the leave-one-out error of the tracked motion predicted from the actuators' (forward least
    # squares over the samples) above this stops before following (estimate)
    max_heldout_error: float = 0.5
    path: FollowOptions | None = None  # follow this path after convergence; None: stop at convergence


