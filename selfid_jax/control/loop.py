"""Path following under ``lax.scan``: one loop (:func:`follow_law`) whose per-step actuator law is pluggable.

Each step the desired twist ``V`` points from the current pose to the current
waypoint (scaled by ``gain``, clipped to ``max_step`` metres and
``max_rot_step`` radians), a :class:`StepLaw` turns it into an actuator step
(``Jinv(q) @ V`` for :func:`follow`, the E-KM's constrained QP for
:func:`selfid_jax.control.qp.follow`), the actuators move by it (clipped to the
system's actuator limits), and the waypoint advances once it is within ``tol``
(and ``rot_tol`` for 6-D tasks). Metrics per rollout are returned in
:class:`FollowResult`; a rollout whose state turns non-finite or which strays
farther than ``diverge_dist`` from the path is frozen and flagged ``failed``,
so every metric stays finite. Completion and failure have one definition here
for every law (:func:`completed`, :func:`feasible_indices`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
import numpy as np

from selfid_jax.control import realism as realism_lib
from selfid_jax.math import geometry
from selfid_jax.math.checks import check_array, check_positive_int, check_scalar, is_traced
from selfid_jax.math.linalg import pseudo_inverse
from selfid_jax.systems.system import System

JinvFn = Callable[[jax.Array], jax.Array]
"""``jinv_fn(q (n,)) -> (n, m)``: the inverse Jacobian the controller uses at ``q``."""


class JinvSource(Protocol):
    """Anything with ``pose_and_jinv(system, q (n,)) -> ((p (3,), R (3, 3)), Jinv (n, m))``: the controller's one
    call per step (:class:`Fixed`, :class:`JacobianInverse`, :class:`FromFunction` or a user's own)."""

    def pose_and_jinv(self, system: System, q) -> tuple[tuple[jax.Array, jax.Array], jax.Array]: ...


class ControllerParams(NamedTuple):
    """Traced controller settings of :func:`follow` (sweepable: any field may carry a batch axis under ``vmap``).

    The defaults are the shipped configs' UR5e protocol
    (:class:`selfid_jax.experiments.common.schema.ControllerConfig` reads its defaults from here).
    """

    max_step: ArrayLike = 0.0025  # () largest POM position step per control step [m]
    tol: ArrayLike = 0.0005  # () waypoint reached within this distance [m]
    gain: ArrayLike = 1.0  # () fraction of the error commanded per step (before clipping)
    max_rot_step: ArrayLike = 0.05  # () largest rotation step per control step [rad] (6-D tasks)
    rot_tol: ArrayLike = 0.01  # () waypoint orientation reached within this angle [rad] (6-D tasks)
    # () failed beyond this distance to the path [m]; None: 2 max|path| + 10 tol
    diverge_dist: ArrayLike | None = None


DEFAULT_STEPS = 435
"""Default step budget of :func:`follow`: 3x the full-speed step count of the shipped star protocols."""


class FollowResult(NamedTuple):
    """Metrics of one rollout (leading batch axes if vmapped)."""

    completion: jax.Array  # () fraction of waypoints reached, in [0, 1]
    mean_error: jax.Array  # () mean distance (m) of the POM position to the path polyline over the steps used
    max_error: jax.Array  # () largest such distance (m)
    waypoint_error: jax.Array  # () mean over waypoints of the position error (m) when reached, or at the end if not
    steps_used: jax.Array  # () int32: steps until the last waypoint was reached (or the budget)
    failed: jax.Array  # () bool: non-finite state or divergence (> diverge_dist from the path)
    final_q: jax.Array  # (n,) actuator positions at the end
    positions: jax.Array | None  # (steps + 1, 3) POM positions if return_trajectory, else None
    orientations: jax.Array | None = None  # (steps + 1, 3, 3) POM orientations if return_trajectory, else None
    targets: jax.Array | None = None  # (steps + 1,) int32 waypoint pursued at each of those poses (W when done)
    # with realism: () int32 tracker readings that dropped out over the active steps; None without
    dropouts: jax.Array | None = None
    # with realism and return_trajectory: (steps + 1, 3) tracker positions the controller used at each of those
    # poses [m]; None otherwise
    readings: jax.Array | None = None
    # the true POM pose (p (3,) [m], R (3, 3)) at the start and at final_q, as the loop sensed them (no second
    # evaluation of the pose map: on a closed-chain hand each is a Newton solve); None where a caller built the
    # result without them
    start_pose: tuple[jax.Array, jax.Array] | None = None
    final_pose: tuple[jax.Array, jax.Array] | None = None


# ------------------------------------------------------------------ inverse-Jacobian sources
# Each has ``pose_and_jinv(system, q) -> ((p (3,), R (3, 3)), Jinv (n, m))``, the one call the controller makes per
# step.

class Fixed(NamedTuple):
    """A constant inverse Jacobian ``J (n, m)`` (e.g. a self-ID estimate)."""

    J: jax.Array

    def __call__(self, q):
        return self.J

    def pose_and_jinv(self, system: System, q):
        return system.pose(q), self.J


class JacobianInverse(NamedTuple):
    """``scale * pinv(J(q))`` from the system's Jacobian, pose and Jacobian from one kinematics pass."""

    system: System
    scale: jax.Array | float = 1.0  # () or (n, m), elementwise

    def __call__(self, q):
        return self.scale * pseudo_inverse(self.system.jacobian(q))

    def pose_and_jinv(self, system: System, q):
        pose, J = system.pose_and_jacobian(q)
        return pose, self.scale * pseudo_inverse(J)


class FromFunction(NamedTuple):
    """Any ``jinv_fn(q) -> (n, m)``; the pose is read separately."""

    fn: JinvFn

    def __call__(self, q):
        return self.fn(q)

    def pose_and_jinv(self, system: System, q):
        return system.pose(q), self.fn(q)


class EstimateOrTrue(NamedTuple):
    """The constant ``estimate (n, m)``, or the true ``pinv(J(q))`` where ``use_true ()`` (a traced bool).

    One program for both: ``vmap`` over ``use_true`` follows with an estimate and with the truth side by side,
    so the pose map is compiled once for the two (on a closed-chain hand each place it is evaluated is a Newton
    solve). Pose and Jacobian come from one kinematics pass either way.
    """

    estimate: jax.Array
    use_true: jax.Array

    def pose_and_jinv(self, system: System, q):
        pose, J = system.pose_and_jacobian(q)
        return pose, jnp.where(self.use_true, pseudo_inverse(J), self.estimate)


def estimate_or_true(estimate, use_true) -> EstimateOrTrue:
    """``estimate (n, m)`` where ``use_true ()`` is False, the system's true inverse Jacobian where it is True."""
    return EstimateOrTrue(jnp.asarray(estimate), jnp.asarray(use_true, bool))


def fixed(J) -> Fixed:
    """A constant inverse Jacobian ``J (n, m)`` (e.g. a self-ID estimate)."""
    return Fixed(J)


def true_inverse(system: System) -> JacobianInverse:
    """The system's true inverse Jacobian at every step."""
    return JacobianInverse(system)


def scaled_true_inverse(system: System, m_eps) -> JacobianInverse:
    """``m_eps * true_inverse_jacobian(q)`` elementwise, ``m_eps (n, m)`` (the valid-region study, Sec. III-C)."""
    return JacobianInverse(system, m_eps)


# ------------------------------------------------------------------ task space

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



def _segment_distance(p, a, b):
    """Distance from points ``p (d,)`` to segments ``a (S, d) -> b (S, d)``: ``(S,)``."""
    ab = b - a
    denom = jnp.sum(ab * ab, axis=-1)
    t = jnp.clip(jnp.sum((p[None, :] - a) * ab, axis=-1) / jnp.where(denom > 0, denom, 1.0), 0.0, 1.0)
    closest = a + t[:, None] * ab
    return jnp.sqrt(jnp.sum((p[None, :] - closest) ** 2, axis=-1))


def waypoint_poses(path, pose0, axes: tuple[int, ...]):
    """Goal poses of waypoint offsets ``path (W, len(axes))`` taken from ``pose0 = (p0 (3,), R0 (3, 3))``.

    The offsets are the task components ``axes`` (indices into ``[dp, rotation
    vector]``) of each waypoint; the others are 0 (held). Returns ``(p (W, 3),
    R (W, 3, 3))``: ``p0 + dp`` and ``exp(r) R0`` [m, rotation matrices].
    """
    full = jnp.zeros((path.shape[0], 6), path.dtype).at[:, jnp.asarray(axes)].set(path)
    p0, R0 = pose0
    return p0[None, :] + full[:, :3], jnp.einsum("wij,jk->wik", geometry.so3_exp(full[:, 3:]), R0)


class _Task(NamedTuple):
    """Waypoints in task space, taken from the start pose ``pose0`` (:func:`waypoint_poses`): the task's position
    components and, where it has them, target orientations. Each goal is formed where it is read (one waypoint per
    step), so the start pose can be the first pose the loop senses."""

    path: jax.Array  # (W, task_dim) waypoint offsets along the task components `axes`
    pose0: tuple[jax.Array, jax.Array]  # (p0 (3,), R0 (3, 3)) the start pose [m, rotation matrix]
    axes: tuple[int, ...]  # static: the task components (indices into [dp, rotation vector])
    pos_axes: tuple[int, ...]  # static: the task's position components (0-2)
    rot_axes: tuple[int, ...]  # static: the task's rotation-vector components (0-2)

    @staticmethod
    def make(path, pose0, system: System) -> _Task:
        return _Task(path, pose0, system.axes, system.position_axes, system.rotation_axes)

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
        return (safe_norm(e_p) <= ctrl.tol) & (safe_norm(e_r) <= ctrl.rot_tol)

    def twist(self, e_p, e_r, ctrl: ControllerParams):
        """Commanded pose change ``V (m,)``: the gained error, position and rotation parts clipped separately."""
        return jnp.concatenate([clip_norm(ctrl.gain * e_p, ctrl.max_step),
                                clip_norm(ctrl.gain * e_r, ctrl.max_rot_step)])

    def path_distance(self, p):
        """Distance of position ``p`` to the path polyline along the task's position axes [m] (0 without any)."""
        if not self.pos_axes:
            return jnp.zeros((), p.dtype)
        v = self.vertices
        return jnp.min(_segment_distance(self.positions(p), v[:-1], v[1:]))


# ------------------------------------------------------------------ step laws

class StepLaw(NamedTuple):
    """A per-step actuator law of :func:`follow_law`: three pure functions over the law's own state (optax-style).

    ``init(q0 (n,)) -> state``: the law's state at the start (a pytree of
    fixed-shape arrays; ``()`` for a memoryless law).

    ``sense(state, q (n,)) -> (pose, aux)``: the POM pose ``(p (3,), R (3, 3))``
    at ``q`` and whatever the law computed with it (e.g. the Jacobian from the
    same kinematics pass), handed back to ``step``.

    ``step(state, q, pose, aux, V (m,)) -> (dq (n,), state, ok ())``: the
    actuator step for the commanded twist ``V`` (before ``system.apply``
    clips it), the state after a move, and a bool that is False where the
    law's own quantities are unusable (a non-finite Jacobian), which fails
    the rollout. The loop keeps the new state only on steps that move.
    """

    init: Callable[[jax.Array], Any]
    sense: Callable[[Any, jax.Array], tuple[tuple[jax.Array, jax.Array], Any]]
    step: Callable[[Any, jax.Array, tuple[jax.Array, jax.Array], Any, jax.Array], tuple[jax.Array, Any, jax.Array]]


def inverse_jacobian_law(system: System, jinv) -> StepLaw:
    """``dq = Jinv(q) @ V``, ``Jinv (n, m)`` from :func:`fixed`, :func:`true_inverse`, :func:`scaled_true_inverse`,
    any object with ``pose_and_jinv(system, q)`` or a plain ``jinv_fn(q) -> (n, m)``; stateless.

    A non-finite ``Jinv`` fails the rollout; one of the wrong shape raises
    ``ValueError`` while tracing.
    """
    source = jinv if hasattr(jinv, "pose_and_jinv") else FromFunction(jinv)
    n, m = system.n_act, system.task_dim

    def sense(state, q):
        pose, J = source.pose_and_jinv(system, q)
        if J.shape != (n, m):  # static: raised while tracing, before any compute
            raise ValueError(f"jinv: the inverse Jacobian has shape {J.shape}, expected ({n}, {m}) = (n_act, task_dim)")
        return pose, J

    def step(state, q, pose, J, V):
        return J @ V, state, jnp.all(jnp.isfinite(J))

    return StepLaw(init=lambda q0: (), sense=sense, step=step)


# ------------------------------------------------------------------ the loop

class _Carry(NamedTuple):
    q: jax.Array  # (n,) actuator positions
    law: Any  # the step law's state (pytree; () for a stateless law)
    waypoint: jax.Array  # () int32 index of the current waypoint (W when done)
    failed: jax.Array  # () bool
    err_sum: jax.Array  # () sum of path distances over active steps [m]
    err_max: jax.Array  # () largest path distance over active steps [m]
    used: jax.Array  # () int32 active steps
    wp_err: jax.Array  # (W,) position error when each waypoint was reached [m]; -1 before
    tracker: realism_lib.Tracker | None = None  # with realism: the tracker's history and last good reading
    dropouts: jax.Array | None = None  # with realism: () int32 readings that dropped out over the active steps
    plant: Any = None  # with a plant: its state (e.g. an mjx.Data); q is its measured actuator positions
    anchor: Any = None  # (p (3,), R (3, 3)) the start pose, which the path's offsets are taken from
    pose: Any = None  # (p (3,), R (3, 3)) the true pose sensed last


def _advance(task: _Task, carry: _Carry, pose, ctrl: ControllerParams, true_pose=None):
    """Mark the current waypoint reached if ``pose`` (what the controller sees) is within tolerance, recording the
    position error of ``true_pose`` (default ``pose``) then; returns ``(carry, active)``."""
    W = task.path.shape[0]
    active = (carry.waypoint < W) & ~carry.failed
    e_p, e_r = task.error(pose, carry.waypoint)
    reached = active & task.reached(e_p, e_r, ctrl)
    wc = jnp.minimum(carry.waypoint, W - 1)
    if true_pose is None:
        e_true = e_p
    else:  # the seen error itself where the reading is the pose (no latency, no noise): the ideal loop's number
        same = jnp.all(pose[0] == true_pose[0])
        e_true = jnp.where(same, e_p, task.error(true_pose, carry.waypoint)[0])
    carry = carry._replace(
        wp_err=jnp.where(reached, carry.wp_err.at[wc].set(safe_norm(e_true)), carry.wp_err),
        waypoint=carry.waypoint + reached.astype(carry.waypoint.dtype),
    )
    return carry, active & (carry.waypoint < W)


def _check_inputs(system: System, path, q0, controller, steps):
    """Eager checks of the followers: shapes, concrete non-finite inputs, positive controller settings."""
    steps = check_positive_int("steps", steps)
    check_array("q0", q0, (system.n_act,))
    if np.ndim(path) == 2 and np.shape(path)[1] != system.task_dim:
        raise ValueError(f"path: expected shape ('*', {system.task_dim}) for the {system.task_dim}-D task of "
                         f"{system.name!r}, got {tuple(np.shape(path))}: a path has one column per task axis; "
                         f"build it with paths.star(size, dim={system.task_dim})")
    check_array("path", path, (None, system.task_dim))
    if not isinstance(controller, ControllerParams):
        raise TypeError(f"controller must be a ControllerParams, got {type(controller).__name__}")
    for name, value in (("q0", q0), ("path", path)):
        if not is_traced(value) and not np.all(np.isfinite(np.asarray(value, np.float64))):
            raise ValueError(f"{name} holds non-finite values: {np.asarray(value)}")
    for name in ("max_step", "tol", "max_rot_step", "rot_tol", "gain"):
        check_scalar(f"controller.{name}", getattr(controller, name), gt=0.0)
    return steps


def completed(completion, failed):
    """Whether rollouts reached every waypoint without failing: ``completion >= 1`` and not ``failed`` (any shape;
    jax or numpy arrays). The one definition of a completed rollout."""
    return (completion >= 1.0) & ~failed.astype(bool)


def follow_law(
    system: System,
    law: StepLaw,
    path: ArrayLike,
    q0: ArrayLike,
    controller: ControllerParams = ControllerParams(),
    *,
    steps: int = DEFAULT_STEPS,
    return_trajectory: bool = False,
    realism: realism_lib.Realism | None = None,
    key: jax.Array | None = None,
    max_latency: int | None = None,
    plant: realism_lib.Plant | None = None,
) -> tuple[FollowResult, Any]:
    """Follow waypoint offsets ``path (W, task_dim)`` from ``q0 (n,)``, each actuator step from ``law``.

    The one follow loop behind :func:`follow` (``law =
    inverse_jacobian_law(system, jinv)``) and
    :func:`selfid_jax.control.qp.follow` (``qp.constrained_law``). Each step:
    ``pose, aux = law.sense(state, q)``; the waypoint advances within ``tol``
    (and ``rot_tol``); the twist ``V`` towards it is the gained error, position
    part clipped to ``max_step`` [m], rotation part to ``max_rot_step`` [rad];
    ``dq, state', ok = law.step(state, q, pose, aux, V)``; ``q' =
    system.apply(q, dq)``. A rollout whose ``q'``, pose or law (``ok``) turns
    non-finite or whose distance to the path exceeds ``diverge_dist``
    (default ``2 max|path| + 10 tol``) is frozen and flagged ``failed``;
    ``q`` and the law's state change only on steps that move.

    With ``realism`` (a :class:`~selfid_jax.control.realism.Realism`, every
    field traceable) the loop is the real one of
    :mod:`selfid_jax.control.realism`: the controller sees the tracker's
    reading instead of the pose (:func:`~selfid_jax.control.realism.read`: the
    pose ``latency`` steps ago, noisy, the last good reading on a dropout,
    counted in ``dropouts``) for the waypoint test, the twist and
    ``law.step``; it commands the target ``u = system.apply(q, dq)`` from the
    measured ``q`` (the law's Jacobian is taken there too); and the actuators
    reach ``q' = servo(q, u)`` (lag, deadband). The metrics, the divergence
    test and the trajectory are of the true pose; the waypoint error is the
    true one when the controller declared the waypoint reached; the path is
    anchored at the true start pose. ``key`` (required) draws the noise and
    dropouts, one split per step; ``max_latency`` (static) sizes the
    tracker's history (default: ``realism.latency``, which must then be
    concrete; a traced latency is clipped to it). A law that reads poses
    itself (the E-KM's online mode) sees them without these effects.
    ``realism=None`` is the ideal loop (what :data:`~selfid_jax.control.realism.IDEAL`
    reproduces bit for bit).

    ``plant`` (a :class:`~selfid_jax.control.realism.Plant`; default the
    kinematic :func:`~selfid_jax.control.realism.servo_plant`) is what the
    actuators do with each target: with
    :func:`~selfid_jax.control.realism.dynamic_plant` the arm's own physics
    (servo gains, inertia, gravity) steps between control steps and ``q`` is
    its measured joint positions. A plant implies the real loop (with
    :data:`~selfid_jax.control.realism.IDEAL` if ``realism`` is None, then
    ``key`` defaults to ``PRNGKey(0)``, which draws nothing).

    Arguments, checks and metrics as :func:`follow`. Returns
    ``(FollowResult, final law state)``.
    """
    steps = _check_inputs(system, path, q0, controller, steps)
    dtype = jnp.result_type(float)
    q0 = jnp.asarray(q0, dtype)
    path = jnp.asarray(path, dtype)
    W = path.shape[0]
    ctrl = controller
    if ctrl.diverge_dist is None:
        reach = jnp.max(jnp.sqrt(jnp.sum(path[:, : len(system.position_axes)] ** 2, axis=-1)))
        ctrl = ctrl._replace(diverge_dist=2.0 * reach + 10.0 * ctrl.tol)
    realism_lib.check_plant(plant, system.n_act)
    if plant is not None and realism is None:
        realism = realism_lib.IDEAL
        key = jax.random.PRNGKey(0) if key is None else key
    real = realism is not None
    r = realism_lib.IDEAL  # the values the realistic loop uses (only when real)
    history = 0  # the tracker's history length - 1 (only when real)
    keys = None
    if realism is not None:
        r = realism_lib.check_realism(realism)
        history = realism_lib.latency_bound(r, max_latency)
        realism_lib.check_max_latency(r, history)
        if key is None:
            raise ValueError("follow: a key is required with realism (it draws the tracker noise and dropouts)")
        keys = jax.random.split(key, steps + 1)

    def see(carry: _Carry, pose, k):
        """What the controller sees of the true ``pose`` this step, and the carry with the tracker advanced."""
        if carry.tracker is None:
            return pose, carry, None
        tr = realism_lib.push(carry.tracker, pose)
        seen, dropped, tr = realism_lib.read(tr, k, r)
        return seen, carry._replace(tracker=tr), dropped

    def where(c, a, b):
        return jax.tree.map(lambda x, y: jnp.where(c, x, y), a, b)

    # The pose map is evaluated at one place in the loop (on a closed-chain hand each place is a Newton solve
    # compiled again): iteration 0 senses the start pose, which anchors the path, and the last iteration
    # (i = steps) only senses the end pose, for the controller's last reading and the end metrics.
    def step(carry: _Carry, xs):
        i, k = xs
        pose, aux = law.sense(carry.law, carry.q)
        first, last = i == 0, i == steps
        carry = carry._replace(
            anchor=where(first, pose, carry.anchor), pose=pose,
            # an unsolvable start pose: failed from the start, finite metrics
            failed=carry.failed | (first & ~jnp.all(jnp.isfinite(pose[0]))),
        )
        if real:
            carry = carry._replace(tracker=where(first, realism_lib.tracker(pose, history), carry.tracker))
        task = _Task.make(path, carry.anchor, system)
        dist = task.path_distance(pose[0])
        seen, carry, dropped = see(carry, pose, k)
        carry, active = _advance(task, carry, seen, ctrl, pose if real else None)
        e_p, e_r = task.error(seen, carry.waypoint)
        V = task.twist(e_p, e_r, ctrl)
        dq, learned, ok = law.step(carry.law, carry.q, seen, aux, V)
        q_new = system.apply(carry.q, dq)
        x_new = None
        if plant is not None:
            x_new = plant.step(carry.plant, q_new, r)
            q_new = plant.q(x_new).astype(dtype)
        elif real:
            q_new = realism_lib.servo(carry.q, q_new, r)
        # a pose map returns NaN where its solve failed (closed-chain hands): that fails the rollout too
        finite = jnp.all(jnp.isfinite(q_new)) & ok & jnp.all(jnp.isfinite(pose[0]))
        active = active & ~last
        failed = carry.failed | (active & (~finite | (dist > ctrl.diverge_dist)))
        move = active & ~failed
        counted = jnp.where(active & jnp.isfinite(dist), dist, 0.0)
        carry = carry._replace(
            q=jnp.where(move, q_new, carry.q),
            law=where(move, learned, carry.law),
            failed=failed,
            err_sum=carry.err_sum + counted,
            err_max=jnp.maximum(carry.err_max, counted),
            used=carry.used + active.astype(carry.used.dtype),
        )
        if real:
            carry = carry._replace(dropouts=carry.dropouts + (active & dropped).astype(jnp.int32))
        if plant is not None:
            carry = carry._replace(plant=where(move, x_new, carry.plant))
        out = None
        if return_trajectory:
            out = (pose, carry.waypoint, seen[0]) if real else (pose, carry.waypoint)
        return carry, out

    law0 = law.init(q0)
    pose_shape = jax.eval_shape(law.sense, law0, q0)[0]
    pose_init = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), pose_shape)  # replaced by iteration 0's
    init = _Carry(
        q=q0,
        law=law0,
        waypoint=jnp.zeros((), jnp.int32),
        # traced NaN input: failed from the start, finite metrics
        failed=~(jnp.all(jnp.isfinite(q0)) & jnp.all(jnp.isfinite(path))),
        err_sum=jnp.zeros((), dtype),
        err_max=jnp.zeros((), dtype),
        used=jnp.zeros((), jnp.int32),
        wp_err=jnp.full((W,), -1.0, dtype),
        tracker=realism_lib.tracker(pose_init, history) if real else None,
        dropouts=jnp.zeros((), jnp.int32) if real else None,
        plant=None if plant is None else plant.init(q0),
        anchor=pose_init,
        pose=pose_init,
    )
    carry, traj = jax.lax.scan(step, init, (jnp.arange(steps + 1), keys), length=steps + 1)
    task = _Task.make(path, carry.anchor, system)
    end_dist = jnp.sqrt(jnp.sum((task.targets - task.positions(carry.pose[0])[None]) ** 2, axis=-1))
    wp_err = jnp.where(carry.wp_err >= 0, carry.wp_err, jnp.where(jnp.isfinite(end_dist), end_dist, 0.0))
    result = FollowResult(
        completion=carry.waypoint.astype(dtype) / W,
        mean_error=carry.err_sum / jnp.maximum(carry.used, 1).astype(dtype),
        max_error=carry.err_max,
        waypoint_error=jnp.mean(wp_err),
        steps_used=carry.used,
        failed=carry.failed,
        final_q=carry.q,
        positions=traj[0][0] if return_trajectory else None,
        orientations=traj[0][1] if return_trajectory else None,
        targets=traj[1] if return_trajectory else None,
        dropouts=carry.dropouts,
        readings=traj[2] if return_trajectory and real else None,
        start_pose=carry.anchor,
        final_pose=carry.pose,
    )
    return result, carry.law


