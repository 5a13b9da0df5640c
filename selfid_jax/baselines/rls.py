"""Recursive least squares with forgetting on ``dtheta = J V``.

``"rls"``: each row of ``J (n, m)`` is a linear regression on the regressor
``V (m,)``; all rows share one covariance ``P (m, m)``. Per sample::

    k = P V / (lam + V^T P V)              (m,)   gain
    J <- J + (dtheta - J V) k^T            (n, m)
    P <- (P - k V^T P) / lam               (m, m), symmetrised

After ``K`` samples this is exactly the minimiser of
``sum_k lam^(K-k) ||dtheta_k - J V_k||^2 + lam^K delta_0 ||J||_F^2`` (weighted,
ridge-regularised Eq. 14 from ``J = 0``), with ``P_0 = I / delta_0``.

Traced parameters:
  ``lam``: forgetting factor in ``(0, 1]`` (default 1: no forgetting). With
    ``lam < 1`` directions of ``V`` that stop being excited inflate ``P`` by
    ``1/lam`` per sample (covariance wind-up); random self-ID excites all of them.
  ``delta``: relative regularisation (default 1e-9, dimensionless). ``P_0`` is
    set at the first accepted sample to ``I / (delta V_1^T V_1)``, so the ridge
    ``delta_0 = delta |V_1|^2`` follows the data's scale (metres or millimetres
    alike). Noise-free, the bias is about ``delta_0 / lambda_min(sum V V^T)``
    relative, and ``delta -> 0`` gives exact least squares once ``>= m``
    independent samples arrived; in float64 the cancellation in the first ``P``
    update costs about ``eps / delta`` relative, hence the default 1e-9. In
    float32 use ``delta`` around 1e-4.
An update whose result is not finite (``lam`` outside ``(0, 1]``, wind-up past
the float range) is skipped.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from selfid_jax.baselines.base import Family, keep_finite_gain


class RLSState(NamedTuple):
    J: jax.Array  # (n, m) float: estimate, actuator per task unit
    P: jax.Array  # (m, m) float: shared covariance (per unit measurement variance), task units^-2
    count: jax.Array  # () int32: accepted samples
    rejected: jax.Array  # () int32: rejected samples
    params: dict  # {"lam": (), "delta": ()}

    @property
    def shape_ref(self) -> jax.Array:
        return self.J


def first_covariance(V, delta, m: int, dtype):
    """``P_0 = I / (delta V^T V)`` ``(m, m)``, the data-scaled prior covariance (floored, never inf)."""
    scale = jnp.maximum(delta * jnp.sum(V * V), jnp.finfo(dtype).tiny)
    return jnp.eye(m, dtype=dtype) / scale


def rls_step(J, P, dtheta, V, lam):
    """One RLS update of ``J (n, m)``, ``P (m, m)`` with forgetting ``lam``; returns ``(J, P)``."""
    PV = P @ V
    k = PV / (lam + V @ PV)
    e = dtheta - J @ V
    J = J + e[:, None] * k[None, :]
    P = (P - k[:, None] * PV[None, :]) / lam
    return J, 0.5 * (P + P.T)


def _init(n, m, key, capacity, dtype, static, params):
    return RLSState(
        J=jnp.zeros((n, m), dtype),
        P=jnp.eye(m, dtype=dtype),  # replaced by the data-scaled P_0 at the first sample
        count=jnp.zeros((), jnp.int32),
        rejected=jnp.zeros((), jnp.int32),
        params=params,
    )


def _update(state, dtheta, V, static):
    m = V.shape[0]
    P = jnp.where(state.count == 0, first_covariance(V, state.params["delta"], m, V.dtype), state.P)
    J, P = rls_step(state.J, P, dtheta, V, state.params["lam"])
    # lam outside (0, 1] or covariance wind-up past the float range: keep the old state.
    return keep_finite_gain(state, J, P)


def _estimate(state, truth, static):
    return state.J


FAMILIES = {
    "rls": Family(
        init=_init,
        update=_update,
        estimate=_estimate,
        static_defaults={},
        param_defaults={"lam": 1.0, "delta": 1e-9},
    )
}
