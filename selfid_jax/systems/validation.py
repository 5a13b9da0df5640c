"""Eager input checks for building a :class:`~selfid_jax.systems.system.System`.

Plain numpy on concrete values, run once when a system is built (never traced),
so a bad argument raises a ``ValueError`` that names it instead of failing
inside ``jit``. Units as in ``System``: rad or m per actuator.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from jax.typing import ArrayLike

from selfid_jax.math.checks import check_magnitude

Values = ArrayLike | Sequence[float]
"""One number or one per actuator (a scalar, a list, a numpy or JAX array) [rad or m]."""

__all__ = ["TASK_DIMS", "AXIS_NAMES", "Limits", "check_task_dim", "check_task_axes", "default_axes", "vector",
           "validate"]


class Limits(NamedTuple):
    """The sizes and actuator limits a :class:`~selfid_jax.systems.System` is built from (rad or m per actuator).

    What the builders (``from_pose_fn``, ``from_mjcf``, ``stewart_hand`` ...) pass to
    ``make_system``; :func:`validate` returns it normalised (``(n_act,)`` float64
    arrays, the sampling box defaulting to the joint limits).
    """

    n_act: int  # number of actuators
    task_dim: int  # 2 (planar xy), 3 (position) or 6 (position + rotation vector)
    q_low: Any  # scalar or (n_act,) joint limits (may be -inf)
    q_high: Any  # scalar or (n_act,) (may be +inf)
    dq_max: Any  # scalar or (n_act,) largest actuator step per control step, > 0
    m_a: Any  # scalar or (n_act,) safe self-ID magnitude, > 0
    sample_low: Any = None  # scalar or (n_act,) box sample_configs draws from (default: q_low)
    sample_high: Any = None  # (default: q_high)
    min_sigma: float = 1e-3  # sample_configs keeps configurations with sigma_min(J) above this

#: Supported task dimensions: planar xy, position, position + rotation vector.
TASK_DIMS = (2, 3, 6)
#: Names of the six pose-difference components ``[dp (3), rotation vector (3)]``, in order.
AXIS_NAMES = ("x", "y", "z", "rx", "ry", "rz")


def default_axes(task_dim: int) -> tuple[int, ...]:
    """The pose-difference components of a ``task_dim`` task: 2 -> (x, y), 3 -> (x, y, z), 6 -> all six."""
    return tuple(range(int(task_dim)))


def check_task_axes(axes, has_rotation: bool = True) -> tuple[int, ...]:
    """Eager check of a task made of chosen pose-difference components; returns them as sorted ints.

    ``axes`` lists indices into ``[x, y, z, rx, ry, rz]`` (0-5) or their names
    (:data:`AXIS_NAMES`), e.g. ``("z", "rx", "ry")``: at least one, no repeats;
    rotation components need a pose map with an orientation.
    """
    try:
        items = list(axes)
    except TypeError:
        raise ValueError(f"task_axes must be a list of axes out of {AXIS_NAMES} (or 0-5), got {axes!r}") from None
    out = []
    for a in items:
        if isinstance(a, str) and a in AXIS_NAMES:
            out.append(AXIS_NAMES.index(a))
        elif isinstance(a, (int, np.integer)) and not isinstance(a, bool) and 0 <= a < 6:
            out.append(int(a))
        else:
            raise ValueError(f"task_axes: {a!r} is not an axis; use names {AXIS_NAMES} or indices 0-5")
    if not out or len(set(out)) != len(out):
        raise ValueError(f"task_axes must name at least one axis, each once, got {items!r}")
    if not has_rotation and any(a >= 3 for a in out):
        raise ValueError(f"task_axes {items!r} include a rotation, but the pose function returns a position only")
    return tuple(sorted(out))


def check_task_dim(task_dim, has_rotation: bool = True) -> None:
    """Eager check: ``task_dim`` is one of :data:`TASK_DIMS`, and not 6 for a position-only pose map."""
    if isinstance(task_dim, bool) or not isinstance(task_dim, (int, np.integer)) or task_dim not in TASK_DIMS:
        raise ValueError(f"task_dim must be one of {TASK_DIMS}, got {task_dim!r}")
    if task_dim == 6 and not has_rotation:
        raise ValueError("task_dim=6 needs an orientation, but the pose function returns a position only")


def vector(name: str, value, n: int) -> np.ndarray:
    """Eager check: ``value`` is a scalar or ``(n,)`` real array; returns ``(n,)`` float64 numpy."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a real scalar or array of shape ({n},), got {value!r}") from e
    if arr.ndim == 0:
        arr = np.full((n,), float(arr))
    if arr.shape != (n,):
        raise ValueError(
            f"{name} must have shape ({n},) (one value per actuator, n_act={n}) or be a scalar, got shape {arr.shape}"
        )
    if np.isnan(arr).any():
        raise ValueError(f"{name} contains NaN: {arr}")
    return arr


def validate(limits: Limits, *, has_rotation: bool) -> Limits:
    """Eager check of a system's sizes and limits; returns them normalised.

    Scalars are broadcast to ``(n_act,)`` float64 numpy arrays, the sampling
    box defaults to the joint limits (``m_a`` too: ``(n_act,)``), and
    ``n_act``, ``task_dim`` and ``min_sigma`` come back as plain numbers. Raises a
    ``ValueError`` naming the first bad field.
    """
    n_act, task_dim, q_low, q_high, dq_max, m_a, sample_low, sample_high, min_sigma = limits
    if isinstance(n_act, bool) or not isinstance(n_act, (int, np.integer)) or n_act < 1:
        raise ValueError(f"n_act must be a positive integer, got {n_act!r}")
    n_act = int(n_act)
    check_task_dim(task_dim, has_rotation)
    q_low = vector("q_low", q_low, n_act)
    q_high = vector("q_high", q_high, n_act)
    if not np.all(q_low < q_high):
        raise ValueError(f"q_low must be < q_high elementwise, got q_low={q_low}, q_high={q_high}")
    dq_max = vector("dq_max", dq_max, n_act)
    if not np.all((dq_max > 0) & np.isfinite(dq_max)):
        raise ValueError(f"dq_max must be positive and finite, got {dq_max}")
    m_a = vector("m_a", m_a, n_act)
    check_magnitude("m_a", m_a, n_act)
    if sample_low is None:
        sample_low = q_low
    if sample_high is None:
        sample_high = q_high
    sample_low = vector("sample_low", sample_low, n_act)
    sample_high = vector("sample_high", sample_high, n_act)
    if not (np.all(np.isfinite(sample_low)) and np.all(np.isfinite(sample_high))):
        raise ValueError(
            "the sampling box must be finite (pass sample_low/sample_high when joint limits are infinite), "
            f"got sample_low={sample_low}, sample_high={sample_high}"
        )
    if not np.all(sample_low < sample_high):
        raise ValueError(
            f"sample_low must be < sample_high elementwise, got sample_low={sample_low}, sample_high={sample_high}"
        )
    if np.any(sample_low < q_low) or np.any(sample_high > q_high):
        raise ValueError(
            f"the sampling box [{sample_low}, {sample_high}] must lie inside the joint limits [{q_low}, {q_high}]"
        )
    min_sigma = float(min_sigma)
    if not (math.isfinite(min_sigma) and min_sigma >= 0):
        raise ValueError(f"min_sigma must be finite and >= 0, got {min_sigma}")
    return Limits(n_act, int(task_dim), q_low, q_high, dq_max, m_a, sample_low, sample_high, min_sigma)
