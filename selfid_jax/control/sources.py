"""Where the follow loop's inverse Jacobian comes from: a constant estimate, the system's own, or a function.

Each source has ``pose_and_jinv(system, q) -> ((p (3,), R (3, 3)), Jinv (n, m))``, the controller's one call per
simulated step (:func:`selfid_jax.control.law.inverse_jacobian_law`); a source that needs no model
(:class:`Fixed`, :class:`FromFunction`) is also callable as ``source(q) -> Jinv``, which is all the live robot
asks of it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp

from selfid_jax.math.linalg import pseudo_inverse
from selfid_jax.systems.system import System

__all__ = ["EstimateOrTrue", "Fixed", "FromFunction", "JacobianInverse", "JinvFn", "JinvSource", "estimate_or_true",
           "fixed", "scaled_true_inverse", "true_inverse"]

JinvFn = Callable[[jax.Array], jax.Array]
"""``jinv_fn(q (n,)) -> (n, m)``: the inverse Jacobian the controller uses at ``q``."""


class JinvSource(Protocol):
    """Anything with ``pose_and_jinv(system, q (n,)) -> ((p (3,), R (3, 3)), Jinv (n, m))``: the controller's one
    call per step (:class:`Fixed`, :class:`JacobianInverse`, :class:`FromFunction` or a user's own)."""

    def pose_and_jinv(self, system: System, q) -> tuple[tuple[jax.Array, jax.Array], jax.Array]: ...


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
