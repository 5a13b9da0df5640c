"""Sparse Online Gaussian Process (SOGP) regression at a fixed capacity, jit- and vmap-able.

Reference: L. Csato and M. Opper, "Sparse on-line Gaussian processes",
Neural Computation 14(3):641-668, 2002. The E-KM baseline (seed 002) learns
the residual of a nominal kinematic model with it (:mod:`selfid_jax.baselines.ekm`).

Representation (Csato & Opper, Sec. 3): the posterior of the latent ``f`` over
the basis set ``B`` is ``mean(x) = k_B(x)^T alpha``, ``var(x) = k(x, x) +
k_B(x)^T C k_B(x)``, with ``Q = K_B^-1`` kept for the novelty test and the
deletion. One update with the Gaussian likelihood of noise sd ``noise``:

* ``m = k^T alpha``, ``s2 = k(x, x) + k^T C k``, ``q = (y - m) / (s2 + noise^2)``,
  ``r = -1 / (s2 + noise^2)``; ``e = Q k``, novelty ``gamma = k(x, x) - k^T e``.
* novel (``gamma > novelty_tol * variance``): ``x`` joins the basis in a free
  slot ``j``: ``s = C k + u_j``, ``Q += (e - u_j)(e - u_j)^T / gamma``;
  otherwise the update is projected onto the basis: ``s = C k + e``.
  Either way ``alpha += s q^T``, ``C += r s s^T``. (Exact Bayesian updating
  while every point is added, so with ``capacity >= T`` and ``novelty_tol = 0``
  this is the full GP posterior.)
* over capacity: the basis element of lowest score
  ``||alpha_i||^2 / (Q_ii + C_ii)`` (Csato & Opper's KL-based score, summed
  over outputs) is deleted with their pruning equations:
  ``alpha -= Q_i alpha_i^T / q*``, ``C += c* Q_i Q_i^T / q*^2 - (Q_i C_i^T +
  C_i Q_i^T) / q*``, ``Q -= Q_i Q_i^T / q*`` (``Q_i``, ``C_i`` column ``i``;
  ``q* = Q_ii``, ``c* = C_ii``). The newest point may be the one deleted.

Fixed shapes: ``capacity + 1`` slots and a mask; add, project and delete are
all computed and selected by ``jnp.where`` (no Python branch on a value), so
``update`` jits, vmaps and scans. Inactive slots hold zeros in ``alpha``,
``C`` and ``Q`` (and are masked out of ``k``).

Choices (stated, sweepable: they live in the state as traced arrays):

* kernel: ARD squared exponential ``k(x, x') = variance * exp(-0.5 sum_d
  ((x_d - x'_d) / lengthscale_d)^2)`` (:class:`RBF`); smooth, so the posterior
  mean is differentiable in ``x`` (E-KM uses its Jacobian).
* outputs share the kernel, the noise and the basis: ``alpha (M+1, dim_out)``,
  one ``C`` and one ``Q``; the predictive variance is the same for all outputs.
* novelty tolerance relative to ``variance`` (dimensionless, default 1e-4),
  floored at ``sqrt(eps) = 1.5e-8``: a point that close to the span of the
  basis is projected (exactly so when it repeats a basis input), since
  ``1 / gamma`` would swamp ``Q`` with round-off.
* precision: float64. The rank-1 updates of ``Q = K_B^-1`` lose positive
  definiteness in float32 (a probe: unless ``novelty_tol >= 1e-2`` and
  ``noise^2 >= 1e-2 variance``, and clamping then gives NaN), so :func:`init`
  refuses float32 with an error that says how to enable float64; no
  square-root form is implemented. ``C`` and ``Q`` are re-symmetrised every
  update; the variance used in ``q`` and ``r`` is clamped at 0 and every
  division is guarded. Even in float64, dense inputs (a control trajectory, a
  line of close points) with ``novelty_tol`` below ~1e-4 make ``K_B`` so
  ill-conditioned that round-off in ``Q`` breaks the invariants ``diag(C) <= 0``,
  ``diag(Q + C) >= 0`` and the state then runs to inf within a few updates;
  an update that breaks them is discarded (counted in ``unstable``), so no
  NaN is ever stored, but keep ``novelty_tol >= 1e-4`` (the default) for a
  useful model on such data.
* a sample with a non-finite entry is rejected (counted in ``rejected``, the
  state is otherwise unchanged); :func:`predict` at a non-finite ``x`` returns
  the prior (zero mean, ``variance``) rather than NaN.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.math.checks import check_array, check_positive_int, check_scalar, float_dtype

__all__ = ["RBF", "SOGPState", "init", "update", "predict", "mean", "size", "kernel_matrix"]


class RBF(NamedTuple):
    """ARD squared-exponential kernel ``variance * exp(-0.5 ||(x - x') / lengthscale||^2)``."""

    lengthscale: jax.Array | float = 1.0  # () or (dim_in,) input units, > 0
    variance: jax.Array | float = 1.0  # () signal variance sf^2, output units^2, > 0


class SOGPState(NamedTuple):
    """State of one SOGP (Csato & Opper 2002): ``S = capacity + 1`` slots, ``D = dim_in``, ``P = dim_out``."""

    basis: jax.Array  # (S, D) float: basis inputs (rows of inactive slots are stale, masked out)
    mask: jax.Array  # (S,) bool: slot holds a basis element
    alpha: jax.Array  # (S, P) float: mean weights, mean(x) = k_B(x)^T alpha [output units / variance]
    C: jax.Array  # (S, S) float: var(x) = k(x,x) + k_B^T C k_B; negative semi-definite [1 / variance]
    Q: jax.Array  # (S, S) float: inverse Gram matrix K_B^-1 of the active slots [1 / variance]
    lengthscale: jax.Array  # (D,) float: kernel lengthscales [input units]
    variance: jax.Array  # () float: kernel signal variance [output units^2]
    noise: jax.Array  # () float: observation noise sd [output units]
    novelty_tol: jax.Array  # () float: add x iff gamma > novelty_tol * variance [dimensionless]
    count: jax.Array  # type: ignore[assignment]  # () int32: accepted samples
    rejected: jax.Array  # () int32: rejected samples (non-finite entries)
    unstable: jax.Array  # () int32: accepted samples whose update broke the invariants and was discarded


def init(
    dim_in: int,
    dim_out: int,
    *,
    capacity: int,
    kernel: RBF = RBF(),
    noise=1e-2,
    novelty_tol=1e-4,
    dtype=None,
) -> SOGPState:
    """An empty SOGP of ``capacity`` basis elements for ``f: R^dim_in -> R^dim_out``.

    Args:
      dim_in, dim_out: input and output sizes (positive ints).
      capacity: the most basis elements kept, ``M >= 1`` (``M + 1`` slots).
      kernel: :class:`RBF`; ``lengthscale`` () or ``(dim_in,)`` > 0,
        ``variance`` > 0. May be traced.
      noise: observation-noise standard deviation, output units, > 0. May be traced.
      novelty_tol: relative novelty threshold in ``[0, 1)``. May be traced.
      dtype: float dtype, default JAX's default float; must be float64
        (``jax.config.update("jax_enable_x64", True)`` or ``with jax.enable_x64(True)``).

    Concrete bad values raise ``ValueError`` naming the argument before any compute.
    """
    dim_in = check_positive_int("sogp: dim_in", dim_in)
    dim_out = check_positive_int("sogp: dim_out", dim_out)
    capacity = check_positive_int("sogp: capacity", capacity)
    if not isinstance(kernel, RBF):
        raise ValueError(f"sogp: kernel: expected an RBF(lengthscale, variance), got {kernel!r}")
    if np.ndim(kernel.lengthscale) not in (0, 1) or np.size(kernel.lengthscale) not in (1, dim_in):
        raise ValueError(f"sogp: kernel.lengthscale: expected shape () or ({dim_in},), "
                         f"got {np.shape(kernel.lengthscale)}")
    check_scalar("sogp: kernel.lengthscale", kernel.lengthscale, gt=0.0)
    check_array("sogp: kernel.variance", kernel.variance, ())
    check_scalar("sogp: kernel.variance", kernel.variance, gt=0.0)
    check_array("sogp: noise", noise, ())
    check_scalar("sogp: noise", noise, gt=0.0)
    check_array("sogp: novelty_tol", novelty_tol, ())
    check_scalar("sogp: novelty_tol", novelty_tol, ge=0.0)
    if not isinstance(novelty_tol, jax.core.Tracer) and float(novelty_tol) >= 1.0:
        raise ValueError(f"sogp: novelty_tol: must be < 1 (relative to the kernel variance), got {novelty_tol!r}")
    dtype = np.dtype(float_dtype() if dtype is None else dtype)
    if dtype != np.float64:
        raise ValueError(
            f"sogp: needs float64 (the rank-1 updates of K_B^-1 break down in {dtype}); enable it with "
            "jax.config.update('jax_enable_x64', True) or `with jax.enable_x64(True):`"
        )
    S = capacity + 1
    return SOGPState(
        basis=jnp.zeros((S, dim_in), dtype),
        mask=jnp.zeros((S,), bool),
        alpha=jnp.zeros((S, dim_out), dtype),
        C=jnp.zeros((S, S), dtype),
        Q=jnp.zeros((S, S), dtype),
        lengthscale=jnp.broadcast_to(jnp.asarray(kernel.lengthscale, dtype), (dim_in,)),
        variance=jnp.asarray(kernel.variance, dtype),
        noise=jnp.asarray(noise, dtype),
        novelty_tol=jnp.asarray(novelty_tol, dtype),
        count=jnp.zeros((), jnp.int32),
        rejected=jnp.zeros((), jnp.int32),
        unstable=jnp.zeros((), jnp.int32),
    )


def size(state: SOGPState) -> jax.Array:
    """Number of basis elements, () int32."""
    return jnp.sum(state.mask.astype(jnp.int32), axis=-1)


def _kvec(state: SOGPState, x):
    """``k_B(x)`` over the slots, zero where inactive: ``(S,)``."""
    d = (state.basis - x[None, :]) / state.lengthscale[None, :]
    k = state.variance * jnp.exp(-0.5 * jnp.sum(d * d, axis=-1))
    return jnp.where(state.mask, k, 0.0)


def kernel_matrix(kernel: RBF, X1, X2):
    """``k(X1_i, X2_j)`` of the RBF kernel: ``X1 (a, D)``, ``X2 (b, D)`` -> ``(a, b)`` (for tests and references)."""
    ls = jnp.broadcast_to(jnp.asarray(kernel.lengthscale), (X1.shape[-1],))
    d = (X1[:, None, :] - X2[None, :, :]) / ls[None, None, :]
    return kernel.variance * jnp.exp(-0.5 * jnp.sum(d * d, axis=-1))


def _sym(A):
    return 0.5 * (A + A.T)


def _safe(x, tiny):
    """``x`` where ``|x| > tiny``, else ``tiny`` (positive denominators only reach here)."""
    return jnp.where(x > tiny, x, tiny)


def _fold(state: SOGPState, x, y) -> SOGPState:
    """Csato-Opper update by one valid sample ``x (D,)``, ``y (P,)``: add or project, then prune to capacity."""
    dtype = state.alpha.dtype
    tiny = jnp.finfo(dtype).tiny
    S = state.mask.shape[0]
    kss = state.variance
    k = _kvec(state, x)
    Ck = state.C @ k
    s2 = jnp.maximum(kss + k @ Ck, 0.0)  # latent predictive variance at x (>= 0 up to round-off)
    denom = s2 + state.noise**2
    q = (y - k @ state.alpha) / denom  # (P,)
    r = -1.0 / denom
    e = state.Q @ k
    gamma = kss - k @ e  # novelty: squared distance of k(x, .) from span(B) in feature space
    # below sqrt(eps) * variance a point is always projected: 1 / gamma would swamp K_B^-1 with round-off
    novel = gamma > jnp.maximum(state.novelty_tol, jnp.sqrt(jnp.finfo(dtype).eps)) * kss
    free = jnp.argmin(state.mask)  # first free slot (one always is: <= capacity active before the update)
    unit = jax.nn.one_hot(free, S, dtype=dtype)
    s = Ck + jnp.where(novel, unit, e)
    eu = e - unit
    Q = jnp.where(novel, state.Q + jnp.outer(eu, eu) / _safe(gamma, tiny), state.Q)
    st = state._replace(
        basis=jnp.where(novel, state.basis.at[free].set(x), state.basis),
        mask=jnp.where(novel, state.mask.at[free].set(True), state.mask),
        alpha=state.alpha + jnp.outer(s, q),
        C=_sym(state.C + r * jnp.outer(s, s)),
        Q=_sym(Q),
    )
    return jax.tree.map(lambda a, b: jnp.where(size(st) > S - 1, a, b), _prune(st), st)


def _prune(state: SOGPState) -> SOGPState:
    """Delete the basis element of lowest score ``||alpha_i||^2 / (Q_ii + C_ii)`` (Csato & Opper's pruning)."""
    tiny = jnp.finfo(state.alpha.dtype).tiny
    qd, cd = jnp.diagonal(state.Q), jnp.diagonal(state.C)
    score = jnp.sum(state.alpha**2, axis=-1) / _safe(qd + cd, tiny)
    i = jnp.argmin(jnp.where(state.mask, score, jnp.inf))
    qs = _safe(qd[i], tiny)
    Qi, Ci, ai = state.Q[:, i], state.C[:, i], state.alpha[i]
    keep = state.mask.at[i].set(False)
    outer_keep = jnp.outer(keep, keep)
    alpha = state.alpha - jnp.outer(Qi, ai) / qs
    C = state.C + cd[i] * jnp.outer(Qi, Qi) / qs**2 - (jnp.outer(Qi, Ci) + jnp.outer(Ci, Qi)) / qs
    Q = state.Q - jnp.outer(Qi, Qi) / qs
    return state._replace(
        mask=keep,
        alpha=jnp.where(keep[:, None], alpha, 0.0),
        C=jnp.where(outer_keep, _sym(C), 0.0),
        Q=jnp.where(outer_keep, _sym(Q), 0.0),
    )


def _check_xy(state: SOGPState, x, y=None):
    D, P = state.basis.shape[-1], state.alpha.shape[-1]
    check_array("sogp: x", x, (D,))
    if y is not None:
        check_array("sogp: y", y, (P,))


def update(state: SOGPState, x, y) -> SOGPState:
    """Fold one observation ``y (dim_out,)`` of ``f`` at ``x (dim_in,)`` (module docstring: add/project/prune).

    Shapes are checked eagerly (``ValueError``). A sample with a non-finite
    entry is rejected: only ``rejected`` changes, and no inf/NaN reaches the
    arithmetic. Jit-, vmap- and scan-able; every hyperparameter is read from
    the state (traced).
    """
    _check_xy(state, x, y)
    dtype = state.alpha.dtype
    x = jnp.asarray(x, dtype)
    y = jnp.asarray(y, dtype)
    ok = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(y))
    new = _fold(state, jnp.where(ok, x, 0.0), jnp.where(ok, y, 0.0))
    healthy = _healthy(new)
    keep = ok & healthy
    new = jax.tree.map(lambda a, b: jnp.where(keep, a, b), new, state)
    return new._replace(
        count=state.count + ok.astype(jnp.int32),
        rejected=state.rejected + (~ok).astype(jnp.int32),
        unstable=state.unstable + (ok & ~healthy).astype(jnp.int32),
    )


def _healthy(state: SOGPState) -> jax.Array:
    """Csato-Opper's invariants hold up to round-off: finite, ``diag(C) <= 0`` and ``diag(Q + C) >= 0``.

    ``-C`` and ``Q + C = K_B^-1 Sigma_B K_B^-1`` are positive semi-definite in
    exact arithmetic; once round-off in ``Q`` (ill-conditioned ``K_B``) breaks
    them the state drifts to inf within a few updates, so such an update is
    discarded instead (counted in ``unstable``).
    """
    qd, cd = jnp.diagonal(state.Q), jnp.diagonal(state.C)
    slack = 1e-6 * jnp.max(jnp.abs(qd)) + jnp.finfo(qd.dtype).tiny
    finite = jnp.all(jnp.isfinite(state.alpha)) & jnp.all(jnp.isfinite(state.C)) & jnp.all(jnp.isfinite(state.Q))
    return finite & jnp.all(cd <= slack) & jnp.all(qd + cd >= -slack)


def predict(state: SOGPState, x) -> tuple[jax.Array, jax.Array]:
    """Posterior mean ``(dim_out,)`` and latent variance ``()`` of ``f`` at ``x (dim_in,)``.

    ``mean = k_B(x)^T alpha`` (output units; differentiable in ``x``: take
    ``jax.jacfwd`` of :func:`mean`), ``var = max(variance + k_B^T C k_B, 0)``
    (output units^2, without the observation noise). A non-finite ``x``
    gives the prior: zero mean, ``variance``.
    """
    _check_xy(state, x)
    x = jnp.asarray(x, state.alpha.dtype)
    ok = jnp.all(jnp.isfinite(x))
    k = jnp.where(ok, _kvec(state, jnp.where(ok, x, 0.0)), 0.0)
    return k @ state.alpha, jnp.maximum(state.variance + k @ (state.C @ k), 0.0)


def mean(state: SOGPState, x) -> jax.Array:
    """Posterior mean ``(dim_out,)`` at ``x (dim_in,)`` (:func:`predict`'s first output)."""
    return predict(state, x)[0]
