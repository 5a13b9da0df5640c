"""Oracle baselines of Sec. V-A that read the true inverse Jacobian.

``"sign_true_mag"``: the estimated signed inverse Jacobian (Eq. 6-10) times the
true element magnitudes, ``signed(state) * |truth|`` ``(n, m)``: isolates the
sign estimate. ``"true"``: ``truth`` itself, the upper bound of the ablation.
Neither has options; both count accepted and rejected samples like every method.
"""

from __future__ import annotations

import jax.numpy as jnp

from selfid_jax import estimator
from selfid_jax.baselines.base import Family
from selfid_jax.baselines.ours import buffer_init, buffer_update


def _init(n, m, key, capacity, dtype, static, params):
    # Only the sign weights are read: a one-row buffer is enough.
    return buffer_init(n, m, 1, dtype, params)


def _sign_true_mag(state, truth, static):
    return estimator.signed_inverse_jacobian(state.est) * jnp.abs(truth)


def _true_update(state, dtheta, V, static):
    return state


def _true(state, truth, static):
    return truth


FAMILIES = {
    "sign_true_mag": Family(
        init=_init, update=buffer_update, estimate=_sign_true_mag, static_defaults={}, param_defaults={"v_tol": 1e-9}
    ),
    "true": Family(init=_init, update=_true_update, estimate=_true, static_defaults={}, param_defaults={}),
}
