"""Path following with an inverse Jacobian: the follow loop, the E-KM QP law, DLS/IK, reference paths, metrics.

``selfid_jax.control`` re-exports the follow loop (:mod:`~selfid_jax.control.loop`: ``follow``,
``FollowResult``, ``feasible_starts``, and ``follow_law`` under them), the inverse-Jacobian sources
(:mod:`~selfid_jax.control.sources`: ``fixed``, ``true_inverse``, ``scaled_true_inverse``, ``estimate_or_true``),
the task geometry (:mod:`~selfid_jax.control.task`: ``ControllerParams``, ``Task``) and the per-step law with the
one control step the simulation and the live robot share (:mod:`~selfid_jax.control.law`: ``StepLaw``,
``inverse_jacobian_law``, ``command``; the QP law is :func:`selfid_jax.control.qp.constrained_law`).
"""

from selfid_jax.control import dls, font, law, loop, metrics, paths, qp, realism, sources, task
from selfid_jax.control.law import Command, StepLaw, command, inverse_jacobian_law
from selfid_jax.control.loop import (
    DEFAULT_STEPS,
    FollowResult,
    completed,
    feasible_indices,
    feasible_starts,
    follow,
    follow_law,
)
from selfid_jax.control.sources import (
    EstimateOrTrue,
    Fixed,
    FromFunction,
    JacobianInverse,
    estimate_or_true,
    fixed,
    scaled_true_inverse,
    true_inverse,
)
from selfid_jax.control.task import ControllerParams, Task, cap_actuator_step, clip_norm, safe_norm, waypoint_poses

__all__ = [
    # the modules
    "dls", "font", "law", "loop", "metrics", "paths", "qp", "realism", "sources", "task",
    "DEFAULT_STEPS",
    "Command",
    "ControllerParams",
    "EstimateOrTrue",
    "Fixed",
    "FollowResult",
    "FromFunction",
    "JacobianInverse",
    "StepLaw",
    "Task",
    "cap_actuator_step",
    "clip_norm",
    "command",
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
