"""Task-space geometry of path following: the controller's settings, the waypoints and the commanded twist.

One definition for the simulated loop (:func:`selfid_jax.control.loop.follow_law`) and the live robot
(:mod:`selfid_jax.robot.session`): where a waypoint is (:func:`waypoint_poses`), when it counts as reached, the
twist towards it with its position and rotation parts clipped separately (:meth:`Task.twist`), the per-actuator
step cap (:func:`cap_actuator_step`) and the distance to the path that the divergence test reads
(:meth:`Task.path_distance`). Pure ``jax.numpy``: it runs traced inside ``lax.scan`` and eagerly on the host.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from selfid_jax.math import geometry

__all__ = ["DEFAULT_STEPS", "ControllerParams", "Task", "cap_actuator_step", "clip_norm", "safe_norm",
           "waypoint_poses"]


class ControllerParams(NamedTuple):
    """Traced controller settings of the follow loop (sweepable: any field may carry a batch axis under ``vmap``).

    The defaults are the shipped configs' UR5e protocol
    (:class:`selfid_jax.experiments.common.schema.ControllerConfig` reads its defaults from here); the live
    runner builds one from its path options and safety envelope
    (:meth:`selfid_jax.robot.options.FollowOptions.controller`).
    """

    max_step: ArrayLike = 0.0025  # () largest POM position step per control step [m]
    tol: ArrayLike = 0.0005  # () waypoint reached within this distance [m]
    gain: ArrayLike = 1.0  # () fraction of the error commanded per step (before clipping)
    max_rot_step: ArrayLike = 0.05  # () largest rotation step per control step [rad] (6-D tasks)
    rot_tol: ArrayLike = 0.01  # () waypoint orientation reached within this angle [rad] (6-D tasks)
    # () failed (simulation) or stopped (robot) beyond this distance to the path [m]; None: 2 max|path| + 10 tol
    diverge_dist: ArrayLike | None = None
    # (n,) or () largest |dq_i| per control step [actuator units]: a longer step is scaled down as a whole (its
    # direction kept); None: no cap beyond the system's own dq_max clip (what every shipped sweep uses)
    max_dq: ArrayLike | None = None


DEFAULT_STEPS = 435
"""Default step budget of :func:`~selfid_jax.control.loop.follow`: 3x the full-speed step count of the shipped star
protocols."""


def safe_norm(v):
    """Euclidean norm of ``v (d,)``, ``()``, whose reverse-mode derivative is 0 (not NaN) at ``v = 0``.

    The square root's derivative is infinite at 0; the double ``where`` keeps
    it off the traced path there (``0 * inf`` would be NaN). Forward value:
    ``sqrt(sum(v * v))`` exactly, NaN included.
    """
    sq = jnp.sum(v * v)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), sq)  # sq: 0 at 0, and NaN stays NaN


def clip_norm(v, limit):
    """``v (d,)`` scaled down to norm ``limit ()`` if longer, NaN-safe: finite reverse derivative at ``v = 0``.

    Forward value: ``v * min(1, limit / |v|)`` (``v`` itself at 0), the same
    number as the single-``where`` form; its derivative at ``v = 0`` is
    ``min(1, limit)`` times the identity instead of NaN.
    """
    sq = jnp.sum(v * v)
    pos = sq > 0
    # the outer where also keeps XLA from rewriting limit / sqrt as limit * rsqrt (not correctly rounded: the
    # rollouts would move in the last bit)
    norm = jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 1.0)
    return v * jnp.minimum(1.0, limit / norm)


def cap_actuator_step(dq, max_dq):
    """``dq (n,)`` scaled down as a whole so that every ``|dq_i| <= max_dq_i`` (``max_dq`` ``()`` or ``(n,)``,
    actuator units); ``dq`` unchanged where it already fits, and for ``max_dq=None``.

    Scaling keeps the step's direction (the twist it was computed for); an
    elementwise clip would turn it. The live runner's envelope ``max_step``
    enters the law here, and so does a simulation given the same cap.
    """
    if max_dq is None:
        return dq
    return dq / jnp.maximum(1.0, jnp.max(jnp.abs(dq) / max_dq))


def waypoint_poses(path, pose0, axes: tuple[int, ...]):
    """Goal poses of waypoint offsets ``path (W, len(axes))`` taken from ``pose0 = (p0 (3,), R0 (3, 3))``.

    The offsets are the task components ``axes`` (indices into ``[dp, rotation
    vector]``) of each waypoint; the others are 0 (held). Returns ``(p (W, 3),
    R (W, 3, 3))``: ``p0 + dp`` and ``exp(r) R0`` [m, rotation matrices].
    """
    full = jnp.zeros((path.shape[0], 6), path.dtype).at[:, jnp.asarray(axes)].set(path)
    p0, R0 = pose0
    return p0[None, :] + full[:, :3], jnp.einsum("wij,jk->wik", geometry.so3_exp(full[:, 3:]), R0)


class Task(NamedTuple):
    """Waypoints in task space, taken from the start pose ``pose0`` (:func:`waypoint_poses`): the task's position
    components and, where it has them, target orientations. Each goal is formed where it is read (one waypoint per
    step), so the start pose can be the first pose the loop senses.

    Build it with :meth:`make` from a :class:`~selfid_jax.systems.System` or with :meth:`from_axes` from the task
    components alone (a robot has no model).
    """

    path: jax.Array  # (W, task_dim) waypoint offsets along the task components `axes`
    pose0: tuple[jax.Array, jax.Array]  # (p0 (3,), R0 (3, 3)) the start pose [m, rotation matrix]
    axes: tuple[int, ...]  # static: the task components (indices into [dp, rotation vector])
    pos_axes: tuple[int, ...]  # static: the task's position components (0-2)
    rot_axes: tuple[int, ...]  # static: the task's rotation-vector components (0-2)

    @staticmethod
    def make(path, pose0, system) -> Task:
        """The task of ``system`` (its ``axes``, ``position_axes`` and ``rotation_axes``)."""
        return Task(path, pose0, system.axes, system.position_axes, system.rotation_axes)

    @staticmethod
    def from_axes(path, pose0, axes) -> Task:
        """The task along ``axes`` (indices into ``(x, y, z, rx, ry, rz)``)."""
        axes = tuple(int(a) for a in axes)
        return Task(path, pose0, axes, tuple(a for a in axes if a < 3), tuple(a - 3 for a in axes if a >= 3))

    @property
    def targets(self):
        """``(W, P)`` waypoint positions along the task's P position axes [m]."""
        return self.positions(waypoint_poses(self.path, self.pose0, self.axes)[0])

    @property
    def vertices(self):
        """``(W + 1, P)`` path polyline, start pose first [m]."""
        return jnp.concatenate([self.positions(self.pose0[0])[None, :], self.targets], axis=0)

    def error(self, pose, w):
        """``(e_p (P,), e_r (R,))`` from ``pose`` to waypoint ``w`` (clamped to the last), task components only."""
        p, R = pose
        wc = jnp.minimum(w, self.path.shape[0] - 1)
        p_goal, R_goal = waypoint_poses(self.path[wc][None], self.pose0, self.axes)
        e_p = self.positions(p_goal[0]) - self.positions(p)
        if not self.rot_axes:
            return e_p, e_p[:0]
        return e_p, geometry.so3_log(R_goal[0] @ R.T)[jnp.asarray(self.rot_axes)]

    def positions(self, p):
        """The task's position components of ``p (..., 3)``: ``(..., P)``."""
        return p[..., list(self.pos_axes)]

    def reached(self, e_p, e_r, ctrl: ControllerParams):
        """Whether an error ``(e_p, e_r)`` is within ``ctrl.tol`` [m] and ``ctrl.rot_tol`` [rad]: ``()`` bool."""
        return (safe_norm(e_p) <= ctrl.tol) & (safe_norm(e_r) <= ctrl.rot_tol)

    def twist(self, e_p, e_r, ctrl: ControllerParams):
        """Commanded pose change ``V (m,)``: the gained error, position and rotation parts clipped separately."""
        return jnp.concatenate([clip_norm(ctrl.gain * e_p, ctrl.max_step),
                                clip_norm(ctrl.gain * e_r, ctrl.max_rot_step)])

    def path_distance(self, p):
        """Distance of position ``p (3,)`` to the path polyline along the task's position axes [m] (0 without any):
        what the divergence test compares with ``diverge_dist``."""
        if not self.pos_axes:
            return jnp.zeros((), p.dtype)
        return jnp.min(geometry.closest_on_polyline(self.positions(p), self.vertices)[1])

    def default_diverge_dist(self, ctrl: ControllerParams):
        """``ctrl.diverge_dist``, or where it is None ``2 max|path| + 10 tol`` over the position offsets [m]."""
        if ctrl.diverge_dist is not None:
            return ctrl.diverge_dist
        reach = jnp.max(jnp.sqrt(jnp.sum(self.path[:, : len(self.pos_axes)] ** 2, axis=-1)))
        return 2.0 * reach + 10.0 * ctrl.tol
