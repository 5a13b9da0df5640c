"""Small dense linear algebra: pseudo-inverses, adjugate inverses and the unrolled PSD solves behind Eq. 14.

The Jacobian pseudo-inverse, the adjugate inverse of k x k matrices (k <= 3),
the unrolled rank-revealing pseudo-inverse and solve of small PSD matrices
behind Eq. 14's closed form, and the implicit-function-theorem derivative of
a root found by any solver (the closed-chain hands' Newton solves).

Pure ``jax.numpy``, one matrix per call (``vmap`` for batches). Units are the
caller's: ``pseudo_inverse`` of a task Jacobian (task units per actuator unit)
is in actuator units per task unit.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from selfid_jax.math.kernels import ldl, small_matmul

__all__ = ["default_rcond", "implicit_root", "jacfwd_with_value", "newton_root", "pseudo_inverse", "psd_pinv",
           "small_inverse"]


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


def default_rcond(m: int, dtype) -> float:
    """Default relative eigenvalue cutoff of :func:`psd_pinv`: ``10 m eps`` of ``dtype`` (6.7e-15 in float64, 3.6e-6 in
    float32 for m = 3)."""
    return 10.0 * m * float(jnp.finfo(dtype).eps)


def psd_pinv(S, *, rcond=None):
    """Pseudo-inverse ``P (m, m)`` of a symmetric positive semi-definite ``S (m, m)`` and the projector ``N (m, m)``
    onto its null space.

    Rank-revealing ``L D L^T`` factorisation without pivoting, unrolled over the
    static ``m`` (vmapped, it is elementwise work across the batch, with no
    LAPACK call per matrix). The Schur complements of a PSD matrix are PSD, so
    a zero pivot means a zero row and column. At step ``k`` the candidate null
    vector ``z_k = L^-T e_k`` (it needs only the columns of ``L`` before ``k``)
    has Rayleigh quotient ``z_k^T S z_k / ||z_k||^2 = d_k / ||z_k||^2``; pivot
    ``k`` counts as zero, and its column of ``L`` is dropped, when that is at
    most ``rcond * tr(S)`` (default :func:`default_rcond`): the eigenvalue
    cutoff of a pseudo-inverse, relative to the sum of the eigenvalues. (The
    pivot itself is a poor test without pivoting: after a small earlier pivot
    the round-off of a null pivot reached 2e-10 of its diagonal entry, while
    the Rayleigh quotient of round-off null directions stayed below 6e-16 of
    the trace and that of excited ones above 6e-8, over 3,200 random rank-1
    and rank-2 streams in 3-D.) Then ``W = L^-T D^+ L^-1`` satisfies
    ``S W S = S``, the ``z_k`` of the dropped pivots span the null space,
    orthonormalised by Gram-Schmidt into ``N = sum q q^T``, and
    ``P = (I - N) W (I - N)`` is the Moore-Penrose inverse. With no pivot
    dropped, ``N = 0`` exactly and ``P = S^-1``.

    Because ``S = V V^T`` squares the condition number of the samples ``V``, a
    direction whose singular value is below about ``sqrt(rcond)`` times the
    largest counts as not excited (float32, m = 3: ``2e-3``; the buffered
    ``pinv(V)`` keeps down to ``10 K eps``). ``rcond`` may be traced. Jit,
    vmap and differentiate (NaN-safe where a pivot is dropped).
    """
    m = S.shape[-1]
    zero = jnp.zeros((), S.dtype)
    Li, dinv, N = _ldl_null_space(S, rcond)
    # W = Li^T D^+ Li (symmetric)
    Wrows = [[zero] * m for _ in range(m)]
    for i in range(m):
        for j in range(i, m):
            w = zero
            for k in range(j, m):
                w = w + Li[k][i] * dinv[k] * Li[k][j]
            Wrows[i][j] = Wrows[j][i] = w
    W = jnp.stack([jnp.stack(row) for row in Wrows])
    R = jnp.eye(m, dtype=S.dtype) - N
    return small_matmul(small_matmul(R, W), R), N


def _ldl_null_space(S, rcond):
    """The rank-revealing ``L D L^T`` of :func:`psd_pinv`: ``(Li, dinv, N)``.

    ``Li`` (nested lists, ``m x m`` scalars): ``L^-1``; ``dinv`` (``m``
    scalars): ``D^+`` (0 for a dropped pivot); ``N (m, m)``: the projector onto
    the span of the dropped ``z_k`` (rows ``k`` of ``L^-1``).
    """
    m = S.shape[-1]
    rcond = default_rcond(m, S.dtype) if rcond is None else rcond
    _, Li, dinv, keep = ldl(S, rcond * sum((S[k, k] for k in range(1, m)), S[0, 0]))  # rcond * tr(S)
    # null space: z_k (row k of Li) for dropped k, orthonormalised
    qs: list[list[jax.Array]] = []
    for k in range(m):
        z = list(Li[k])
        for q in qs:
            dot = sum((q[i] * z[i] for i in range(1, m)), q[0] * z[0])
            z = [z[i] - dot * q[i] for i in range(m)]
        norm2 = sum((zi * zi for zi in z[1:]), z[0] * z[0])
        drop = ~keep[k]
        inv_norm = jnp.where(drop, jax.lax.rsqrt(jnp.where(drop & (norm2 > 0), norm2, 1.0)), 0.0)
        qs.append([zi * inv_norm for zi in z])
    N = jnp.stack([jnp.stack([sum((q[i] * q[j] for q in qs[1:]), qs[0][i] * qs[0][j]) for j in range(m)])
                   for i in range(m)])
    return Li, dinv, N


def _spd_right_solve(B, A):
    """``B (p, m) A^-1`` for a symmetric positive definite ``A (m, m)``: unrolled ``L D L^T`` and two substitutions."""
    m = A.shape[-1]
    L, _, dinv, _ = ldl(A, 0.0)
    y = [B[:, j] for j in range(m)]  # Y L^T = B, forward
    for j in range(m):
        for k in range(j):
            y[j] = y[j] - L[j][k] * y[k]
    y = [y[j] * dinv[j] for j in range(m)]
    for k in reversed(range(m)):  # X L = Y D^-1, backward
        for j in range(k + 1, m):
            y[k] = y[k] - L[j][k] * y[j]
    return jnp.stack(y, axis=-1)


def jacfwd_with_value(f):
    """``x -> (df/dx (k, n), f(x) (k,))`` for ``f: (n,) -> (k,)``: the value from the same forward-mode pass as the
    Jacobian, so a compiled program holds one copy of ``f`` where a separate ``f(x)`` would add a second."""
    return jax.jacfwd(lambda x: (lambda r: (r, r))(f(x)), has_aux=True)


def newton_root(residual, y0, args, *, rtol: float, atol: float, max_steps: int):
    """Newton's method for ``residual(y, args) = 0`` from ``y0``: ``(y (k,), F_y (k, k), converged ())``.

    Each step solves ``F_y dy = F`` by LU (``jnp.linalg.solve``) and sets
    ``y <- y - dy``. The test is ``optimistix.Newton``'s Cauchy test: ``y_j`` is
    returned once the step that made it was within ``atol + rtol |y_j|``
    (every entry) and the residual it started from within ``atol`` (every
    entry); ``converged`` is False after ``max_steps`` steps without that, or
    at a non-finite iterate (a singular ``F_y``), and ``y`` is then the last
    iterate. ``F_y = d residual / dy`` (``jacfwd``) is the Jacobian at the
    returned ``y``, for :func:`implicit_root` and stability tests.

    The residual and its Jacobian are evaluated at one place in the loop
    body (one more evaluation than steps), so a compiled program holds a
    single copy of them: the solve's share of XLA compile time is about half
    that of a solver that forms ``F_y`` again after its loop. ``y`` carries no
    derivative (wrap it in :func:`implicit_root`). jit and vmap (a batch
    iterates until its last member stops).

    Args:
      residual: ``(y (k,), args) -> (k,)``.
      y0: ``(k,)`` the starting point.
      args: the residual's other arguments (any pytree; treated as constants).
      rtol, atol: the test's tolerances (units of ``y`` and of the residual).
      max_steps: the most Newton steps.
    """
    y0, args = jax.lax.stop_gradient((jnp.asarray(y0), args))

    def evaluate(y):
        return jacfwd_with_value(lambda y_: residual(y_, args))(y)

    def body(c):
        k, y, _, passed, _ = c
        F_y, F = evaluate(y)
        stop = passed | (k >= max_steps) | ~jnp.all(jnp.isfinite(y))
        dy = jnp.linalg.solve(F_y, F)
        y_new = y - dy
        small = (jnp.max(jnp.abs(dy) / (atol + rtol * jnp.abs(y_new))) < 1) & (jnp.max(jnp.abs(F)) < atol)
        return jnp.where(stop, k, k + 1), jnp.where(stop, y, y_new), F_y, jnp.where(stop, passed, small), stop

    init = (jnp.zeros((), jnp.int32), y0, jnp.zeros(y0.shape * 2, y0.dtype), jnp.zeros((), bool), jnp.zeros((), bool))
    _, y, F_y, passed, _ = jax.lax.while_loop(lambda c: ~c[4], body, init)
    return y, F_y, passed & jnp.all(jnp.isfinite(y))


def implicit_root(residual, y, args, F_y=None):
    """``y``, a root of ``residual(y, args) = 0`` found by any solver, with derivatives by the implicit function
    theorem.

    The value is ``y`` itself, bit for bit. Its derivative with respect to
    ``args`` (any pytree) is ``dy = -F_y^-1 (d residual / d args) dargs``,
    ``F_y = d residual / dy`` at ``(y, args)`` (``(k, k)``; computed by
    ``jacfwd`` if not given), solved by LU (``jnp.linalg.solve``); ``y``
    and ``F_y`` themselves are treated as constants. Forward and reverse mode,
    jit and vmap. Unlike a solver's own implicit adjoint (optimistix's goes
    through lineax, which checks the solve with a host callback), the
    program holds no host callback, so XLA's persistent compilation cache
    can keep it. A singular or non-finite ``F_y`` gives non-finite
    derivatives, never an error.

    Args:
      residual: ``(y (k,), args) -> (k,)``, differentiable in ``args``.
      y: ``(k,)`` the root.
      args: the residual's other arguments.
      F_y: optional ``(k, k)`` Jacobian of ``residual`` in ``y`` at the root.
    """
    y = jax.lax.stop_gradient(y)
    if F_y is None:
        F_y = jax.jacfwd(residual)(y, jax.lax.stop_gradient(args))
    return _implicit_value(residual, y, jax.lax.stop_gradient(F_y), args)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _implicit_value(residual, y, F_y, args):
    return y


@_implicit_value.defjvp
def _implicit_value_jvp(residual, primals, tangents):
    y, F_y, args = primals
    _, rhs = jax.jvp(lambda a: residual(y, a), (args,), (tangents[2],))
    return y, -jnp.linalg.solve(F_y, rhs)