def follow(
    system: System,
    jinv: JinvSource | JinvFn,
    path: ArrayLike,
    q0: ArrayLike,
    controller: ControllerParams = ControllerParams(),
    *,
    steps: int = DEFAULT_STEPS,
    return_trajectory: bool = False,
    realism: realism_lib.Realism | None = None,
    key: jax.Array | None = None,
    max_latency: int | None = None,
    plant: realism_lib.Plant | None = None,
) -> FollowResult:
    """Follow waypoint offsets ``path (W, task_dim)`` from ``q0 (n,)`` with ``dtheta = Jinv @ V``.

    The path's columns are the system's task components (:attr:`System.axes`:
    position then rotation-vector offsets); components outside the task are
    not controlled.

    Each step the desired twist ``V`` points from the current pose to the
    current waypoint, times ``controller.gain``, position part clipped to
    ``max_step`` [m], rotation part to ``max_rot_step`` [rad]; the actuators
    move by ``Jinv @ V`` (clipped by ``system.apply``), and the waypoint
    advances within ``tol`` (and ``rot_tol`` for tasks with rotation).
    :func:`follow_law` with :func:`inverse_jacobian_law`.

    Args:
      system: the :class:`~selfid_jax.systems.System`.
      jinv: where ``Jinv (n, m)`` comes from: :func:`fixed`,
        :func:`true_inverse`, :func:`scaled_true_inverse`,
        :func:`estimate_or_true`, any object with
        ``pose_and_jinv(system, q)``, or a plain ``jinv_fn(q) -> (n, m)``.
      path: waypoint offsets from the start pose (:mod:`selfid_jax.control.paths`):
        positions [m] added to the start position, rotation vectors ``r``
        [rad] giving ``exp(r) R_start``.
      q0: ``(n,)`` start actuator positions.
      controller: :class:`ControllerParams`; every field may be traced.
      steps: static step budget.
      return_trajectory: also return the ``(steps + 1, 3)`` POM positions,
        ``(steps + 1, 3, 3)`` orientations (at the start of each step, then at
        the end) and the ``(steps + 1,)`` index of the waypoint pursued then
        (with ``realism`` also the ``(steps + 1, 3)`` tracker positions the
        controller used: ``readings``).
      realism, key, max_latency: the real loop's non-idealities
        (:mod:`selfid_jax.control.realism`; see :func:`follow_law`): with a
        :class:`~selfid_jax.control.realism.Realism` the controller sees
        delayed, noisy tracker readings with dropouts (counted in
        ``dropouts``) and the actuators lag and have a deadband; ``key``
        draws the noise; ``max_latency`` (static) bounds a traced latency.
        None (default): the ideal loop.
      plant: the actuators' model (:func:`follow_law`): None, the kinematic
        servo; :func:`~selfid_jax.control.realism.dynamic_plant` for an arm
        whose own physics steps between control steps.

    A rollout whose state or pose turns non-finite (a closed-chain hand's pose
    map returns NaN where its solve fails or leaves the equilibrium branch) or
    strays farther than ``diverge_dist`` from the path is frozen and flagged
    ``failed``, so every
    metric stays finite (distances that cannot be computed, as from a traced
    NaN ``q0`` or waypoint, count as 0: read them only where ``failed`` is
    False). Concrete non-finite ``q0``/``path``, non-positive controller
    settings and an inverse Jacobian of the wrong shape raise ``ValueError``.
    """
    return follow_law(system, inverse_jacobian_law(system, jinv), path, q0, controller, steps=steps,
                      return_trajectory=return_trajectory, realism=realism, key=key, max_latency=max_latency,
                      plant=plant)[0]


