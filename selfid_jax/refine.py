"""Refinement of an inverse-Jacobian guess on buffered self-ID samples (Eq. 14).

``argmin_J sum_k rho(dtheta_k - J V_k) + ridge * ||J - J0||_F^2`` starting from
``J0``, where ``rho`` is the squared L2 norm (the paper) or a Huber loss.

Three methods:

* ``"closed_form"``: the minimum-norm correction ``J0 + (Theta - J0 V) pinv(V)``
  (``Theta (n, K)``, ``V (m, K)`` the samples as columns), or the exact ridge
  solution ``J0 + R V^T (V V^T + ridge I)^-1`` for ``ridge > 0``.
  Gradient descent on the L2 loss keeps its iterates in ``J0 + A V^T``, so this
  is also the exact limit of gradient descent from ``J0``, with fewer samples
  than task dimensions too.
* ``"optax"``: gradient descent with optax, preconditioned on the right by
  ``(V V^T + ridge I)^-1`` (or, for the sign projection, Nesterov descent with
  step ``1/L`` from the largest eigenvalue of ``V V^T``); supports the Huber
  loss, the ridge term and a projection onto the signs of the signed inverse
  Jacobian. Both keep iterates in ``J0 + A V^T`` and so reach the minimum-norm
  solution; per-element scaled optimizers (Adam & co.) would leave that space
  and are not used. See :func:`gradient_refine`.
* ``"slsqp"``: scipy's SLSQP as in the paper; eager only, the reference for
  tests and benchmarks.

With no buffered samples every method returns ``J0``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax

from selfid_jax._checks import check_array, check_scalar, is_traced
from selfid_jax.estimator import EstimatorState, samples, signed_inverse_jacobian, sizes

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
    """
    R = theta.T - J0 @ V.T  # (n, K)
    if isinstance(ridge, (int, float)) and ridge == 0:
        return J0 + R @ jnp.linalg.pinv(V.T)
    m = V.shape[1]
    ridge = jnp.asarray(ridge, V.dtype)
    safe = jnp.where(ridge > 0, ridge, 1.0)
    ridge_corr = jnp.linalg.solve(V.T @ V + safe * jnp.eye(m, dtype=V.dtype), V.T @ R.T).T
    return J0 + jnp.where(ridge > 0, ridge_corr, R @ jnp.linalg.pinv(V.T))


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
    """Gradient descent with optax on :func:`refine_objective` from ``J0 (n, m)``.

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
    """
    if precondition is None:
        precondition = not sign_project
    dtype = V.dtype
    m = V.shape[1]
    ridge = jnp.asarray(ridge, dtype)
    gram = V.T @ V
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

    def loss_fn(J):
        return refine_objective(J, theta, V, J0, loss=loss, huber_delta=huber_delta, ridge=ridge)

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


def refine(
    state: EstimatorState,
    J0,
    *,
    method: str = "optax",
    steps: int = 100,
    tol: float | None = None,
    loss: str = "l2",
    huber_delta=1.0,
    ridge=0.0,
    sign_project: bool = False,
    precondition: bool | None = None,
    numeric_grad: bool = False,
):
    """Refined inverse Jacobian ``(n, m)`` from ``J0 (n, m)`` on the state's buffered samples (Eq. 14).

    ``method``, ``steps``, ``loss``, ``sign_project``, ``precondition`` and ``numeric_grad`` are
    static; ``huber_delta`` (actuator units, > 0) and ``ridge`` (>= 0) may be
    traced (concrete values out of range raise ``ValueError``).
    ``"closed_form"`` honours ``ridge`` only (always the L2 loss);
    ``"slsqp"`` is eager only and plain L2. See the module docstring.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {LOSSES}, got {loss!r}")
    n, m, _ = sizes(state)
    check_array("J0", J0, (n, m))
    check_scalar("huber_delta", huber_delta, gt=0.0)
    check_scalar("ridge", ridge, ge=0.0)
    J0 = jnp.asarray(J0, state.dtheta_buf.dtype)
    theta, V, _ = _masked(state)
    if method == "closed_form":
        if loss != "l2" or sign_project:
            raise ValueError("method='closed_form' supports only loss='l2' without sign_project; use method='optax'")
        return closed_form(theta, V, J0, ridge=ridge)
    if method == "optax":
        S = signed_inverse_jacobian(state)
        return gradient_refine(
            theta,
            V,
            J0,
            S,
            steps=steps,
            tol=tol,
            loss=loss,
            huber_delta=huber_delta,
            ridge=ridge,
            sign_project=sign_project,
            precondition=precondition,
        )
    if any(is_traced(x) for x in jax.tree.leaves((state, J0))):
        raise ValueError("method='slsqp' runs scipy eagerly and cannot be used under jit/vmap/grad")
    if loss != "l2" or sign_project or np.any(np.asarray(ridge) != 0):
        raise ValueError("method='slsqp' is the plain-L2 reference: no huber loss, ridge or sign_project")
    return jnp.asarray(slsqp_refine(theta, V, J0, numeric_grad=numeric_grad), J0.dtype)
