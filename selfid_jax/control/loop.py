"""Path following under ``lax.scan``: one loop (:func:`follow_law`) whose per-step actuator law is pluggable.

Each step is :func:`selfid_jax.control.law.command`, the control step the live
robot runs too: the waypoint advances once the pose is within ``tol`` (and
``rot_tol`` for tasks with rotation), the desired twist ``V`` points from the
pose to the current waypoint (scaled by ``gain``, clipped to ``max_step``
metres and ``max_rot_step`` radians), a :class:`~selfid_jax.control.law.StepLaw`
turns it into an actuator step (``Jinv(q) @ V`` for :func:`follow`, the
E-KM's constrained QP for :func:`selfid_jax.control.qp.follow`), capped per
actuator (``max_dq``), and the actuators move by it (clipped to the system's
actuator limits). Metrics per rollout are returned in :class:`FollowResult`;
a rollout whose state turns non-finite or which strays farther than
``diverge_dist`` from the path is frozen and flagged ``failed``, so every
metric stays finite. Completion and failure have one definition here for
every law (:func:`completed`, :func:`feasible_indices`).

The inverse-Jacobian sources are in :mod:`selfid_jax.control.sources`, the
task geometry (waypoints, twist, path distance) in
:mod:`selfid_jax.control.task`, the law and the control step in
:mod:`selfid_jax.control.law`.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from selfid_jax.control import realism as realism_lib
from selfid_jax.control.law import StepLaw, command, inverse_jacobian_law
from selfid_jax.control.sources import JinvFn, JinvSource, true_inverse
from selfid_jax.control.task import DEFAULT_STEPS, ControllerParams, Task, safe_norm
from selfid_jax.math.checks import check_array, check_positive_int, check_scalar, is_traced
from selfid_jax.systems.system import System

__all__ = ["DEFAULT_STEPS", "ControllerParams", "FollowResult", "completed", "feasible_indices", "feasible_starts",
           "follow", "follow_law"]


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
    # (W,) position error (m) of each waypoint when it was reached, or at the end if not (its mean is
    # waypoint_error); None where a caller built the result without them
    waypoint_errors: jax.Array | None = None


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
    cap = controller.max_dq
    if cap is not None:
        if np.shape(cap) not in ((), (system.n_act,)):
            raise ValueError(f"controller.max_dq: expected one number or {system.n_act} (one per actuator), got shape "
                             f"{np.shape(cap)}")
        if not is_traced(cap) and not np.all(np.asarray(cap, np.float64) > 0):
            raise ValueError(f"controller.max_dq: every value must be > 0, got {np.asarray(cap).tolist()}")
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
    ctrl = controller._replace(diverge_dist=Task.make(path, None, system).default_diverge_dist(controller))
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
        task = Task.make(path, carry.anchor, system)
        dist = task.path_distance(pose[0])
        seen, carry, dropped = see(carry, pose, k)
        # a reading that dropped out is no new information: no waypoint test and no new command this step (the
        # target is the measured q), as the live runner waits for a fresh pose; time passes, the step counts
        fresh = ~dropped if real else True
        active = (carry.waypoint < W) & ~carry.failed
        cmd = command(law, task, ctrl, carry.law, carry.waypoint, carry.q, seen, aux, active & fresh)
        e_true = cmd.error
        if real:  # the seen error itself where the reading is the pose (no latency, no noise): the ideal loop's number
            e_true = jnp.where(jnp.all(seen[0] == pose[0]), cmd.error, task.error(pose, carry.waypoint)[0])
        wc = jnp.minimum(carry.waypoint, W - 1)
        carry = carry._replace(
            wp_err=jnp.where(cmd.reached, carry.wp_err.at[wc].set(safe_norm(e_true)), carry.wp_err),
            waypoint=cmd.waypoint,
        )
        active = active & (carry.waypoint < W)
        dq, learned, ok = cmd.dq, cmd.law, cmd.ok
        if real:
            dq, learned = jnp.where(fresh, dq, 0.0), where(fresh, learned, carry.law)
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
    task = Task.make(path, carry.anchor, system)
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
        waypoint_errors=wp_err,
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
