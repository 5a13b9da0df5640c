"""SO(3) helpers and the pose difference used as the self-ID task vector.

The SO(3) maps are ``jaxlie.SO3``'s (a unit quaternion ``(w, x, y, z)``
inside; Taylor branches near the identity and near pi with the "double-where"
trick, so values and gradients stay finite); this module keeps the
matrix-in, matrix-out contract the rest of the package uses. Every function
accepts leading batch axes (``...``) without ``vmap``. Integer inputs are cast
to the default float dtype; jaxlie supports float32 and float64.

Units: rotation vectors and angles in radians, positions in the caller's length
unit (metres for the shipped systems).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie

__all__ = ["hat", "so3_exp", "so3_log", "rotation_to_quaternion", "quaternion_to_rotation", "pose_difference",
           "noisy_pose", "closest_on_polyline"]


def _as_float(x):
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


def hat(w):
    """Skew-symmetric matrix ``[w]x`` with ``[w]x v = w x v``.

    Args:
      w: ``(..., 3)`` vector.

    Returns:
      ``(..., 3, 3)`` skew-symmetric matrix.
    """
    w = jnp.asarray(w)
    z = jnp.zeros_like(w[..., 0])
    x, y, zz = w[..., 0], w[..., 1], w[..., 2]
    return jnp.stack(
        [
            jnp.stack([z, -zz, y], axis=-1),
            jnp.stack([zz, z, -x], axis=-1),
            jnp.stack([-y, x, z], axis=-1),
        ],
        axis=-2,
    )


def so3_exp(rotvec):
    """Rotation matrix of a rotation vector (``jaxlie.SO3.exp``).

    ``R = exp([w]x)``, through the unit quaternion
    ``(cos(t/2), sin(t/2) w / t)`` with ``t = |w|``; a Taylor expansion is used
    for small ``t`` so that values and gradients are finite at ``w = 0``.

    Args:
      rotvec: ``(..., 3)`` rotation vector ``w = angle * axis`` (rad).

    Returns:
      ``(..., 3, 3)`` rotation matrix.
    """
    return jaxlie.SO3.exp(_as_float(rotvec)).as_matrix()


def rotation_to_quaternion(R):
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix (``jaxlie.SO3.from_matrix``).

    Mike Day's branch choice: the square root always sees an argument
    ``>= 1``, so values and gradients stay finite at every angle.

    Args:
      R: ``(..., 3, 3)`` rotation matrix.

    Returns:
      ``(..., 4)`` quaternion ``(w, x, y, z)``, sign arbitrary.
    """
    return jaxlie.SO3.from_matrix(_as_float(R)).wxyz


def quaternion_to_rotation(quaternion):
    """Rotation matrix of a quaternion ``(w, x, y, z)``, normalised here (``jaxlie.SO3``).

    Args:
      quaternion: ``(..., 4)`` quaternion ``(w, x, y, z)``, any non-zero norm.

    Returns:
      ``(..., 3, 3)`` rotation matrix. A zero quaternion gives NaN (callers
      that read poses from outside, a tracker or a log, refuse it first).
    """
    v = _as_float(quaternion)
    return jaxlie.SO3(v / jnp.linalg.norm(v, axis=-1, keepdims=True)).as_matrix()


def so3_log(R):
    """Rotation vector of a rotation matrix (inverse of :func:`so3_exp`; ``jaxlie.SO3.log``).

    Goes through the quaternion (:func:`rotation_to_quaternion`), which is
    well conditioned at every angle including pi; ``angle = 2 atan2(|v|, |w|)``.
    For small ``|v|`` a Taylor expansion replaces ``angle / |v|`` so that
    values and gradients are finite at the identity (and the derivative there
    is the exact ``vee((dR - dR^T) / 2)``). At exactly pi the result's sign is
    a convention (the map is discontinuous there).

    Args:
      R: ``(..., 3, 3)`` rotation matrix.

    Returns:
      ``(..., 3)`` rotation vector (rad), norm in ``[0, pi]``.
    """
    return jaxlie.SO3.from_matrix(_as_float(R)).log()


def pose_difference(p_t, R_t, p_prev, R_prev):
    """World-frame pose difference ``V = [p_t - p_prev, log(R_t R_prev^T)]``.

    The rotational part is the rotation vector that takes ``R_prev`` to
    ``R_t`` expressed in the world (camera) frame, i.e. ``omega * dt`` to
    first order.

    Args:
      p_t: ``(..., 3)`` current position (length unit of the system, e.g. m).
      R_t: ``(..., 3, 3)`` current orientation.
      p_prev: ``(..., 3)`` previous position.
      R_prev: ``(..., 3, 3)`` previous orientation.

    Returns:
      ``(..., 6)``: position difference (length unit), rotation vector (rad).
    """
    dp = jnp.asarray(p_t) - jnp.asarray(p_prev)
    dr = so3_log(jnp.asarray(R_t) @ jnp.swapaxes(jnp.asarray(R_prev), -1, -2))
    dtype = jnp.result_type(dp, dr)
    dp, dr = jnp.broadcast_arrays(dp.astype(dtype), dr.astype(dtype))
    return jnp.concatenate([dp, dr], axis=-1)


def noisy_pose(key, pose, pose_noise, rot_noise):
    """A tracker reading of ``pose = (p (3,), R (3, 3))``: ``p + N(0, pose_noise^2)`` per axis (m) and
    ``exp(N(0, rot_noise^2 I)) R``, a random rotation vector of ``rot_noise`` rad per axis.

    ``key`` is split once, position noise first. The one tracker-noise model of
    the self-ID sampling (:func:`selfid_jax.identify.algorithm.run`) and of the
    realism readings (:mod:`selfid_jax.control.realism`).
    """
    p, R = pose
    kp, kr = jax.random.split(key)
    p = p + pose_noise * jax.random.normal(kp, p.shape, p.dtype)
    R = so3_exp(rot_noise * jax.random.normal(kr, (3,), R.dtype)) @ R
    return p, R


def closest_on_polyline(p, vertices):
    """The points of the segments of the polyline ``vertices (V, d)`` closest to ``p (d,)`` and their distances:
    ``(c (S, d), dist (S,))``, ``S = V - 1``; the polyline's closest point is ``c[argmin(dist)]``, its distance
    ``min(dist)``.

    The polyline runs ``vertices[0] -> vertices[1] -> ... -> vertices[-1]``
    (``V >= 2``; a zero-length segment is its start point). The one segment
    distance of the package: the follow loop's path distance and divergence
    test (:class:`selfid_jax.control.task.Task`) and the per-axis path errors
    of :mod:`selfid_jax.control.metrics`. NaN in ``p`` gives NaN.
    """
    a, b = vertices[:-1], vertices[1:]  # (S, d)
    ab = b - a
    denom = jnp.sum(ab * ab, axis=-1)  # (S,)
    t = jnp.clip(jnp.sum((p[None, :] - a) * ab, axis=-1) / jnp.where(denom > 0, denom, 1.0), 0.0, 1.0)
    candidates = a + t[:, None] * ab  # (S, d)
    return candidates, jnp.sqrt(jnp.sum((p[None, :] - candidates) ** 2, axis=-1))
