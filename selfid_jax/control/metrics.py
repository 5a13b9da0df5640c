"""Tracking metrics on recorded trajectories (paper Tables I and II): per-axis distance to the path, rotation error.

Pure ``jax.numpy`` on fixed shapes: every function jits and vmaps (batch a
set of rollouts with ``jax.vmap``). Positions in the system's length unit
(m for the shipped systems), angles in radians unless a name says ``deg``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from selfid_jax.math import geometry
from selfid_jax.math.checks import check_array

__all__ = ["axis_errors", "closest_points", "rotation_error", "rotation_errors_deg"]


def closest_points(points, vertices):
    """Closest point of the polyline ``vertices (V, d)`` to each of ``points (T, d)``: ``(T, d)``.

    The polyline runs ``vertices[0] -> vertices[1] -> ... -> vertices[-1]``
    (e.g. the start pose followed by the waypoints); ``V >= 2``.
    """
    check_array("points", points, (None, None))
    check_array("vertices", vertices, (None, points.shape[-1] if hasattr(points, "shape") else None))
    points, vertices = jnp.asarray(points), jnp.asarray(vertices)
    if vertices.shape[0] < 2:
        raise ValueError(f"vertices: need at least 2 (one segment), got shape {vertices.shape}")

    def one(p):
        candidates, dist = geometry.closest_on_polyline(p, vertices)
        return candidates[jnp.argmin(dist)]

    return jax.vmap(one)(points)


def axis_errors(points, vertices):
    """Per-axis absolute distance ``|p - c(p)|`` of ``points (T, d)`` to their closest path points: ``(T, d)``
    (Table I)."""
    return jnp.abs(jnp.asarray(points) - closest_points(points, vertices))


def rotation_error(R_goal, R):
    """Angle [rad] of the rotation from ``R (..., 3, 3)`` to ``R_goal (..., 3, 3)``: ``|log(R_goal R^T)|``
    (Table II)."""
    R_goal, R = jnp.asarray(R_goal), jnp.asarray(R)
    w = geometry.so3_log(R_goal @ jnp.swapaxes(R, -1, -2))
    return jnp.sqrt(jnp.sum(w * w, axis=-1))


def rotation_errors_deg(R_goal, R):
    """:func:`rotation_error` in degrees."""
    return jnp.degrees(rotation_error(R_goal, R))
