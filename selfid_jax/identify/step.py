"""One self-ID sample: update (Eq. 6-12), initial guess (Eq. 13), refine (Eq. 14), record (Sec. IV-D).

:func:`sample_step` is the per-sample identification step every path runs:
Algorithm 1 after each random actuation
(:func:`selfid_jax.identify.algorithm.self_identify`), the batch closed form of
the recursive estimator (:func:`selfid_jax.identify.recursive.exact_step`),
self-ID from a recorded log (:func:`selfid_jax.robot.offline.fit_samples`) and
the online runner (:mod:`selfid_jax.robot.live`). Pure: it jits, vmaps and
differentiates; the per-sample diagnostics go out in a :class:`StepInfo`, not
into the state.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
from jax.typing import ArrayLike

from selfid_jax.identify import estimator
from selfid_jax.identify.refine import refine

__all__ = ["StepInfo", "sample_step"]


class StepInfo(NamedTuple):
    """Per-sample diagnostics of :func:`sample_step` (not carried forward)."""

    estimate: jax.Array  # (n, m) refined estimate J_t after the sample (Eq. 14)
    delta: jax.Array  # () ||J_t - J_{t-1}||_F, with J_0 = 0 (Sec. IV-D)
    threshold: jax.Array  # () eps + eps_rel ||J_t||_F: the bound delta is tested against
    accepted: jax.Array  # () bool: the estimator took the sample (not non-finite, all-zero or overflowing)


def sample_step(state: estimator.EstimatorState, dtheta: ArrayLike, V: ArrayLike, eps: ArrayLike,
                eps_rel: ArrayLike, *, method: str, options: tuple = (), min_count: ArrayLike = 0
                ) -> tuple[estimator.EstimatorState, StepInfo]:
    """One sample ``(dtheta (n,) actuator units, V (m,) task units)``: update, guess, refine, record.

    Update (Eq. 6-12), initial guess (Eq. 13), refinement (Eq. 14), record for the convergence test (Sec. IV-D).

    Returns the new state (its ``estimate (n, m)`` the refined ``J_t``) and a
    :class:`StepInfo`. ``method`` (``"closed_form"`` or ``"optax"``; see
    :data:`selfid_jax.identify.refine.METHODS`) and ``options`` (``(key,
    value)`` pairs of keyword options for
    :func:`~selfid_jax.identify.refine.refine`, sorted where they must hash,
    as a ``jit`` static argument) are static; ``eps`` (inverse-Jacobian units)
    and ``eps_rel`` (relative to ``||J_t||_F``) may be traced, and so may
    option values that :func:`~selfid_jax.identify.refine.refine` traces
    (``rcond``, ``ridge``) when ``sample_step`` is not jitted with ``options``
    static. A rejected sample (non-finite, all-zero) leaves the statistics
    as they were and is still recorded, as a record with no new data
    (:func:`selfid_jax.identify.estimator.record`). ``min_count`` (may be
    traced): convergence counts only from that many accepted samples on.
    """
    new = estimator.update(state, dtheta, V)
    J = refine(new, estimator.initial_guess(new), method=method, **dict(options))
    new = estimator.record(new, J, eps, eps_rel, min_count=min_count)
    return new, StepInfo(estimate=new.estimate, delta=new.last_deltas[1],
                         threshold=new.last_norms[1] * eps_rel + eps, accepted=new.count > state.count)
