"""Oracle baselines of Sec. V-A that read the true inverse Jacobian.

:func:`sign_true_mag`: the estimated signed inverse Jacobian (Eq. 6-10) times
the true element magnitudes, isolating the sign estimate. :func:`true`: the
true inverse Jacobian itself, the upper bound of the ablation. Both keep an
:class:`~selfid_jax.identify.estimator.EstimatorState` without a sample buffer (only the
sign weights and the counters are read) and count accepted and rejected
samples like every method.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.typing import ArrayLike

from selfid_jax.baselines.base import Estimator, assemble, check_number
from selfid_jax.identify import estimator


def _init_for(v_tol):
    def init(n, m, key, capacity, dtype):
        # Only the sign weights are read: no sample buffer, whatever `capacity` is.
        return estimator.init(n, m, capacity=0, v_tol=v_tol, dtype=dtype)

    return init


def sign_true_mag(*, v_tol: ArrayLike = 1e-9) -> Estimator:
    """Sign x true magnitude: ``signed(state) * |truth|`` ``(n, m)`` (Eq. 6-10 with the true Eq. 12).

    State: an :class:`~selfid_jax.identify.estimator.EstimatorState` (no sample buffer).

    Args:
      v_tol: task units; the estimator's Eq. 11 threshold. It does not change
        this method's estimate (only the sign weights are read; kept for
        configurations that set it).
    """
    check_number("sign_true_mag", "v_tol", v_tol)

    def read(state, truth):
        return estimator.signed_inverse_jacobian(state) * jnp.abs(truth)

    return assemble("sign_true_mag", init=_init_for(v_tol), fold=estimator.accumulate, read=read,
                    ref=lambda s: s.sign_net)


def true() -> Estimator:
    """The true inverse Jacobian ``truth (n, m)`` itself, whatever the samples; the ablation's upper bound.

    State: an :class:`~selfid_jax.identify.estimator.EstimatorState` (no sample buffer)
    that only counts samples.
    """
    return assemble("true", init=_init_for(1e-9), fold=lambda state, dtheta, V: state,
                    read=lambda state, truth: truth, ref=lambda s: s.sign_net)