def feasible_indices(system: System, valid, completion, failed, k: int) -> np.ndarray:
    """Indices ``(k,)`` of the first ``k`` candidate starts that are ``valid`` and :func:`completed` the path.

    ``valid``, ``completion``, ``failed``: ``(total,)`` per candidate (jax or
    numpy). Eager; raises ``ValueError`` if fewer than ``k`` qualify. The
    selection and message of :func:`feasible_starts` and of the valid-region
    study's start configurations.
    """
    ok = np.asarray(valid) & completed(np.asarray(completion), np.asarray(failed))
    idx = np.flatnonzero(ok)
    if idx.shape[0] < k:
        raise ValueError(
            f"only {int(idx.shape[0])} of {ok.shape[0]} sampled configurations of {system.name!r} complete "
            f"the path with the true inverse Jacobian; need {k} (raise oversample: the feasible_starts argument, "
            "or the config key of the same name; or shrink the path or the sampling box)"
        )
    return idx[:k]


def feasible_starts(system: System, path, key, k: int, controller: ControllerParams = ControllerParams(), *,
                    steps: int = DEFAULT_STEPS, oversample: int = 4):
    """``k`` start configurations ``(k, n)`` from which the true inverse Jacobian completes ``path``.

    Draws ``k * oversample`` configurations with ``system.sample_configs``
    (away from singularities), follows ``path`` from each with the true inverse
    Jacobian (``controller`` and ``steps`` as for :func:`follow`) and keeps the
    first ``k`` that complete it without failing (:func:`feasible_indices`), so a
    study measures robustness to inverse-Jacobian error rather than paths that
    leave the workspace or hit a joint limit. Sampling and rollouts are one
    compiled call. Eager; raises ``ValueError`` if fewer than ``k`` qualify.
    """
    k = check_positive_int("k", k)
    total = k * check_positive_int("oversample", oversample)
    cand, valid, completion, failed = _feasible_candidates(system, jnp.asarray(path), key, total,
                                                           check_positive_int("steps", steps), controller)
    return cand[feasible_indices(system, valid, completion, failed, k)]


@functools.partial(jax.jit, static_argnames=("total", "steps"))
def _feasible_candidates(system, path, key, total, steps, controller):
    cand, valid = system.sample_configs(key, total, return_valid=True)
    res = jax.vmap(lambda q: follow(system, true_inverse(system), path, q, controller, steps=steps))(cand)
    return cand, valid, res.completion, res.failed
