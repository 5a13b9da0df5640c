"""Inverse-Jacobian path following: ``dtheta = Jinv(q) @ V`` towards each waypoint, under ``lax.scan``.

Each step the desired twist ``V`` points from the current pose to the current
waypoint (scaled by ``gain``, clipped to ``max_step`` metres and
``max_rot_step`` radians), the actuators move by ``Jinv(q) @ V`` (clipped to the
system's actuator limits), and the waypoint advances once it is within ``tol``
(and ``rot_tol`` for 6-D tasks). Metrics per rollout are returned in
:class:`FollowResult`; a rollout whose state turns non-finite or which strays
farther than ``diverge_dist`` from the path is frozen and flagged ``failed``,
so every metric stays finite.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from selfid_jax import geometry
from selfid_jax._checks import check_array, check_positive_int
from selfid_jax.linalg import pseudo_inverse
from selfid_jax.systems.system import System

JinvFn = Callable[[jax.Array], jax.Array]
"""``jinv_fn(q (n,)) -> (n, m)``: the inverse Jacobian the controller uses at ``q``."""


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


def fixed(J) -> JinvFn:
    """A constant inverse Jacobian ``J (n, m)`` (e.g. a self-ID estimate)."""
    return lambda q: J


class JacobianInverse(NamedTuple):
    """An inverse-Jacobian function built from the system's Jacobian: ``scale * pinv(J(q))``.

    Callable as a :data:`JinvFn`; :func:`follow` recognises it and computes the
    pose and the Jacobian in one kinematics pass (``System.pose_and_jacobian``).
    """

    system: System
    scale: jax.Array | float = 1.0  # () or (n, m), elementwise

    def __call__(self, q):
        return self.from_jacobian(self.system.jacobian(q))

    def from_jacobian(self, J):
        """``scale * pinv(J)`` for a Jacobian ``J (m, n)``."""
        return self.scale * pseudo_inverse(J)


def true_inverse(system: System) -> JinvFn:
    """The system's true inverse Jacobian at every step."""
    return JacobianInverse(system)


def scaled_true_inverse(system: System, m_eps) -> JinvFn:
    """``m_eps * true_inverse_jacobian(q)`` elementwise, ``m_eps (n, m)`` (the valid-region study, Sec. III-C)."""
    return JacobianInverse(system, m_eps)


def _segment_distance(p, a, b):
    """Distance from points ``p (d,)`` to segments ``a (S, d) -> b (S, d)``: ``(S,)``."""
    ab = b - a
    denom = jnp.sum(ab * ab, axis=-1)
    t = jnp.clip(jnp.sum((p[None, :] - a) * ab, axis=-1) / jnp.where(denom > 0, denom, 1.0), 0.0, 1.0)
    closest = a + t[:, None] * ab
    return jnp.sqrt(jnp.sum((p[None, :] - closest) ** 2, axis=-1))


def _clip_norm(v, limit):
    norm = jnp.sqrt(jnp.sum(v * v))
    return v * jnp.minimum(1.0, limit / jnp.where(norm > 0, norm, 1.0))


