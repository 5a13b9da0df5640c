"""The paper's estimator behind the ablation interface: signed x magnitude, refined (Eq. 6-14).

``"ours"``: :func:`selfid_jax.estimator.update` folds each sample; the estimate
is ``refine(state, J0)`` (Eq. 14) from ``J0 = signed * magnitude`` (Eq. 13),
with the magnitude variant of :mod:`selfid_jax.magnitude` selectable.

Static options:
  ``magnitude``: ``"mean"`` (paper, Eq. 12) | ``"median"`` | ``"weighted"`` | ``"kalman"``.
  ``refine``: ``False`` returns ``J0`` itself (Eq. 13 alone).
  ``refine_method``: ``"closed_form"`` (default; min-norm least squares from
    ``J0``) | ``"optax"`` (preconditioned gradient descent, 100 steps).
  ``refine_steps``: ``None`` or a step budget ``k``: ``k`` steps of plain
    Nesterov gradient descent (``method="optax"``, ``precondition=False``), an
    early-stopped refinement as SLSQP stopped at its tolerance in the paper;
    overrides ``refine_method``. Under a small budget the initial guess matters.
  ``sign_project``: project the gradient iterates onto the signed inverse
    Jacobian (gradient refinement only).
Traced parameters: ``v_tol`` (task units, Eq. 11 threshold), ``magnitude_q``,
``magnitude_r`` (relative noise variances of the Kalman magnitude).

With ``>= m`` independent samples and a converged refinement, Eq. 14 has one
solution whatever ``J0`` is, so ``"ours"`` equals ``"direct"``; they differ with
fewer samples than task dimensions or under ``refine_steps``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from selfid_jax import estimator, magnitude
from selfid_jax.baselines.base import Family
from selfid_jax.refine import refine

REFINE_METHODS = ("closed_form", "optax")


class BufferState(NamedTuple):
    """State of the buffer-based methods (ours, direct, the oracles)."""

    est: estimator.EstimatorState  # sign weights, magnitude sums, sample ring buffer (Eq. 6-12)
    J_init: jax.Array  # (n, m) float: fixed initial guess of "direct" (zeros elsewhere)
    count: jax.Array  # () int32: accepted samples
    rejected: jax.Array  # () int32: rejected samples
    params: dict  # traced scalars: {"v_tol", ...}

    @property
    def shape_ref(self) -> jax.Array:
        return self.J_init


def buffer_init(n, m, capacity, dtype, params, J_init=None) -> BufferState:
    """Empty :class:`BufferState`; ``params["v_tol"]`` (if present) sets the Eq. 11 threshold."""
    est = estimator.init(n, m, capacity=capacity, v_tol=params.get("v_tol", 1e-9), dtype=dtype)
    return BufferState(
        est=est,
        J_init=jnp.zeros((n, m), dtype) if J_init is None else J_init,
        count=jnp.zeros((), jnp.int32),
        rejected=jnp.zeros((), jnp.int32),
        params=params,
    )


def buffer_update(state: BufferState, dtheta, V, static) -> BufferState:
    """Fold a (valid) sample into the estimator (Eq. 6-12) and its ring buffer."""
    return state._replace(est=estimator.update(state.est, dtheta, V))


def refine_from(est: estimator.EstimatorState, J0, static) -> jax.Array:
    """Eq. 14 refinement of ``J0 (n, m)`` on the buffered samples, as the static options select."""
    steps = static.get("refine_steps")
    sign_project = static.get("sign_project", False)
    if steps is not None:
        return refine(est, J0, method="optax", steps=steps, precondition=False, sign_project=sign_project)
    if static["refine_method"] == "closed_form" and not sign_project:
        return refine(est, J0, method="closed_form")
    return refine(est, J0, method="optax", sign_project=sign_project)


def validate_refine(static) -> None:
    """Raise ``ValueError`` on bad refinement options."""
    if static["refine_method"] not in REFINE_METHODS:
        raise ValueError(f"refine_method: expected one of {REFINE_METHODS}, got {static['refine_method']!r}")
    steps = static["refine_steps"]
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise ValueError(f"refine_steps: expected None or a positive int, got {steps!r}")


def initial_guess(state: BufferState, static) -> jax.Array:
    """``J0 = signed * magnitude`` (Eq. 13) with the selected magnitude variant, ``(n, m)``."""
    name = static["magnitude"]
    if name == "kalman":
        mag = magnitude.kalman(state.est, q=state.params["magnitude_q"], r=state.params["magnitude_r"])
    else:
        mag = magnitude.get(name)(state.est)
    return estimator.signed_inverse_jacobian(state.est) * mag


def _init(n, m, key, capacity, dtype, static, params):
    return buffer_init(n, m, capacity, dtype, params)


def _estimate(state, truth, static):
    J0 = initial_guess(state, static)
    if not static["refine"]:
        return J0
    return refine_from(state.est, J0, static)


def _validate(static):
    if static["magnitude"] not in magnitude.VARIANTS:
        raise ValueError(f"magnitude: expected one of {magnitude.VARIANTS}, got {static['magnitude']!r}")
    if not isinstance(static["refine"], bool) or not isinstance(static["sign_project"], bool):
        raise ValueError("refine and sign_project must be booleans")
    if static["sign_project"] and static["refine_method"] == "closed_form" and static["refine_steps"] is None:
        raise ValueError("sign_project needs a gradient refinement: refine_method='optax' or refine_steps")
    validate_refine(static)


FAMILIES = {
    "ours": Family(
        init=_init,
        update=buffer_update,
        estimate=_estimate,
        static_defaults={
            "magnitude": "mean",
            "refine": True,
            "refine_method": "closed_form",
            "refine_steps": None,
            "sign_project": False,
        },
        param_defaults={"v_tol": 1e-9, "magnitude_q": 1e-2, "magnitude_r": 1.0},
        validate=_validate,
    )
}
