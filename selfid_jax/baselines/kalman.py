"""Kalman filter on the elements of the inverse Jacobian.

``"kalman"``: the state is ``x = vec(J)`` (column-major, ``(n m,)``) with a
full covariance ``P (n m, n m)``; the model is a random walk observed through
the self-ID samples::

    x_k = x_{k-1} + w_k,                  w_k ~ N(0, q I)
    dtheta_k = H_k x_k + v_k,             v_k ~ N(0, r I_n),   H_k = V_k^T kron I_n  (n, n m)

since ``J V = (V^T kron I_n) vec(J)``. Each sample runs predict (``P += q I``)
and update (``S = H P H^T + r I``, ``K = P H^T S^-1`` by Cholesky solve,
``x += K (dtheta - J V)``, ``P`` by the Joseph form, symmetrised).

Traced parameters (defaults sized for self-ID in radians and metres):
  ``q``: process-noise variance per element per sample, (actuator/task)^2
    (default 0: a fixed Jacobian). ``q > 0`` lets the filter track a Jacobian
    that drifts as the configuration moves.
  ``r``: measurement-noise variance per actuator, actuator^2 (default 1e-6,
    i.e. 1 mrad).
  ``p0``: prior variance per element, (actuator/task)^2 (default 1e4); prior mean 0.
With ``q = 0`` the covariance stays ``Sigma kron I_n`` and the filter is RLS with
``lam = 1`` and ``P_rls = Sigma / r``: ``"rls"`` with ``delta V_1^T V_1 = r / p0``.
An update whose result is not finite (``r = 0`` with a singular ``S``) is
skipped. Cost per update ``O((n m)^2 n)``, memory ``(n m)^2``: 36 x 36 for a 6 x 6 Jacobian.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_factor, cho_solve

from selfid_jax.baselines.base import Family, keep_finite_gain


class KalmanState(NamedTuple):
    J: jax.Array  # (n, m) float: posterior mean of the inverse Jacobian (x = vec(J), column-major)
    P: jax.Array  # (n m, n m) float: posterior covariance of vec(J), (actuator/task)^2
    count: jax.Array  # () int32: accepted samples
    rejected: jax.Array  # () int32: rejected samples
    params: dict  # {"q": (), "r": (), "p0": ()}

    @property
    def shape_ref(self) -> jax.Array:
        return self.J


def vec(J):
    """Column-major ``vec(J)`` ``(n m,)`` of ``J (n, m)``."""
    return J.T.reshape(-1)


def unvec(x, n: int, m: int):
    """Inverse of :func:`vec`: ``(n m,) -> (n, m)``."""
    return x.reshape(m, n).T


def kalman_step(J, P, dtheta, V, q, r):
    """One predict + update of the element-wise Kalman filter; returns ``(J, P)``."""
    n, m = J.shape
    dtype = J.dtype
    eye_nm = jnp.eye(n * m, dtype=dtype)
    H = jnp.kron(V[None, :], jnp.eye(n, dtype=dtype))  # (n, n m)
    P = P + q * eye_nm
    PHt = P @ H.T  # (n m, n)
    S = H @ PHt + r * jnp.eye(n, dtype=dtype)
    S = 0.5 * (S + S.T)
    c = cho_factor(S, lower=True)
    K = cho_solve(c, PHt.T).T  # (n m, n)
    e = dtheta - J @ V
    x = vec(J) + K @ e
    A = eye_nm - K @ H
    P = A @ P @ A.T + r * (K @ K.T)  # Joseph form: stays symmetric positive semi-definite
    return unvec(x, n, m), 0.5 * (P + P.T)


def _init(n, m, key, capacity, dtype, static, params):
    return KalmanState(
        J=jnp.zeros((n, m), dtype),
        P=params["p0"] * jnp.eye(n * m, dtype=dtype),
        count=jnp.zeros((), jnp.int32),
        rejected=jnp.zeros((), jnp.int32),
        params=params,
    )


def _update(state, dtheta, V, static):
    J, P = kalman_step(state.J, state.P, dtheta, V, state.params["q"], state.params["r"])
    # r = 0 with a singular innovation covariance would fail the Cholesky: keep the old state then.
    return keep_finite_gain(state, J, P)


def _estimate(state, truth, static):
    return state.J


FAMILIES = {
    "kalman": Family(
        init=_init,
        update=_update,
        estimate=_estimate,
        static_defaults={},
        param_defaults={"q": 0.0, "r": 1e-6, "p0": 1e4},
    )
}
