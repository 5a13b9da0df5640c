"""SO(3) helpers and the pose difference used as the self-ID task vector.

Pure ``jax.numpy``; every function accepts leading batch axes (``...``) without
``vmap``. Small-angle (and, for ``so3_log``, near-pi) cases use the
"double-where" trick: the unsafe branch is evaluated on a dummy safe input, so
both values and gradients stay finite (jaxlie's ``_so3.py`` does the same).

Units: rotation vectors and angles in radians, positions in the caller's length
unit (metres for the shipped systems).
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["hat", "so3_exp", "so3_log", "rotation_to_quaternion", "pose_difference"]


def _small_angle_threshold(dtype) -> float:
    # Below eps**(1/4) the next neglected Taylor term is O(eps) relative.
    return float(jnp.finfo(dtype).eps) ** 0.25


def _float_dtype(x):
    return x.dtype if jnp.issubdtype(x.dtype, jnp.floating) else jnp.result_type(float)


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
    """Rotation matrix of a rotation vector (Rodrigues' formula).

    ``R = I + sin(t)/t [w]x + (1 - cos t)/t^2 [w]x^2`` with ``t = |w|``; a
    Taylor expansion is used below ``t ~ eps**(1/4)`` so that values and
    gradients are finite at ``w = 0``.

    Args:
      rotvec: ``(..., 3)`` rotation vector ``w = angle * axis`` (rad).

    Returns:
      ``(..., 3, 3)`` rotation matrix.
    """
    rotvec = jnp.asarray(rotvec)
    rotvec = rotvec.astype(_float_dtype(rotvec))
    theta2 = jnp.sum(rotvec * rotvec, axis=-1)
    small = theta2 < _small_angle_threshold(rotvec.dtype) ** 2
    theta2_safe = jnp.where(small, 1.0, theta2)
    theta_safe = jnp.sqrt(theta2_safe)
    a = jnp.where(small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, jnp.sin(theta_safe) / theta_safe)
    b = jnp.where(small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, (1.0 - jnp.cos(theta_safe)) / theta2_safe)
    k = hat(rotvec)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=rotvec.dtype), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def rotation_to_quaternion(R):
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix (Shepperd's method).

    Picks the largest of ``4w^2, 4x^2, 4y^2, 4z^2`` (one of them is >= 1) as the
    pivot, so no square root or division sees a small argument; the unused
    branches are evaluated on clamped inputs so gradients stay finite.

    Args:
      R: ``(..., 3, 3)`` rotation matrix.

    Returns:
      ``(..., 4)`` quaternion ``(w, x, y, z)``, sign arbitrary.
    """
    R = jnp.asarray(R)
    R = R.astype(_float_dtype(R))
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = r00 + r11 + r22
    # 4 * (w^2, x^2, y^2, z^2); they sum to 4, so the largest is >= 1.
    d = jnp.stack([1.0 + tr, 1.0 + 2.0 * r00 - tr, 1.0 + 2.0 * r11 - tr, 1.0 + 2.0 * r22 - tr], axis=-1)
    pivot = jnp.argmax(d, axis=-1)
    s = 2.0 * jnp.sqrt(jnp.maximum(d, 0.25))  # clamp only matters for unused branches
    s0, s1, s2, s3 = s[..., 0], s[..., 1], s[..., 2], s[..., 3]
    q_w = jnp.stack([0.25 * s0, (r21 - r12) / s0, (r02 - r20) / s0, (r10 - r01) / s0], axis=-1)
    q_x = jnp.stack([(r21 - r12) / s1, 0.25 * s1, (r01 + r10) / s1, (r02 + r20) / s1], axis=-1)
    q_y = jnp.stack([(r02 - r20) / s2, (r01 + r10) / s2, 0.25 * s2, (r12 + r21) / s2], axis=-1)
    q_z = jnp.stack([(r10 - r01) / s3, (r02 + r20) / s3, (r12 + r21) / s3, 0.25 * s3], axis=-1)
    cands = jnp.stack([q_w, q_x, q_y, q_z], axis=-2)  # (..., 4 pivots, 4)
    return jnp.take_along_axis(cands, pivot[..., None, None], axis=-2)[..., 0, :]


def so3_log(R):
    """Rotation vector of a rotation matrix (inverse of :func:`so3_exp`).

    Goes through the quaternion (Shepperd's method), which is well conditioned
    at every angle including pi; ``angle = 2 atan2(|v|, |w|)``. Below
    ``|v| ~ eps**(1/4)`` a Taylor expansion replaces ``angle / |v|`` so that
    values and gradients are finite at the identity (and the derivative there
    is the exact ``vee((dR - dR^T) / 2)``). At exactly pi the result's sign is
    a convention (the map is discontinuous there).

    Args:
      R: ``(..., 3, 3)`` rotation matrix.

    Returns:
      ``(..., 3)`` rotation vector (rad), norm in ``[0, pi]``.
    """
    q = rotation_to_quaternion(R)
    q = jnp.where(q[..., :1] < 0.0, -q, q)  # w >= 0: angle in [0, pi]
    w, v = q[..., 0], q[..., 1:]
    n2 = jnp.sum(v * v, axis=-1)
    small = n2 < _small_angle_threshold(q.dtype) ** 2
    n_safe = jnp.sqrt(jnp.where(small, 1.0, n2))
    w_safe = jnp.where(small, w, 1.0)  # w ~ 1 when small
    scale = jnp.where(
        small,
        2.0 / w_safe * (1.0 - n2 / (3.0 * w_safe**2)),
        2.0 * jnp.arctan2(n_safe, w) / n_safe,
    )
    return scale[..., None] * v


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
