"""Refinement of an inverse-Jacobian guess on self-ID samples (Eq. 14).

``argmin_J sum_k w_k rho(dtheta_k - J V_k) + ridge * ||J - J0||_F^2`` starting
from ``J0``, where ``rho`` is the squared L2 norm (the paper) or a Huber loss
and ``w_k = forget^(K - k)`` (all 1 without forgetting).

The L2 loss depends on the samples only through the statistics the estimator
keeps, ``S_vv = sum w_k V_k V_k^T`` and ``S_tv = sum w_k dtheta_k V_k^T``, so
its refinements cover every accepted sample in constant memory; the Huber
loss and SLSQP need the samples and read the estimator's ring buffer.

Three methods:

* ``"closed_form"``: the minimum-norm correction ``J0 + (Theta - J0 V) pinv(V)``
  (``Theta (n, K)``, ``V (m, K)`` the samples as columns), which, because
  ``pinv(V) = V^T pinv(V V^T)``, is
  ``J0 + (S_tv - J0 S_vv) pinv(S_vv) = S_tv pinv(S_vv) + J0 N`` with ``N`` the
  orthogonal projector onto the null space of ``S_vv``
  (:func:`statistics_closed_form`, :func:`psd_pinv`): ``S_tv S_vv^-1`` once the
  samples span the task space, ``J0`` filling only the directions no sample
  has excited yet. For ``ridge > 0`` the exact ridge solution
  ``(S_tv + ridge J0) (S_vv + ridge I)^-1``. Gradient descent on the L2 loss
  keeps its iterates in ``J0 + A V^T``, so this is also the exact limit of
  gradient descent from ``J0``, with fewer samples than task dimensions too.
  :func:`closed_form` is the same formula on explicit samples (the buffered
  reference).
* ``"optax"``: gradient descent with optax, preconditioned on the right by
  ``(V V^T + ridge I)^-1`` (or, for the sign projection, Nesterov descent with
  step ``1/L`` from the largest eigenvalue of ``V V^T``); supports the Huber
  loss (on the buffer), the ridge term and a projection onto the signs of the
  signed inverse Jacobian. Both keep iterates in ``J0 + A V^T`` and so reach
  the minimum-norm solution; per-element scaled optimizers (Adam & co.) would
  leave that space and are not used. See :func:`gradient_refine`.
* ``"slsqp"``: scipy's SLSQP as in the paper, on the buffered samples; eager
  only, the reference for tests and benchmarks.

With no samples every method returns ``J0``.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.typing import ArrayLike

from selfid_jax.identify.estimator import EstimatorState, samples, signed_inverse_jacobian, sizes
from selfid_jax.math import native
from selfid_jax.math.checks import check_array, check_scalar, is_traced
from selfid_jax.math.kernels import small_matmul
from selfid_jax.math.linalg import _ldl_null_space, _spd_right_solve, default_rcond, psd_pinv  # noqa: F401

METHODS = ("closed_form", "optax", "slsqp")
LOSSES = ("l2", "huber")


def _masked(state: EstimatorState):
    theta, V, mask = samples(state)
    w = mask.astype(theta.dtype)[:, None]
    return theta * w, V * w, mask


def refine_objective(J, theta, V, J0, *, loss: str = "l2", huber_delta=1.0, ridge=0.0):
    """Eq. 14 objective of ``J (n, m)`` on samples ``theta (K, n)``, ``V (K, m)`` (zero rows ignored).

    ``loss="l2"``: ``sum ||theta_k - J V_k||^2``; ``"huber"``: ``sum 2 huber(r, delta)``
    elementwise (equal to L2 where ``|r| <= delta``). Plus ``ridge ||J - J0||_F^2``.
    """
    r = theta - V @ J.T
    if loss == "l2":
        data = jnp.sum(r**2)
    else:
        data = 2.0 * jnp.sum(optax.losses.huber_loss(r, delta=huber_delta))
    return data + ridge * jnp.sum((J - J0) ** 2)


def closed_form(theta, V, J0, *, ridge=0.0):
    """Minimum-norm least-squares correction of ``J0 (n, m)`` on ``theta (K, n)``, ``V (K, m)``.

    ``ridge = 0``: ``J0 + R pinv(V^T)`` with residual ``R = theta^T - J0 V^T``.
    ``ridge > 0``: ``J0 + R V (V^T V + ridge I)^-1``, the exact ridge solution.
    ``ridge`` may be traced; a literal 0 skips the ridge branch.

    Computed in the Gram form, :func:`statistics_closed_form` of ``V^T V (m,
    m)`` and ``theta^T V (n, m)`` (``pinv(V^T) = V pinv(V^T V)``): an
    ``m x m`` factorisation with no library call, where ``pinv(V^T)`` was an
    SVD of the ``m x K`` buffer per estimator (on a GPU, cuSOLVER loops over
    the batch for a ``3 x 64`` matrix; ``tests/test_cuda_lowering.py``).
    """
    return statistics_closed_form(V.T @ V, theta.T @ V, J0, ridge=ridge)


def statistics_closed_form(S_vv, S_tv, J0, *, ridge=0.0, rcond=None):
    """Eq. 14 in closed form from the sufficient statistics: ``(n, m)``.

    ``S_vv (m, m) = sum V V^T``, ``S_tv (n, m) = sum dtheta V^T`` (over every
    sample, possibly forgetting-weighted), ``J0 (n, m)`` the initial guess.
    ``ridge = 0``: the minimum-norm correction of ``J0``,
    ``J0 + (S_tv - J0 S_vv) pinv(S_vv)``, which is ``S_tv P + J0 N`` with
    ``(P, N) = psd_pinv(S_vv)``, computed without forming ``P`` (see the code)
    so that a large ``J0`` does not cancel against itself (in float32,
    ``J0 - J0 S_vv S_vv^-1`` leaves errors of ``eps |J0| cond(S_vv)``); equal to :func:`closed_form` on the samples
    themselves, and
    to ``S_tv S_vv^-1`` whatever ``J0`` is once ``S_vv`` has full rank.
    ``ridge > 0``: ``(S_tv + ridge J0) (S_vv + ridge I)^-1``, the exact ridge
    solution. ``ridge`` and ``rcond`` may be traced; a literal 0 skips the
    ridge branch.
    """
    S_vv, S_tv, J0 = jnp.asarray(S_vv), jnp.asarray(S_tv), jnp.asarray(J0)
    m = S_vv.shape[-1]
    dtype = jnp.result_type(S_vv, S_tv, J0)
    rcond = jnp.asarray(default_rcond(m, dtype) if rcond is None else rcond, dtype)
    # the native CPU kernel where it is built (selfid_jax.math.native); _minimum_norm_correction elsewhere
    J = native.call("closed_form", _minimum_norm_correction, S_vv, S_tv, J0, rcond)
    if isinstance(ridge, (int, float)) and ridge == 0:
        return J
    ridge = jnp.asarray(ridge, S_vv.dtype)
    safe = jnp.where(ridge > 0, ridge, 1.0)
    ridged = jnp.linalg.solve(S_vv + safe * jnp.eye(m, dtype=S_vv.dtype), (S_tv + safe * J0).T).T
    return jnp.where(ridge > 0, ridged, J)


def _minimum_norm_correction(S_vv, S_tv, J0, rcond):
    """``S_tv P + J0 N`` with ``(P, N) = psd_pinv(S_vv, rcond=rcond)``: :func:`statistics_closed_form` with ridge 0."""
    m = S_vv.shape[-1]
    _, _, N = _ldl_null_space(S_vv, rcond)
    # S P = I - N and N S = 0 give (S / c + N)^-1 = c P + N, so that
    # (S_tv / c + (J0 - S_tv / c) N) (S / c + N)^-1 = S_tv P + J0 N with one
    # solve of a positive definite matrix (c = tr(S) / m sets the scale of N) and no P formed.
    tr = sum((S_vv[k, k] for k in range(1, m)), S_vv[0, 0])
    inv_c = 1.0 / jnp.where(tr > 0, tr / m, 1.0)
    T = S_tv * inv_c
    return _spd_right_solve(T + small_matmul(J0 - T, N), S_vv * inv_c + N)


def _project(J, S, sign_project: bool):
    return jnp.where(S * J < 0, 0.0, J) if sign_project else J


def gradient_refine(
    theta,
    V,
    J0,
    S=None,
    *,
    steps: int = 100,
    tol: float | None = None,
    loss: str = "l2",
    huber_delta=1.0,
    ridge=0.0,
    sign_project: bool = False,
    precondition: bool | None = None,
):
    """Gradient descent with optax on :func:`refine_objective` from ``J0 (n, m)``, on samples ``theta (K, n)``,
    ``V (K, m)``.

    ``precondition=True`` (default without ``sign_project``): each gradient
    ``G (n, m)`` is right-multiplied by ``P = (V^T V + ridge I)^+`` restricted to
    the range of ``V^T V`` (eigenvalues below the ``pinv`` rank tolerance count
    as zero) and plain SGD steps with learning rate 1/2. ``G P`` stays in the
    row space of ``V`` like ``G``, so iterates stay in ``J0 + A V`` and converge to
    the minimum-norm solution; for the L2 loss the first step is already the
    Gauss-Newton solution, and the Huber loss (curvature below L2's) descends
    monotonically. Random self-ID data can make ``V^T V`` very ill-conditioned
    (condition numbers of 1e4-1e6 on random 6x6 systems), which the
    unpreconditioned method below needs thousands of steps for.

    ``precondition=False`` (default with ``sign_project``): Nesterov gradient
    descent, step ``1/L`` with ``L = 2 (lambda_max(V^T V) + ridge)`` and momentum
    ``(sqrt(k) - 1) / (sqrt(k) + 1)``, ``k`` the condition number on the range of
    ``V``. With ``sign_project`` every iterate is projected onto the sign pattern
    ``S (n, m)`` (wrong-sign elements set to 0), a Euclidean projection, which is
    why it uses this unpreconditioned metric.

    ``steps`` is a static iteration count; with ``tol`` the loop stops early once
    ``||grad||_F <= tol`` (a ``while_loop``: not reverse-differentiable; leave
    ``tol=None`` to differentiate through the refinement).
    :func:`statistics_gradient_refine` is the same descent for the L2 loss
    from ``S_vv = V^T V`` and ``S_tv = theta^T V``.
    """

    def loss_fn(J):
        return refine_objective(J, theta, V, J0, loss=loss, huber_delta=huber_delta, ridge=ridge)

    return _descend(loss_fn, V.T @ V, J0, S, steps=steps, tol=tol, ridge=ridge, sign_project=sign_project,
                    precondition=precondition)


def statistics_gradient_refine(
    S_vv,
    S_tv,
    J0,
    S=None,
    *,
    steps: int = 100,
    tol: float | None = None,
    ridge=0.0,
    sign_project: bool = False,
    precondition: bool | None = None,
):
    """:func:`gradient_refine` for the L2 loss from the statistics ``S_vv (m, m)``, ``S_tv (n, m)``: ``(n, m)``.

    The objective ``sum ||dtheta_k - J V_k||^2 + ridge ||J - J0||_F^2`` is
    ``s_tt - 2 <J, S_tv> + <J S_vv, J> + ridge ||J - J0||_F^2``; its gradient
    ``-2 (S_tv - J S_vv) + 2 ridge (J - J0)`` needs no samples, and the constant
    ``s_tt`` does not enter the descent.
    """

    def loss_fn(J):
        return -2.0 * jnp.sum(J * S_tv) + jnp.sum((J @ S_vv) * J) + ridge * jnp.sum((J - J0) ** 2)

    return _descend(loss_fn, S_vv, J0, S, steps=steps, tol=tol, ridge=ridge, sign_project=sign_project,
                    precondition=precondition)


def _descend(loss_fn, gram, J0, S, *, steps, tol, ridge, sign_project, precondition):
    """The descent of :func:`gradient_refine` on ``loss_fn(J)`` with the Gram matrix ``gram (m, m)`` of the samples."""
    if precondition is None:
        precondition = not sign_project
    dtype = gram.dtype
    m = gram.shape[0]
    ridge = jnp.asarray(ridge, dtype)
    eig, U = jnp.linalg.eigh(gram)
    lam_max = eig[-1]
    has_data = lam_max > 0
    if precondition:
        # A pseudo-inverse rather than a damped inverse: damping a rank-deficient
        # gram amplifies round-off in its null space, pushing iterates off J0 + A V.
        rank_tol = 10.0 * m * jnp.finfo(dtype).eps * lam_max
        inv_eig = jnp.where(eig > rank_tol, 1.0 / jnp.where(eig > rank_tol, eig + ridge, 1.0), 0.0)
        precond = (U * inv_eig[None, :]) @ U.T

        def direction(g):
            return g @ precond

        opt = optax.sgd(learning_rate=0.5)
    else:
        nonzero = eig > lam_max * 1e-10
        lam_min = jnp.min(jnp.where(nonzero, eig, jnp.inf))
        lip = jnp.where(has_data, 2.0 * (lam_max + ridge), 1.0)
        mu = jnp.where(has_data & jnp.isfinite(lam_min), 2.0 * (lam_min + ridge), lip)
        kappa_sqrt = jnp.sqrt(lip / mu)
        opt = optax.sgd(learning_rate=1.0 / lip, momentum=(kappa_sqrt - 1.0) / (kappa_sqrt + 1.0), nesterov=True)

        def direction(g):
            return g

    if S is None:
        S = jnp.ones_like(J0)
    grad_fn = jax.grad(loss_fn)

    def step(carry):
        J, opt_state, i = carry
        upd, opt_state = opt.update(direction(grad_fn(J)), opt_state, J)
        J = _project(optax.apply_updates(J, upd), S, sign_project)
        return J, opt_state, i + 1

    J_start = _project(J0, S, sign_project)
    carry = (J_start, opt.init(J_start), jnp.zeros((), jnp.int32))
    if tol is None:
        J, _, _ = jax.lax.fori_loop(0, steps, lambda _, c: step(c), carry)
    else:

        def cond(carry):
            J, _, i = carry
            g = grad_fn(J)
            return (i < steps) & (jnp.sqrt(jnp.sum(g**2)) > tol)

        J, _, _ = jax.lax.while_loop(cond, step, carry)
    return jnp.where(has_data, J, J0)


def slsqp_refine(theta, V, J0, *, numeric_grad: bool = False, ftol: float = 1e-12, maxiter: int = 1000):
    """Eq. 14 by scipy's SLSQP (the paper's optimizer), eager only; returns ``(n, m)`` numpy array.

    ``numeric_grad=True`` lets SLSQP use finite differences (as a plain
    ``scipy.optimize.minimize`` call would); otherwise the analytic gradient
    ``-2 (theta^T - J V^T) V`` is supplied.
    """
    from scipy.optimize import minimize  # test/benchmark dependency only

    theta = np.asarray(theta, np.float64)
    V = np.asarray(V, np.float64)
    J0 = np.asarray(J0, np.float64)
    shape = J0.shape
    if not np.any(V):
        return J0

    def fun(x):
        r = theta.T - x.reshape(shape) @ V.T
        return float(np.sum(r * r))

    def jac(x):
        r = theta.T - x.reshape(shape) @ V.T
        return (-2.0 * r @ V).ravel()

    res = minimize(
        fun, J0.ravel(), jac=None if numeric_grad else jac, method="SLSQP", options={"ftol": ftol, "maxiter": maxiter}
    )
    return res.x.reshape(shape)


def needs_samples(method: str, loss: str = "l2") -> bool:
    """Whether :func:`refine` with ``method`` and ``loss`` reads the ring buffer (Huber loss, SLSQP) rather than the
    statistics."""
    return method == "slsqp" or loss == "huber"


def refine(
    state: EstimatorState,
    J0: ArrayLike,
    *,
    method: str = "optax",
    steps: int = 100,
    tol: float | None = None,
    loss: str = "l2",
    huber_delta: ArrayLike = 1.0,
    ridge: ArrayLike = 0.0,
    sign_project: bool = False,
    precondition: bool | None = None,
    numeric_grad: bool = False,
    rcond: ArrayLike | None = None,
) -> jax.Array:
    """Refined inverse Jacobian ``(n, m)`` from ``J0 (n, m)`` (Eq. 14).

    ``"closed_form"`` and ``"optax"`` with the L2 loss read the statistics
    ``S_vv``, ``S_tv`` and so cover every accepted sample (forgetting-weighted);
    the Huber loss and ``"slsqp"`` read the ring buffer (the last ``capacity``
    samples; ``ValueError`` for a state without one, ``capacity=0``).
    ``method``, ``steps``, ``loss``, ``sign_project``, ``precondition`` and ``numeric_grad`` are
    static; ``huber_delta`` (actuator units, > 0), ``ridge`` (>= 0) and ``rcond``
    (the relative pivot tolerance of :func:`psd_pinv`, closed form only) may be
    traced (concrete values out of range raise ``ValueError``).
    ``"closed_form"`` honours ``ridge`` only (always the L2 loss);
    ``"slsqp"`` is eager only and plain L2. See the module docstring.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {LOSSES}, got {loss!r}")
    n, m, capacity = sizes(state)
    check_array("J0", J0, (n, m))
    check_scalar("huber_delta", huber_delta, gt=0.0)
    check_scalar("ridge", ridge, ge=0.0)
    if rcond is not None:
        check_scalar("rcond", rcond, ge=0.0)
    if capacity == 0 and needs_samples(method, loss):
        raise ValueError(
            f"method={method!r} with loss={loss!r} refines on buffered samples, but the state has none "
            "(capacity=0): init the estimator with capacity > 0"
        )
    J0 = jnp.asarray(J0, state.S_tv.dtype)
    if method == "closed_form":
        if loss != "l2" or sign_project:
            raise ValueError("method='closed_form' supports only loss='l2' without sign_project; use method='optax'")
        return statistics_closed_form(state.S_vv, state.S_tv, J0, ridge=ridge, rcond=rcond)
    if method == "optax":
        S = signed_inverse_jacobian(state)
        options: dict[str, Any] = dict(steps=steps, tol=tol, ridge=ridge, sign_project=sign_project,
                                       precondition=precondition)
        if loss == "l2":
            return statistics_gradient_refine(state.S_vv, state.S_tv, J0, S, **options)
        theta, V, _ = _masked(state)
        return gradient_refine(theta, V, J0, S, loss=loss, huber_delta=huber_delta, **options)
    if any(is_traced(x) for x in jax.tree.leaves((state, J0))):
        raise ValueError("method='slsqp' runs scipy eagerly and cannot be used under jit/vmap/grad")
    if loss != "l2" or sign_project or np.any(np.asarray(ridge) != 0):
        raise ValueError("method='slsqp' is the plain-L2 reference: no huber loss, ridge or sign_project")
    theta, V, _ = _masked(state)
    return jnp.asarray(slsqp_refine(theta, V, J0, numeric_grad=numeric_grad), J0.dtype)
