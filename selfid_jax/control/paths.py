"""Waypoint paths for the point of manipulation: star, text, cube, rotation.

Every generator returns waypoint *offsets* relative to a start pose, shape
``(W, dim)``, as a float ``jnp`` array. The start pose itself is not a
waypoint: offset 0 is never waypoint 0, so a controller that starts at the
start pose must move to reach the first waypoint. Paths that close
(``star``, ``cube``) end with an all-zero offset.

Task vectors (and so offsets) are ``(dim,)`` with ``dim`` one of

* 2: planar ``xy`` position (metres),
* 3: ``xyz`` position (metres),
* 6: position (metres) followed by a rotation vector (radians), world frame.

The generators are built eagerly in numpy from static arguments (sizes,
planes, strings): call them outside ``jit`` and pass the result in. Only
``place`` is traceable.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from selfid_jax.control.font import FONT, FONT_CAP_UNITS

__all__ = [
    "DIMS",
    "PLANES",
    "PENTAGRAM_INNER_RATIO",
    "FONT",
    "FONT_CAP_UNITS",
    "TextBox",
    "star",
    "text",
    "text_box",
    "supported_characters",
    "cube",
    "rotation",
    "place",
    "path_length",
    "densify",
]

DIMS: tuple[int, ...] = (2, 3, 6)
# Plane name -> (index of the horizontal axis, index of the vertical axis).
PLANES: dict[str, tuple[int, int]] = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}

# Inner/outer radius of a regular pentagram {5/2}: cos(72 deg)/cos(36 deg) = 1/phi^2.
PENTAGRAM_INNER_RATIO: float = math.cos(2 * math.pi / 5) / math.cos(math.pi / 5)


# ----------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------


def _check_dim(dim, allowed: tuple[int, ...] = DIMS) -> int:
    if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or int(dim) not in allowed:
        raise ValueError(f"dim must be one of {allowed}, got {dim!r}")
    return int(dim)


def _check_plane(plane, dim: int) -> tuple[int, int]:
    if plane not in PLANES:
        raise ValueError(f"plane must be one of {tuple(PLANES)}, got {plane!r}")
    if dim == 2 and plane != "xy":
        raise ValueError(f"plane must be 'xy' when dim=2 (the only plane of a planar task), got {plane!r}")
    return PLANES[plane]


def _check_positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}") from None
    if not math.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def _embed_plane(uv: np.ndarray, plane: str, dim: int) -> np.ndarray:
    """Map planar points ``(N, 2)`` into task offsets ``(N, dim)``; rotation part zero."""
    i, j = _check_plane(plane, dim)
    out = np.zeros((uv.shape[0], dim), dtype=np.float64)
    out[:, i] = uv[:, 0]
    out[:, j] = uv[:, 1]
    return out


def _drop_repeats(points: np.ndarray) -> np.ndarray:
    """Remove consecutive duplicate points ``(N, d)`` (zero-length segments)."""
    if points.shape[0] == 0:
        return points
    keep = np.ones(points.shape[0], dtype=bool)
    keep[1:] = np.any(np.abs(np.diff(points, axis=0)) > 1e-12, axis=1)
    return points[keep]


def _as_jnp(points: np.ndarray) -> jnp.ndarray:
    # jnp.asarray follows the x64 setting: float64 with x64 on, float32 otherwise.
    return jnp.asarray(points, dtype=jnp.result_type(float))


# ----------------------------------------------------------------------------
# Star
# ----------------------------------------------------------------------------


def star(*, size: float = 0.1, plane: str = "xy", dim: int = 3, inner_ratio: float = PENTAGRAM_INNER_RATIO):
    """Outline of a 5-pointed star whose top outer point is the start pose.

    The outline has 10 vertices alternating outer points (radius ``size``) and
    inner vertices (radius ``inner_ratio * size``), 36 degrees apart about the
    star's centre, which lies ``size`` below the start along the plane's
    vertical axis. The start is the top outer vertex (vertex 0); the path
    visits vertices 1..9 counter-clockwise in the plane (the first waypoint is
    the inner vertex below and left of the start) and returns to vertex 0.

    Args:
      size: outer radius in metres (> 0).
      plane: ``"xy"``, ``"xz"`` or ``"yz"``; the first named axis is the
        star's horizontal, the second its vertical. Only ``"xy"`` for dim 2.
      dim: task dimension, 2, 3 or 6 (rotation part zero).
      inner_ratio: inner/outer radius in (0, 1). The default
        ``PENTAGRAM_INNER_RATIO`` (~0.382) makes the outline a regular
        pentagram: each pair of edges O_k -> I -> I' -> O_{k+2} is collinear.

    Returns:
      ``(10, dim)`` offsets in metres from the start; the last row is 0.
      All 10 outline edges have the same length.
    """
    size = _check_positive("size", size)
    ratio = _check_positive("inner_ratio", inner_ratio)
    if ratio >= 1.0:
        raise ValueError(f"inner_ratio must be in (0, 1), got {inner_ratio!r}")
    dim = _check_dim(dim)
    _check_plane(plane, dim)

    k = np.arange(11)
    angle = np.pi / 2 + k * np.pi / 5
    radius = np.where(k % 2 == 0, size, ratio * size)
    uv = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)
    uv = uv - uv[0]  # offsets from the start vertex (vertex 0 at the top)
    uv[10] = 0.0  # exact closure, not cos/sin round-off
    return _as_jnp(_embed_plane(uv[1:], plane, dim))


# ----------------------------------------------------------------------------
# Text in the single-stroke font of selfid_jax.control.font
# ----------------------------------------------------------------------------

def supported_characters() -> str:
    """The characters ``text`` can draw, as one string."""
    return "".join(FONT)


class TextBox(NamedTuple):
    """Layout box of a ``text`` path, in plane coordinates (u along the text, v up).

    ``waypoint_uv - origin`` lies in ``[0, width] x [0, height]``.
    """

    origin: np.ndarray  # (2,) offset of the box's lower-left corner from the start, metres
    width: float  # metres
    height: float  # cap height, metres


def _text_layout(string, height: float, spacing) -> tuple[np.ndarray, float, float]:
    """Chained polyline in box coordinates ``(N, 2)``, box width, letter spacing."""
    if not isinstance(string, str) or not string:
        raise ValueError(f"string must be a non-empty str, got {string!r}")
    unknown = sorted({c for c in string if c not in FONT})
    if unknown:
        raise ValueError(
            f"string contains unsupported character(s) {''.join(unknown)!r}; "
            f"supported characters: {supported_characters()!r}"
        )
    height = _check_positive("height", height)
    if spacing is None:
        spacing = 0.25 * height
    else:
        try:
            spacing = float(spacing)
        except (TypeError, ValueError):
            raise ValueError(f"spacing must be a finite number >= 0 or None, got {spacing!r}") from None
        if not math.isfinite(spacing) or spacing < 0.0:
            raise ValueError(f"spacing must be a finite number >= 0 or None, got {spacing!r}")

    unit = height / FONT_CAP_UNITS
    cursor = 0.0
    pieces = []
    for i, char in enumerate(string):
        width, strokes = FONT[char]
        for stroke in strokes:
            pieces.append(np.asarray(stroke, dtype=np.float64) * unit + np.array([cursor, 0.0]))
        cursor += width * unit + (spacing if i < len(string) - 1 else 0.0)
    if not pieces:
        raise ValueError(f"string {string!r} has no strokes to draw (only blanks)")
    return np.concatenate(pieces, axis=0), cursor, spacing


def text_box(string: str, *, height: float = 0.012, spacing: float | None = None) -> TextBox:
    """Where ``text(string, ...)`` puts its letters relative to the start.

    Same arguments as ``text``. Returns a ``TextBox`` whose ``origin`` (``(2,)``,
    metres) is the lower-left corner of the text relative to the start pose,
    in the plane's (horizontal, vertical) coordinates.
    """
    points, width, _ = _text_layout(string, height, spacing)
    return TextBox(origin=-points[0], width=width, height=float(height))


def text(string: str, *, height: float = 0.012, plane: str = "xy", dim: int = 3, spacing: float | None = None):
    """Letters of ``string`` written as one pen-down polyline, start = first stroke point.

    Glyphs come from ``FONT`` (uppercase A-Z, digits 0-9, ``-`` and space),
    scaled so capitals are ``height`` tall and placed left to right along the
    plane's horizontal axis (vertical axis up) with ``spacing`` between
    letters. Strokes are chained with straight moves; the pen never lifts, so
    these moves are part of the path. The first point of the first stroke is
    the start pose and is dropped; consecutive duplicate points are merged.
    ``text_box`` gives the letters' box relative to the start.

    Args:
      string: characters to draw; any other character raises ``ValueError``.
      height: cap height in metres (> 0).
      plane: ``"xy"``, ``"xz"`` or ``"yz"`` (first axis = writing direction,
        second = up). Only ``"xy"`` for dim 2.
      dim: task dimension, 2, 3 or 6 (rotation part zero).
      spacing: gap between letter boxes in metres (>= 0); ``None`` = ``height / 4``.

    Returns:
      ``(W, dim)`` offsets in metres from the start, W depends on the string.
    """
    dim = _check_dim(dim)
    _check_plane(plane, dim)
    points, _, _ = _text_layout(string, height, spacing)
    uv = _drop_repeats(points - points[0])[1:]
    return _as_jnp(_embed_plane(uv, plane, dim))


# ----------------------------------------------------------------------------
# Cube
# ----------------------------------------------------------------------------

# Closed route over the 12 edges of the unit cube from corner (0, 0, 0):
# every corner has odd degree 3, so a closed route repeats at least 4 edges
# (Chinese postman); this one repeats the 4 vertical edges, 16 moves in all.
_CUBE_ROUTE = np.array(
    [
        (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 0),  # bottom face
        (0, 0, 1), (1, 0, 1), (1, 0, 0), (1, 0, 1),
        (1, 1, 1), (1, 1, 0), (1, 1, 1), (0, 1, 1),
        (0, 1, 0), (0, 1, 1), (0, 0, 1), (0, 0, 0),
    ],
    dtype=np.float64,
)  # fmt: skip


def cube(*, edge: float = 0.15, dim: int = 3):
    """Route along all 12 edges of an axis-aligned cube with one corner at the start.

    The cube spans ``[0, edge]^3`` from the start (positive x, y, z). The route
    is a shortest closed walk covering every edge: 16 moves of length
    ``edge``, the 4 vertical (z) edges traversed twice, ending at the start.
    The orientation is constant (rotation part zero for dim 6).

    Args:
      edge: edge length in metres (> 0).
      dim: task dimension, 3 or 6.

    Returns:
      ``(16, dim)`` corner offsets in metres from the start; the last row is 0.
    """
    edge = _check_positive("edge", edge)
    dim = _check_dim(dim, (3, 6))
    out = np.zeros((_CUBE_ROUTE.shape[0], dim), dtype=np.float64)
    out[:, :3] = edge * _CUBE_ROUTE
    return _as_jnp(out)


# ----------------------------------------------------------------------------
# Rotation
# ----------------------------------------------------------------------------


def rotation(*, axis=(1.0, 0.0, 0.0), angle: float = 0.2, steps: int = 1, dim: int = 6):
    """Pure rotation targets about a fixed world axis, position held.

    Waypoint k (k = 1..steps) has position offset 0 and rotation-vector offset
    ``axis / |axis| * angle * k / steps``, i.e. ``R_k = exp(r_k) R_start``.

    Args:
      axis: ``(3,)`` rotation axis in the world frame, any non-zero length.
      angle: final rotation angle in radians (sign follows the axis).
      steps: number of evenly spaced targets (int >= 1).
      dim: task dimension; must be 6.

    Returns:
      ``(steps, 6)`` offsets: zeros in ``[:, :3]`` (metres), rotation vectors
      in ``[:, 3:]`` (radians).
    """
    dim = _check_dim(dim, (6,))
    axis = np.asarray(axis, dtype=np.float64)
    if axis.shape != (3,) or not np.all(np.isfinite(axis)):
        raise ValueError(f"axis must be a finite 3-vector, got {axis.tolist()!r}")
    norm = float(np.linalg.norm(axis))
    if norm == 0.0:
        raise ValueError("axis must be non-zero, got (0, 0, 0)")
    try:
        angle = float(angle)
    except (TypeError, ValueError):
        raise ValueError(f"angle must be a finite number (radians), got {angle!r}") from None
    if not math.isfinite(angle):
        raise ValueError(f"angle must be a finite number (radians), got {angle!r}")
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValueError(f"steps must be an int >= 1, got {steps!r}")
    fractions = np.arange(1, int(steps) + 1, dtype=np.float64) / int(steps)
    out = np.zeros((int(steps), 6), dtype=np.float64)
    out[:, 3:] = (axis / norm * angle)[None, :] * fractions[:, None]
    return _as_jnp(out)


# ----------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------


def place(offsets, start_task_vector):
    """Absolute waypoints from offsets and the start task vector (traceable).

    ``offsets`` ``(..., W, dim)`` and ``start_task_vector`` ``(..., dim)``
    (broadcast over leading axes). For dim 2 and 3 this is
    ``start + offsets`` (metres). For dim 6 only the position part is added;
    the rotation part (``offsets[..., 3:]``) is returned unchanged and stays a
    rotation vector *relative to the start orientation*: the target
    orientation is ``R_target = exp(r) R_start`` (world frame, left
    multiplied), not the rotation vector ``r_start + r``.

    Returns:
      ``(..., W, dim)`` waypoints.
    """
    offsets = jnp.asarray(offsets)
    start = jnp.asarray(start_task_vector)
    dim = offsets.shape[-1]
    _check_dim(dim)
    if start.shape[-1] != dim:
        raise ValueError(f"start_task_vector must have last dimension {dim} (offsets' dim), got shape {start.shape}")
    start = jnp.expand_dims(start, -2)
    shape = jnp.broadcast_shapes(offsets.shape, start.shape)
    offsets, start = jnp.broadcast_to(offsets, shape), jnp.broadcast_to(start, shape)
    if dim == 6:
        return jnp.concatenate([offsets[..., :3] + start[..., :3], offsets[..., 3:]], axis=-1)
    return offsets + start


def _position_dims(dim: int) -> int:
    return 3 if dim == 6 else dim


def _waypoints_and_start(waypoints, start) -> tuple[np.ndarray, np.ndarray, int]:
    """Checked ``(waypoints (W, dim) with W >= 1, start (dim,) default 0, dim)`` as float64 numpy."""
    pts = np.asarray(waypoints, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[0] == 0:
        raise ValueError(f"waypoints must have shape (W, dim) with W >= 1, got {pts.shape}")
    dim = _check_dim(pts.shape[1])
    start = np.zeros(dim) if start is None else np.asarray(start, dtype=np.float64)
    if start.shape != (dim,):
        raise ValueError(f"start must have shape ({dim},), got {start.shape}")
    return pts, start, dim


def path_length(waypoints, start=None) -> float:
    """Euclidean length (metres) of the polyline start -> waypoints[0] -> ... -> waypoints[-1].

    ``waypoints`` ``(W, dim)``; ``start`` ``(dim,)``, default the origin (as
    for offsets). For dim 6 only the position part is measured. Eager
    (returns a Python float).
    """
    pts, start, dim = _waypoints_and_start(waypoints, start)
    p = _position_dims(dim)
    full = np.concatenate([start[None, :p], pts[:, :p]], axis=0)
    return float(np.sum(np.linalg.norm(np.diff(full, axis=0), axis=1)))


def densify(waypoints, max_segment: float, *, start=None, max_angle: float | None = None):
    """Insert evenly spaced intermediate waypoints so no move exceeds ``max_segment``.

    Each segment (including start -> waypoints[0]) is split into
    ``n = max(1, ceil(|dp| / max_segment), ceil(|dr| / max_angle))`` equal
    pieces (up to a 1e-6 relative slack for float32 round-off) by linear
    interpolation, ``dp`` being the position change (metres)
    and ``dr`` the rotation-vector change (radians, dim 6 and ``max_angle``
    given only). The original waypoints are kept; the start is not added.
    Output size is computed eagerly, so call outside ``jit``.

    Args:
      waypoints: ``(W, dim)`` waypoints (offsets or absolute).
      max_segment: largest allowed position step in metres (> 0).
      start: ``(dim,)`` start of the first segment, default the origin.
      max_angle: largest allowed rotation-vector step in radians (> 0), or None.

    Returns:
      ``(W', dim)`` waypoints, ``W' >= W``, ending at ``waypoints[-1]``.
    """
    max_segment = _check_positive("max_segment", max_segment)
    if max_angle is not None:
        max_angle = _check_positive("max_angle", max_angle)
    pts, start, dim = _waypoints_and_start(waypoints, start)
    p = _position_dims(dim)
    prev = np.concatenate([start[None], pts[:-1]], axis=0)
    delta = pts - prev
    # The slack lets float32 inputs that are exact multiples (0.15 m / 0.15 m) keep n = 1.
    slack = 1e-6
    n = np.ceil(np.linalg.norm(delta[:, :p], axis=1) / max_segment - slack)
    if max_angle is not None and dim == 6:
        n = np.maximum(n, np.ceil(np.linalg.norm(delta[:, 3:], axis=1) / max_angle - slack))
    n = np.maximum(n, 1).astype(int)
    out = [prev[i] + delta[i] * (np.arange(1, n[i] + 1)[:, None] / n[i]) for i in range(pts.shape[0])]
    dense = np.concatenate(out, axis=0)
    dense[np.cumsum(n) - 1] = pts  # exact original waypoints
    return _as_jnp(dense)
