"""Recursive least squares and a Kalman filter on ``dtheta = J V``: the linear-Gaussian baselines.

:func:`rls`: each row of ``J (n, m)`` is a linear regression on the regressor
``V (m,)``; all rows share one covariance ``P (m, m)``. Per sample::

    k = P V / (lam + V^T P V)              (m,)   gain
    J <- J + (dtheta - J V) k^T            (n, m)
    P <- (P - k V^T P) / lam               (m, m), symmetrised

After ``K`` samples this is exactly the minimiser of
``sum_k lam^(K-k) ||dtheta_k - J V_k||^2 + lam^K delta_0 ||J||_F^2`` (weighted,
ridge-regularised Eq. 14 from ``J = 0``), with ``P_0 = I / delta_0``.

:func:`kalman`: the state is ``x = vec(J)`` (column-major, ``(n m,)``) with a
full covariance ``P (n m, n m)``; the model is a random walk observed through
the self-ID samples::

    x_k = x_{k-1} + w_k,                  w_k ~ N(0, q I)
    dtheta_k = H_k x_k + v_k,             v_k ~ N(0, r I_n),   H_k = V_k^T kron I_n  (n, n m)

since ``J V = (V^T kron I_n) vec(J)``. Each sample runs predict (``P += q I``)
and update (``S = H P H^T + r I``, ``K = P H^T S^-1`` by Cholesky solve,
``x += K (dtheta - J V)``, ``P`` by the Joseph form, symmetrised). With
``q = 0`` the covariance stays ``Sigma kron I_n`` and the filter is RLS with
``lam = 1`` and ``P_rls = Sigma / r``: :func:`rls` with ``delta V_1^T V_1 = r / p0``.

An update of either whose result is not finite (RLS: ``lam`` outside
``(0, 1]``, covariance wind-up past the float range; Kalman: ``r = 0`` with a
singular ``S``) is skipped (:func:`keep_finite_gain`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_factor, cho_solve
from jax.typing import ArrayLike

from selfid_jax.baselines.base import Estimator, assemble, check_number


class RLSState(NamedTuple):
    """State of :func:`rls`."""

    J: jax.Array  # (n, m) float: estimate, actuator per task unit
    P: jax.Array  # (m, m) float: shared covariance (per unit measurement variance), task units^-2
    # () int32: accepted samples (P is replaced by the data-scaled P_0 while 0)
    count: jax.Array  # type: ignore[assignment]  # shadows tuple.count
    rejected: jax.Array  # () int32: rejected samples


class KalmanState(NamedTuple):
    """State of :func:`kalman`."""

    J: jax.Array  # (n, m) float: posterior mean of the inverse Jacobian (x = vec(J), column-major)
    P: jax.Array  # (n m, n m) float: posterior covariance of vec(J), (actuator/task)^2
    count: jax.Array  # type: ignore[assignment]  # () int32: accepted samples
    rejected: jax.Array  # () int32: rejected samples


def keep_finite_gain(state, J, P):
    """``state`` with the filter update ``(J, P)`` if both are finite, else unchanged (RLS and Kalman)."""
    good = jnp.all(jnp.isfinite(J)) & jnp.all(jnp.isfinite(P))
    return state._replace(J=jnp.where(good, J, state.J), P=jnp.where(good, P, state.P))


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


def rls(*, lam: ArrayLike = 1.0, delta: ArrayLike = 1e-9) -> Estimator:
    """Recursive least squares with forgetting: the weighted, ridge-regularised Eq. 14 solution ``J (n, m)``.

    State: :class:`RLSState`. Cost per update ``O(n m + m^2)``.

    Args:
      lam: forgetting factor in ``(0, 1]``, dimensionless (1: no forgetting).
        With ``lam < 1`` directions of ``V`` that stop being excited inflate
        ``P`` by ``1/lam`` per sample (covariance wind-up); random self-ID
        excites all of them. May be traced.
      delta: relative regularisation, dimensionless. ``P_0`` is set at the
        first accepted sample to ``I / (delta V_1^T V_1)``, so the ridge
        ``delta_0 = delta |V_1|^2`` follows the data's scale (metres or
        millimetres alike). Noise-free, the bias is about
        ``delta_0 / lambda_min(sum V V^T)`` relative, and ``delta -> 0`` gives
        exact least squares once ``>= m`` independent samples arrived; in
        float64 the cancellation in the first ``P`` update costs about
        ``eps / delta`` relative, hence the default 1e-9. In float32 use
        ``delta`` around 1e-4. May be traced.
    """
    name = "rls"
    check_number(name, "lam", lam)
    check_number(name, "delta", delta)

    def init(n, m, key, capacity, dtype):
        return RLSState(
            J=jnp.zeros((n, m), dtype),
            P=jnp.eye(m, dtype=dtype),  # replaced by the data-scaled P_0 at the first sample
            count=jnp.zeros((), jnp.int32),
            rejected=jnp.zeros((), jnp.int32),
        )

    def fold(state: RLSState, dtheta, V):
        dtype = state.J.dtype
        m = V.shape[0]
        P0 = first_covariance(V, jnp.asarray(delta, dtype), m, dtype)
        P = jnp.where(state.count == 0, P0, state.P)
        J, P = rls_step(state.J, P, dtheta, V, jnp.asarray(lam, dtype))
        return keep_finite_gain(state, J, P)

    return assemble(name, init=init, fold=fold, read=lambda state, truth: state.J, ref=lambda s: s.J)


def kalman(*, q: ArrayLike = 0.0, r: ArrayLike = 1e-6, p0: ArrayLike = 1e4) -> Estimator:
    """Kalman filter on ``vec(J)``: the posterior mean ``J (n, m)`` of a random walk observed by ``dtheta = J V``.

    State: :class:`KalmanState`. Cost per update ``O((n m)^2 n)``, memory
    ``(n m)^2``: 36 x 36 for a 6 x 6 Jacobian. Defaults are sized for self-ID
    in radians and metres.

    Args:
      q: process-noise variance per element per sample, (actuator/task)^2
        (0: a fixed Jacobian). ``q > 0`` lets the filter track a Jacobian that
        drifts as the configuration moves. May be traced.
      r: measurement-noise variance per actuator, actuator^2 (1e-6: 1 mrad).
        May be traced.
      p0: prior variance per element, (actuator/task)^2; prior mean 0. May be traced.
    """
    name = "kalman"
    for option, value in (("q", q), ("r", r), ("p0", p0)):
        check_number(name, option, value)

    def init(n, m, key, capacity, dtype):
        return KalmanState(
            J=jnp.zeros((n, m), dtype),
            P=jnp.asarray(p0, dtype) * jnp.eye(n * m, dtype=dtype),
            count=jnp.zeros((), jnp.int32),
            rejected=jnp.zeros((), jnp.int32),
        )

    def fold(state: KalmanState, dtheta, V):
        dtype = state.J.dtype
        J, P = kalman_step(state.J, state.P, dtheta, V, jnp.asarray(q, dtype), jnp.asarray(r, dtype))
        return keep_finite_gain(state, J, P)

    return assemble(name, init=init, fold=fold, read=lambda state, truth: state.J, ref=lambda s: s.J)
