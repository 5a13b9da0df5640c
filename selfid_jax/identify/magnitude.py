"""Variants of the magnitude inverse Jacobian (Eq. 11-12) for the estimation ablation.

Every function maps an :class:`~selfid_jax.identify.estimator.EstimatorState` to an
``(n, m)`` array of element magnitudes ``|Jinv_ij|`` in actuator units per task
unit, built from the ratios ``r_kij = |dtheta_ki / V_kj|`` (Eq. 11) of the
samples ``k`` that may enter column ``j`` (``|V_kj| > v_tol``):

* :func:`mean`: the paper's mean over every sample seen (Eq. 12);
* :func:`median`: elementwise median (robust to the heavy tail of the ratio
  when ``V_kj`` is near zero);
* :func:`weighted`: mean weighted by the sign weights ``w_theta_i w_V_j``
  (Eq. 7-8), which shrink exactly the samples with a small ``|V_kj|``;
* :func:`kalman`: a scalar Kalman filter per element over the ratios, in sample
  order (the "Kalman magnitude" the paper names as future work, Sec. VI).

``mean`` reads the running sums and so covers every accepted sample (weighted
by the estimator's forgetting factor); the other three read the ring buffer and
so cover the last ``capacity`` samples only (all of them when ``capacity`` >=
the number of iterations), unweighted; they raise ``ValueError`` for a state
without a buffer (``capacity=0``). An element without any usable ratio is 0.
All are NaN-free on empty states and degenerate samples, and jit and vmap (no
Python control flow on values).
"""

from __future__ import annotations

from typing import Literal

import jax
import jax.numpy as jnp

from selfid_jax.identify import estimator
from selfid_jax.identify.estimator import EstimatorState
from selfid_jax.math.kernels import sort_axis0

Variant = Literal["mean", "median", "weighted", "kalman"]
VARIANTS: tuple[Variant, ...] = ("mean", "median", "weighted", "kalman")
BUFFERED = ("median", "weighted", "kalman")
"""The variants that read the ring buffer (need ``capacity > 0``)."""


def _need_buffer(state: EstimatorState, name: str) -> None:
    if estimator.sizes(state)[2] == 0:
        raise ValueError(f"magnitude {name!r} reads the sample buffer, but the state has none (capacity=0): "
                         "init the estimator with capacity > 0, or use magnitude 'mean'")


def ratios(state: EstimatorState) -> tuple[jax.Array, jax.Array]:
    """Buffered ratios ``r (K, n, m) = |dtheta_ki / V_kj|`` (Eq. 11) and their validity ``(K, n, m)`` bool.

    ``K`` is the buffer capacity; row ``k`` is valid for column ``j`` iff it holds
    a sample and ``|V_kj| > v_tol``. Invalid entries of ``r`` are 0.
    """
    theta, V, mask = estimator.samples(state)
    n = theta.shape[-1]
    big = mask[:, None] & (jnp.abs(V) > state.v_tol)  # (K, m)
    safe_v = jnp.where(big, V, 1.0)
    r = jnp.abs(theta[:, :, None] / safe_v[:, None, :])
    valid = jnp.broadcast_to(big[:, None, :], (big.shape[0], n, big.shape[1]))
    return jnp.where(valid, r, 0.0), valid


def mean(state: EstimatorState) -> jax.Array:
    """Mean ratio ``(n, m)`` over all accepted samples: the paper's Eq. 12
    (= ``estimator.magnitude_inverse_jacobian``)."""
    return estimator.magnitude_inverse_jacobian(state)


