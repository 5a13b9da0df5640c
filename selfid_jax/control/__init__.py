"""Path following with an inverse Jacobian: the follow loop, the E-KM QP law, DLS/IK, reference paths, metrics.

``selfid_jax.control`` re-exports the follow loop (:mod:`~selfid_jax.control.loop`):
``follow``, ``ControllerParams``, ``FollowResult``, the inverse-Jacobian sources
(``fixed``, ``true_inverse``, ``scaled_true_inverse``, ``estimate_or_true``), ``feasible_starts``, and
the one loop under them with a pluggable step law (``follow_law``, ``StepLaw``,
``inverse_jacobian_law``; the QP law is :func:`selfid_jax.control.qp.constrained_law`).
"""

from selfid_jax.control.loop import (
    DEFAULT_STEPS,
    ControllerParams,
    EstimateOrTrue,
    Fixed,
    FollowResult,
    FromFunction,
    JacobianInverse,
    StepLaw,
    clip_norm,
    completed,
    estimate_or_true,
    feasible_indices,
    feasible_starts,
    fixed,
    follow,
    follow_law,
    inverse_jacobian_law,
    safe_norm,
    scaled_true_inverse,
    true_inverse,
    waypoint_poses,
)

__all__ = [
    "DEFAULT_STEPS",
    "ControllerParams",
    "EstimateOrTrue",
    "Fixed",
    "FollowResult",
    "FromFunction",
    "JacobianInverse",
    "StepLaw",
    "clip_norm",
    "completed",
    "estimate_or_true",
    "feasible_indices",
    "feasible_starts",
    "fixed",
    "follow",
    "follow_law",
    "inverse_jacobian_law",
    "safe_norm",
    "scaled_true_inverse",
    "true_inverse",
    "waypoint_poses",
]
