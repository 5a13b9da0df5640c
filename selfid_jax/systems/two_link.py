"""Planar two-link arm: two hinges about z, POM at the tip, task = xy position."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from selfid_jax.systems.system import System, from_pose_fn

__all__ = ["two_link", "two_link_pose"]


def two_link_pose(params, q):
    """Tip pose of a planar 2-link arm.

    ``p = (l1 c1 + l2 c12, l1 s1 + l2 s12, 0)``, ``R = Rz(q1 + q2)``.

    Args:
      params: ``(2,)`` link lengths ``(l1, l2)`` (m).
      q: ``(2,)`` joint angles (rad); ``q2`` is the elbow angle relative to link 1.

    Returns:
      ``(p (3,), R (3, 3))``.
    """
    l1, l2 = params[0], params[1]
    q1, q12 = q[0], q[0] + q[1]
    c1, s1, c12, s12 = jnp.cos(q1), jnp.sin(q1), jnp.cos(q12), jnp.sin(q12)
    z = jnp.zeros_like(c1)
    o = jnp.ones_like(c1)
    p = jnp.stack([l1 * c1 + l2 * c12, l1 * s1 + l2 * s12, z])
    R = jnp.stack([jnp.stack([c12, -s12, z]), jnp.stack([s12, c12, z]), jnp.stack([z, z, o])])
    return p, R


def two_link(
    *,
    l1: float = 1.0,
    l2: float = 1.0,
    task_dim: int = 2,
    m_a=0.05,
    dq_max: float = 0.1,
    q_low=(-np.pi, -np.pi),
    q_high=(np.pi, np.pi),
    sample_low=(-2.5, 0.3),
    sample_high=(2.5, 2.6),
    min_sigma: float = 0.1,
) -> System:
    """Planar two-link arm (plain-JAX forward kinematics).

    Link lengths are traced ``params`` (a sweep can vmap over them). The
    Jacobian's determinant is ``l1 l2 sin(q2)``: singular with the elbow
    straight (``q2 = 0``) or folded (``q2 = pi``); the default sampling box
    keeps one elbow branch, ``q2`` in ``[0.3, 2.6]`` rad.

    Args:
      l1, l2: link lengths (m).
      task_dim: 2 (xy position, default), 3 (position, z row is zero, so
        the Jacobian is rank 2) or 6.
      m_a: safe self-ID magnitude (rad), scalar or ``(2,)``.
      dq_max: per-step actuator limit (rad).
      q_low, q_high: joint limits (rad).
      sample_low, sample_high: sampling box (rad).
      min_sigma: smallest singular value accepted by ``sample_configs`` (m/rad).

    Returns:
      A :class:`System` with ``n_act = 2``.
    """
    if not (np.isfinite(l1) and np.isfinite(l2) and l1 > 0 and l2 > 0):
        raise ValueError(f"link lengths must be positive and finite, got l1={l1}, l2={l2}")
    params = jnp.asarray([l1, l2], dtype=jnp.result_type(float))
    return from_pose_fn(
        two_link_pose,
        2,
        task_dim=task_dim,
        q_low=q_low,
        q_high=q_high,
        dq_max=dq_max,
        m_a=m_a,
        params=params,
        sample_low=sample_low,
        sample_high=sample_high,
        min_sigma=min_sigma,
        name="two_link",
    )