def median(state: EstimatorState) -> jax.Array:
    """Elementwise median ``(n, m)`` of the buffered ratios ``|dtheta_ki / V_kj|`` with ``|V_kj| > v_tol``.

    Invalid entries are set to ``+inf`` and sorted to the end; with ``c`` valid
    entries the median is entry ``(c - 1) // 2`` of the sorted column (odd ``c``)
    or the mean of entries ``c/2 - 1`` and ``c/2`` (even ``c``), as ``np.median``.
    0 where ``c = 0``.
    """
    _need_buffer(state, "median")
    r, valid = ratios(state)
    srt = sort_axis0(jnp.where(valid, r, jnp.inf))  # (K, n, m)
    c = jnp.sum(valid, axis=0)  # (n, m) int
    lo = jnp.clip((c - 1) // 2, 0, None)
    hi = jnp.clip(c // 2, 0, srt.shape[0] - 1)
    a = jnp.take_along_axis(srt, lo[None], axis=0)[0]
    b = jnp.take_along_axis(srt, hi[None], axis=0)[0]
    med = jnp.where(c % 2 == 1, a, 0.5 * (a + b))
    return jnp.where(c > 0, med, 0.0)


def weighted(state: EstimatorState) -> jax.Array:
    """Weighted mean ``(n, m)`` of the buffered ratios with weights ``w_theta_i w_V_j`` (Eq. 7-8).

    ``m_ij = sum_k w_kij r_kij / sum_k w_kij`` over samples with ``|V_kj| > v_tol``,
    ``w_kij = (|dtheta_ki| / sum|dtheta_k|) (|V_kj| / sum|V_k|)``. A small
    ``|V_kj|``, which makes the ratio large and unreliable, gets a small weight.
    0 where the weights sum to 0 (no valid sample, or ``dtheta_i = 0`` in all).
    """
    _need_buffer(state, "weighted")
    theta, V, _ = estimator.samples(state)
    r, valid = ratios(state)
    _, w = jax.vmap(estimator.sample_contribution)(theta, V)  # (K, n, m); zero rows give zero weight
    w = jnp.where(valid, w, 0.0)
    wsum = jnp.sum(w, axis=0)
    return jnp.where(wsum > 0, jnp.sum(w * r, axis=0) / jnp.where(wsum > 0, wsum, 1.0), 0.0)


def _kalman_step(carry, z, ok, q, r):
    """One scalar Kalman step per element; ``carry = (x, P, started)``, all ``(n, m)``."""
    x, P, started = carry
    # Predict: random walk with variance q * x^2 (relative to the running estimate).
    P_pred = P + q * x**2
    R = r * x**2
    denom = P_pred + R
    # x = 0 with P = 0 (a first ratio of 0) carries no information: take the measurement.
    K = jnp.where(denom > 0, P_pred / jnp.where(denom > 0, denom, 1.0), 1.0)
    x_upd = x + K * (z - x)
    P_upd = (1.0 - K) * P_pred
    # First valid ratio initialises the filter: x = z with the variance of one measurement.
    x_new = jnp.where(started, x_upd, z)
    P_new = jnp.where(started, P_upd, r * z**2)
    return (
        jnp.where(ok, x_new, x),
        jnp.where(ok, P_new, P),
        started | ok,
    )


def kalman(state: EstimatorState, *, q=1e-2, r=1.0) -> jax.Array:
    """Scalar Kalman filter ``(n, m)`` per element over the buffered ratios, oldest first (``lax.scan``).

    Model, per element ``(i, j)``: the magnitude ``x = |Jinv_ij|`` follows a
    random walk ``x_k = x_{k-1} + w_k``, and each valid ratio is a measurement
    ``z_k = |dtheta_ki / V_kj| = x_k + v_k``. Both noise variances are relative to
    the running estimate ``x_hat`` (the ratio's spread scales with the element):
    ``Var w_k = q x_hat^2``, ``Var v_k = r x_hat^2``; ``q`` and ``r`` are
    dimensionless and may be traced. The first valid ratio sets ``x_hat = z_1``,
    ``P = r z_1^2``; each later valid ratio runs predict (``P += q x_hat^2``)
    and update (``K = P / (P + r x_hat^2)``, ``x_hat += K (z - x_hat)``,
    ``P = (1 - K) P``). Invalid rows (empty buffer slots, ``|V_kj| <= v_tol``)
    are skipped, process noise included. 0 where no valid ratio. Larger ``q / r``
    tracks recent samples faster; ``q = 0`` averages with decreasing gains.
    """
    _need_buffer(state, "kalman")
    r_k, valid = ratios(state)
    capacity = r_k.shape[0]
    # Ring buffer order: once full, the oldest sample sits at count % capacity.
    start = jnp.where(state.count > capacity, state.count % capacity, 0)
    order = (start + jnp.arange(capacity)) % capacity
    dtype = r_k.dtype
    q = jnp.asarray(q, dtype)
    r = jnp.asarray(r, dtype)
    zeros = jnp.zeros(r_k.shape[1:], dtype)
    carry0 = (zeros, zeros, jnp.zeros(r_k.shape[1:], bool))

    def body(carry, k):
        return _kalman_step(carry, r_k[k], valid[k], q, r), None

    (x, _, _), _ = jax.lax.scan(body, carry0, order)
    return x


def get(name: str):
    """The magnitude function called ``name`` (one of :data:`VARIANTS`)."""
    funcs = {"mean": mean, "median": median, "weighted": weighted, "kalman": kalman}
    if name not in funcs:
        raise ValueError(f"magnitude: expected one of {VARIANTS}, got {name!r}")
    return funcs[name]
