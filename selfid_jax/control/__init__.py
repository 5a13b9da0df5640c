"""Path following with an inverse Jacobian: the follow loop, the E-KM QP law, DLS/IK, reference paths, metrics.

``selfid_jax.control`` re-exports the follow loop (:mod:`~selfid_jax.control.loop`):
``follow``, ``ControllerParams``, ``FollowResult``, the inverse-Jacobian sources
(``fixed``, ``true_inverse``, ``scaled_true_inverse``) and ``feasible_starts``.
"""

from selfid_jax.control.loop import (
    DEFAULT_STEPS,
    ControllerParams,
    Fixed,
    FollowResult,
    FromFunction,
    JacobianInverse,
    feasible_starts,
    fixed,
    follow,
    scaled_true_inverse,
    true_inverse,
    waypoint_poses,
)

__all__ = [
    "DEFAULT_STEPS",
    "ControllerParams",
    "Fixed",
    "FollowResult",
    "FromFunction",
    "JacobianInverse",
    "feasible_starts",
    "fixed",
    "follow",
    "scaled_true_inverse",
    "true_inverse",
    "waypoint_poses",
]
