"""Small dense linear algebra: the Jacobian pseudo-inverse and the adjugate inverse of k x k matrices, k <= 3.

Pure ``jax.numpy``, one matrix per call (``vmap`` for batches). Units are the
caller's: ``pseudo_inverse`` of a task Jacobian (task units per actuator unit)
is in actuator units per task unit.
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["pseudo_inverse", "small_inverse"]


def pseudo_inverse(J):
    """Pseudo-inverse ``(n, m)`` of a Jacobian ``J (m, n)`` (see :meth:`System.true_inverse_jacobian`)."""
    m, n = J.shape
    if n == m:
        return small_inverse(J) if m <= 3 else jnp.linalg.solve(J, jnp.eye(m, dtype=J.dtype))
    if n > m:
        A = J @ J.T
        return J.T @ (small_inverse(A) if m <= 3 else jnp.linalg.solve(A, jnp.eye(m, dtype=J.dtype)))
    return jnp.linalg.solve(J.T @ J, J.T)


def small_inverse(A):
    """Inverse of a ``(k, k)`` matrix, ``k <= 3``, by the adjugate over the determinant.

    NaN where ``A`` is numerically singular: ``|det A|`` at most ``1e3 eps``
    times the product of its row norms (Hadamard's bound, so the test is
    scale-free), as an exactly singular ``solve`` would give inf/NaN.
    """
    k = A.shape[0]
    if k == 1:
        adj, det = jnp.ones_like(A), A[0, 0]
    elif k == 2:
        adj = jnp.stack([jnp.stack([A[1, 1], -A[0, 1]]), jnp.stack([-A[1, 0], A[0, 0]])])
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    else:
        c0, c1, c2 = jnp.cross(A[1], A[2]), jnp.cross(A[2], A[0]), jnp.cross(A[0], A[1])
        adj = jnp.stack([c0, c1, c2], axis=1)
        det = jnp.dot(A[0], c0)
    bound = jnp.prod(jnp.sqrt(jnp.sum(A * A, axis=1)))
    singular = jnp.abs(det) <= 1e3 * jnp.finfo(A.dtype).eps * bound
    return jnp.where(singular, jnp.nan, adj / jnp.where(singular, 1.0, det))