def follow(
    system: System,
    jinv_fn: JinvFn,
    path,
    q0,
    *,
    steps: int,
    max_step=0.005,
    tol=0.002,
    gain=1.0,
    max_rot_step=0.05,
    rot_tol=0.01,
    diverge_dist=None,
    return_trajectory: bool = False,
) -> FollowResult:
    """Follow waypoint offsets ``path (W, task_dim)`` from ``q0 (n,)`` with ``dtheta = jinv_fn(q) @ V``.

    ``path`` holds offsets from the start pose (see :mod:`selfid_jax.paths`):
    positions are added to the start position, rotation vectors ``r`` give the
    target orientation ``exp(r) R_start``. ``steps`` (the step budget) is
    static; ``max_step`` (m per step), ``tol`` (m), ``gain``, ``max_rot_step``,
    ``rot_tol`` (rad) and ``diverge_dist`` (m; default: twice the path's
    largest offset plus 10 ``tol``) may be traced, so they can be swept.
    """
    steps = check_positive_int("steps", steps)
    n, m = system.n_act, system.task_dim
    check_array("q0", q0, (n,))
    check_array("path", path, (None, m))
    dtype = jnp.result_type(float)
    q0 = jnp.asarray(q0, dtype)
    path = jnp.asarray(path, dtype)
    W = path.shape[0]
    pos_dim = min(m, 3)

    p0, R0 = system.pose(q0)
    targets = p0[:pos_dim][None, :] + path[:, :pos_dim]  # (W, pos_dim)
    vertices = jnp.concatenate([p0[None, :pos_dim], targets], axis=0)  # (W + 1, pos_dim)
    if m == 6:
        target_R = jnp.einsum("wij,jk->wik", geometry.so3_exp(path[:, 3:]), R0)
    if diverge_dist is None:
        diverge_dist = 2.0 * jnp.max(jnp.sqrt(jnp.sum(path[:, :pos_dim] ** 2, axis=-1))) + 10.0 * tol

    def errors(pose, w):
        """Position and rotation errors from ``pose = (p, R)`` towards waypoint ``w``."""
        p, R = pose
        wc = jnp.minimum(w, W - 1)
        e_p = targets[wc] - p[:pos_dim]
        if m == 6:
            return e_p, geometry.so3_log(target_R[wc] @ R.T)
        return e_p, jnp.zeros((0,), dtype)

    def close_enough(e_p, e_r):
        ok = jnp.sqrt(jnp.sum(e_p**2)) <= tol
        if m == 6:
            ok = ok & (jnp.sqrt(jnp.sum(e_r**2)) <= rot_tol)
        return ok

    def step(carry, _):
        q, w, failed, err_sum, err_max, used, wp_err = carry
        active = (w < W) & ~failed
        if isinstance(jinv_fn, JacobianInverse):
            pose, jac = system.pose_and_jacobian(q)
            J = jinv_fn.from_jacobian(jac)
        else:
            pose = system.pose(q)
            J = jinv_fn(q)
        p = pose[0]
        e_p, e_r = errors(pose, w)
        dist = jnp.min(_segment_distance(p[:pos_dim], vertices[:-1], vertices[1:]))
        reached = active & close_enough(e_p, e_r)
        wp_err = jnp.where(reached, wp_err.at[jnp.minimum(w, W - 1)].set(jnp.sqrt(jnp.sum(e_p**2))), wp_err)
        w = w + reached.astype(w.dtype)
        active = active & (w < W)
        e_p, e_r = errors(pose, w)
        V = _clip_norm(gain * e_p, max_step)
        if m == 6:
            V = jnp.concatenate([V, _clip_norm(gain * e_r, max_rot_step)])
        q_new = system.apply(q, J @ V)
        finite = jnp.all(jnp.isfinite(q_new)) & jnp.all(jnp.isfinite(J))
        diverged = dist > diverge_dist
        failed = failed | (active & (~finite | diverged))
        move = active & ~failed
        q = jnp.where(move, q_new, q)
        err_sum = err_sum + jnp.where(active, dist, 0.0)
        err_max = jnp.maximum(err_max, jnp.where(active, dist, 0.0))
        used = used + active.astype(used.dtype)
        return (q, w, failed, err_sum, err_max, used, wp_err), (p if return_trajectory else None)

    init = (
        q0,
        jnp.zeros((), jnp.int32),
        jnp.zeros((), bool),
        jnp.zeros((), dtype),
        jnp.zeros((), dtype),
        jnp.zeros((), jnp.int32),
        jnp.full((W,), -1.0, dtype),
    )
    (q, w, failed, err_sum, err_max, used, wp_err), traj = jax.lax.scan(step, init, None, length=steps)
    pose_end = system.pose(q)
    p_end = pose_end[0]
    # the last step may have reached a waypoint after its move: check once more
    e_p, e_r = errors(pose_end, w)
    last = (w < W) & ~failed & close_enough(e_p, e_r)
    wp_err = jnp.where(last, wp_err.at[jnp.minimum(w, W - 1)].set(jnp.sqrt(jnp.sum(e_p**2))), wp_err)
    w = w + last.astype(w.dtype)
    end_dist = jnp.sqrt(jnp.sum((targets - p_end[None, :pos_dim]) ** 2, axis=-1))
    wp_err = jnp.where(wp_err >= 0, wp_err, end_dist)
    positions = None
    if return_trajectory:
        positions = jnp.concatenate([traj, p_end[None, :]], axis=0)
    return FollowResult(
        completion=w.astype(dtype) / W,
        mean_error=err_sum / jnp.maximum(used, 1).astype(dtype),
        max_error=err_max,
        waypoint_error=jnp.mean(wp_err),
        steps_used=used,
        failed=failed,
        final_q=q,
        positions=positions,
    )


def feasible_starts(system: System, path, key, k: int, *, oversample: int = 4, steps: int, max_step=0.005,
                    tol=0.002, gain=1.0):
    """``k`` start configurations ``(k, n)`` from which the true inverse Jacobian completes ``path``.

    Draws ``k * oversample`` configurations with ``system.sample_configs``
    (away from singularities), follows ``path`` from each with the true inverse
    Jacobian (controller arguments as for :func:`follow`) and keeps the first
    ``k`` that complete it without failing, so a study measures robustness to
    inverse-Jacobian error rather than paths that leave the workspace or hit a
    joint limit. Sampling and rollouts are one compiled call. Eager; raises
    ``ValueError`` if fewer than ``k`` qualify.
    """
    k = check_positive_int("k", k)
    total = k * check_positive_int("oversample", oversample)
    cand, ok = _feasible_candidates(system, jnp.asarray(path), key, total, check_positive_int("steps", steps),
                                    max_step, tol, gain)
    idx = jnp.flatnonzero(ok)
    if idx.shape[0] < k:
        raise ValueError(
            f"only {int(idx.shape[0])} of {total} sampled configurations of {system.name!r} complete "
            f"the path with the true inverse Jacobian; need {k} (raise oversample, shrink the path or the box)"
        )
    return cand[idx[:k]]


@functools.partial(jax.jit, static_argnames=("total", "steps"))
def _feasible_candidates(system, path, key, total, steps, max_step, tol, gain):
    cand, valid = system.sample_configs(key, total, return_valid=True)
    res = jax.vmap(lambda q: follow(system, true_inverse(system), path, q, steps=steps, max_step=max_step, tol=tol,
                                    gain=gain))(cand)
    return cand, valid & (res.completion >= 1.0) & ~res.failed
