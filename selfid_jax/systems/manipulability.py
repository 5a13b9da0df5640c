"""Dexterity metrics of a Jacobian: manipulability (two definitions), condition, position-only and unit-consistent.

All functions take a task Jacobian ``J (..., m, n)`` (leading batch axes work
without ``vmap``; ``vmap`` and ``jit`` work too) and go through its singular
values ``sigma_1 >= ... >= sigma_k``, ``k = min(m, n)`` (``jnp.linalg.svd``).
Units: for a geometric Jacobian ``[Jv; Jw]`` of revolute joints, ``Jv`` rows are
m/rad and ``Jw`` rows rad/rad, so a 6-row ``J`` mixes units (see
:func:`unit_consistent_condition`).

Two manipulabilities, both named because they differ by a square root:

* :func:`yoshikawa_manipulability` ``prod sigma_i``: Yoshikawa's
  ``sqrt(det(J J^T))`` where ``J`` has full row rank (``m <= n``), the volume
  of the velocity ellipsoid; what ``System.manipulability`` returns.
* :func:`sqrt_manipulability` ``sqrt(prod sigma_i)``: seed 004's ``omega``.
  For its 6x5 Jacobian ``J J^T`` is 6x6 of rank 5, so ``det(J J^T) = 0``
  always; the slides take the product of the five singular values instead and
  keep the outer square root of ``sqrt(det(.))``. It orders configurations
  exactly as Yoshikawa's does (a monotone map), but its scale differs.

The condition ``sigma_max / sigma_min`` is 1 for an isotropic Jacobian and
grows without bound near a singularity (``inf`` at an exact one).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from selfid_jax.math.checks import check_scalar

__all__ = [
    "Metrics",
    "condition",
    "metrics",
    "position_rows",
    "singular_values",
    "sqrt_manipulability",
    "unit_consistent_condition",
    "unit_consistent_jacobian",
    "yoshikawa_manipulability",
]


def _check_jacobian(J, name: str = "J") -> jax.Array:
    J = jnp.asarray(J)
    if J.ndim < 2 or 0 in J.shape[-2:]:
        raise ValueError(f"{name}: expected a Jacobian of shape (..., m, n) with m, n >= 1, got shape {J.shape}")
    if not jnp.issubdtype(J.dtype, jnp.floating):
        J = J.astype(jnp.result_type(float))
    return J


def singular_values(J) -> jax.Array:
    """Singular values of ``J (..., m, n)``, descending: ``(..., min(m, n))`` (task units per actuator unit)."""
    return jnp.linalg.svd(_check_jacobian(J), compute_uv=False)


def yoshikawa_manipulability(J) -> jax.Array:
    """Yoshikawa's manipulability ``prod_i sigma_i`` of ``J (..., m, n)``: ``(...)``.

    Equals ``sqrt(det(J J^T))`` when ``m <= n`` and ``sqrt(det(J^T J))`` when
    ``m > n`` (e.g. the 6x5 Jacobian of a 5-DOF arm, where ``det(J J^T) = 0``).
    Units: the product of the rows' units per actuator unit (m^3/rad^3 for a
    position Jacobian of revolute joints).
    """
    return jnp.prod(singular_values(J), axis=-1)


def sqrt_manipulability(J) -> jax.Array:
    """Seed 004's manipulability ``omega = sqrt(prod_i sigma_i)`` of ``J (..., m, n)``: ``(...)``.

    The slides' definition for the 6x5 Jacobian of their arm, whose
    ``det(J J^T)`` is always 0 (rank 5 in 6 rows): the square root of
    :func:`yoshikawa_manipulability`, so the same ordering on a compressed scale.
    """
    return jnp.sqrt(yoshikawa_manipulability(J))


def _ratio(sigma):
    """``sigma[..., 0] / sigma[..., -1]`` with ``inf`` (not NaN) where the smallest is 0."""
    hi, lo = sigma[..., 0], sigma[..., -1]
    ok = lo > 0
    return jnp.where(ok, hi / jnp.where(ok, lo, 1.0), jnp.inf)


def condition(J) -> jax.Array:
    """Condition number ``sigma_max / sigma_min`` of ``J (..., m, n)``: ``(...)``, >= 1, ``inf`` if singular.

    ``kappa >> 1`` means close to a singularity (seed 004). For a 6-row
    Jacobian that mixes m/rad and rad/rad rows the number depends on the
    length unit: use :func:`unit_consistent_condition` to compare arms or
    configurations.
    """
    return _ratio(singular_values(J))


def position_rows(J) -> jax.Array:
    """The position part ``Jv = J[..., :3, :]`` of a geometric Jacobian ``(..., 6, n)``: ``(..., 3, n)``."""
    J = _check_jacobian(J)
    if J.shape[-2] != 6:
        raise ValueError(f"J: position_rows needs a 6-row geometric Jacobian [Jv; Jw], got shape {J.shape}")
    return J[..., :3, :]


def unit_consistent_jacobian(J, length) -> jax.Array:
    """``[Jv; L Jw]``: the rotation rows of a geometric ``J (..., 6, n)`` times a characteristic length ``L`` [m].

    Every row then reads m per actuator unit: ``L Jw`` is the velocity that the
    angular velocity gives a point ``L`` away from the tool.
    """
    J = _check_jacobian(J)
    if J.shape[-2] != 6:
        raise ValueError(f"J: the unit-consistent Jacobian needs a 6-row [Jv; Jw], got shape {J.shape}")
    check_scalar("length", length, gt=0.0)
    length = jnp.asarray(length, J.dtype)
    if length.ndim:
        raise ValueError(f"length: expected a scalar (vmap for several), got shape {length.shape}")
    return jnp.concatenate([J[..., :3, :], length * J[..., 3:, :]], axis=-2)


def unit_consistent_condition(J, length) -> jax.Array:
    """Condition of :func:`unit_consistent_jacobian`: ``(...)``, dimensionless and independent of the length unit.

    Why: ``Jv`` (m/rad) and ``Jw`` (rad/rad) differ in size by about the arm's
    length, so the plain 6-row condition mostly measures that ratio. On seed
    004's arm the link lengths are 0.1-0.15 m while ``|Jw|`` columns are 1: the
    mixed-unit condition never drops below about 16 anywhere in the workspace
    and does not show where the arm is dexterous. Scaling the rotation rows by a
    characteristic length ``L`` (e.g. about the arm's reach; Angeles' choice is
    the ``L`` minimising the best condition) gives a number that changes only
    with the arm's geometry, not with the unit.
    """
    return _ratio(singular_values(unit_consistent_jacobian(J, length)))


class Metrics(NamedTuple):
    """Dexterity of one geometric Jacobian ``J (6, n)`` (leading batch axes if vmapped)."""

    sqrt_manipulability: jax.Array  # () sqrt(prod sigma(J)), seed 004's omega
    yoshikawa: jax.Array  # () prod sigma(J)
    condition: jax.Array  # () sigma_max / sigma_min of the mixed-unit 6-row J
    position_sqrt_manipulability: jax.Array  # () sqrt(prod sigma(Jv)), Jv = J[:3] [m^(3/2)/rad^(3/2)]
    position_yoshikawa: jax.Array  # () prod sigma(Jv) [m^3/rad^3]
    position_condition: jax.Array  # () of Jv
    unit_consistent_condition: jax.Array  # () of [Jv; L Jw]
    sigma_min: jax.Array  # () smallest singular value of J
    position_sigma_min: jax.Array  # () smallest singular value of Jv [m/rad]


def metrics(J, length) -> Metrics:
    """Every metric of this module for a geometric ``J (..., 6, n)`` and characteristic length ``length`` [m].

    Three SVDs (``J``, ``Jv``, ``[Jv; L Jw]``); batch axes pass through.
    """
    J = _check_jacobian(J)
    s6 = singular_values(J)
    s3 = singular_values(position_rows(J))
    su = singular_values(unit_consistent_jacobian(J, length))
    y6, y3 = jnp.prod(s6, axis=-1), jnp.prod(s3, axis=-1)
    return Metrics(
        sqrt_manipulability=jnp.sqrt(y6),
        yoshikawa=y6,
        condition=_ratio(s6),
        position_sqrt_manipulability=jnp.sqrt(y3),
        position_yoshikawa=y3,
        position_condition=_ratio(s3),
        unit_consistent_condition=_ratio(su),
        sigma_min=s6[..., -1],
        position_sigma_min=s3[..., -1],
    )
