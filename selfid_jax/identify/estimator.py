"""The self-ID inverse-Jacobian estimator as pure functions over a pytree state.

Shapes: ``n`` actuators, ``m`` task dimensions. The inverse Jacobian ``Jinv`` is
``(n, m)`` and maps a desired task twist to actuator motion: ``dtheta = Jinv @ V``.

One self-ID sample is a pair ``(dtheta (n,), V (m,))``: the random actuation and
the pose change it produced. :func:`update` folds a sample into the
:class:`EstimatorState` in ``O(n m + m^2)`` time and constant memory: sign
weights and magnitude sums (Eq. 6-12) and the sufficient statistics of Eq. 14,
``S_vv = sum V V^T`` and ``S_tv = sum dtheta V^T``, optionally with exponential
forgetting. :func:`signed_inverse_jacobian` (Eq. 6-10),
:func:`magnitude_inverse_jacobian` (Eq. 11-12) and :func:`initial_guess`
(Eq. 13) read estimates out of it; :func:`selfid_jax.identify.refine.refine` (Eq. 14)
fine-tunes an initial guess from the statistics (every accepted sample) or from
the optional ring buffer of the last ``capacity`` samples (Huber, SLSQP, and the
median, weighted and Kalman magnitudes); :func:`record` and :func:`converged`
implement the convergence test of Sec. IV-D, and :func:`convergence_iteration`
applies the same test to a whole sequence of estimates. :func:`guarded_update`
is the one sample screen (rejection of non-finite or all-zero samples) shared
by :func:`update` and every method of :mod:`selfid_jax.baselines`.

Every function is pure and has no Python control flow on values: all of them
jit, vmap and (where meaningful) differentiate.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from selfid_jax.math import native
from selfid_jax.math.checks import (
    check_array,
    check_float_dtype,
    check_positive_int,
    check_scalar,
    float_dtype,
    is_traced,
)
from selfid_jax.math.kernels import small_sum


class EstimatorState(NamedTuple):
    """Fixed-shape state of one estimator (a pytree; batch it with ``vmap``).

    Its size is independent of the number of samples: the sums below are over
    every accepted sample ``k = 1..K``, each weighted by ``forget^(K - k)``
    (all weights 1 with the default ``forget = 1``); only the optional ring
    buffer (``capacity`` rows, 0 for none) holds samples themselves.
    """

    sign_net: jax.Array  # (n, m) float: weight of s_ij = +1 minus weight of s_ij = -1 (Eq. 9's two buckets)
    mag_sum: jax.Array  # (n, m) float: sum of |dtheta_i / V_j| over samples with |V_j| > v_tol (Eq. 11)
    mag_count: jax.Array  # (m,) float: (weighted) number of samples in mag_sum, per task component j
    S_vv: jax.Array  # (m, m) float: sum V V^T, task units^2 (Gram matrix of Eq. 14)
    S_tv: jax.Array  # (n, m) float: sum dtheta V^T, actuator x task units (right-hand side of Eq. 14)
    s_tt: jax.Array  # () float: sum ||dtheta||^2, actuator units^2 (constant term of Eq. 14's objective)
    dtheta_buf: jax.Array  # (capacity, n) float: ring buffer of accepted actuations (capacity may be 0)
    v_buf: jax.Array  # (capacity, m) float: ring buffer of accepted pose changes
    # () int32: accepted samples so far (the buffer holds min(count, capacity))
    count: jax.Array  # type: ignore[assignment]  # shadows tuple.count
    rejected: jax.Array  # () int32: samples rejected as non-finite, all-zero, or overflowing the sums
    v_tol: jax.Array  # () float: |V_j| at or below this does not enter the magnitude mean
    forget: jax.Array  # () float in (0, 1]: factor applied to every sum before a sample is added
    estimate: jax.Array  # (n, m) float: last estimate passed to `record` (J_t; zeros before any)
    last_deltas: jax.Array  # (2,) float: ||J_t - J_{t-1}||_F of the last two records (inf before)
    last_norms: jax.Array  # (2,) float: ||J_t||_F of the last two records (for eps_rel; 0 before)
    last_fresh: jax.Array  # (2,) bool: whether each of the last two records followed a newly accepted sample
    recorded_count: jax.Array  # () int32: `count` at the last record
    iteration: jax.Array  # () int32: number of estimates recorded
    converged_at: jax.Array  # () int32: iteration at which `record` first saw convergence, -1 if never


def init(
    n: int, m: int, *, capacity: int = 64, v_tol: ArrayLike = 1e-9, forget: ArrayLike = 1.0, dtype=None
) -> EstimatorState:
    """Empty estimator for ``n`` actuators and ``m`` task dimensions.

    Args:
      n, m: static sizes.
      capacity: static number of most recent samples kept in a ring buffer for
        what needs samples (Huber loss, SLSQP, median, weighted and Kalman
        magnitudes); 0 keeps none. The closed-form and L2 gradient refinements
        (Eq. 14) read the statistics: every accepted sample, whatever ``capacity``.
      v_tol: pose-change magnitude (task units) below which a component is not
        used for the magnitude ratio of Eq. 11; may be a traced scalar.
      forget: exponential forgetting factor in ``(0, 1]``, dimensionless: every
        sum is multiplied by it before a sample is added, so sample ``k`` of
        ``K`` weighs ``forget^(K - k)`` (an effective memory of about
        ``1 / (1 - forget)`` samples). 1 (default) is the paper's estimator,
        which never forgets; below 1 the estimate follows a Jacobian that drifts
        or jumps (a grasp that slips). May be traced.
      dtype: float32 or float64 (default: JAX's default float).
    """
    n = check_positive_int("n", n)
    m = check_positive_int("m", m)
    capacity = check_nonnegative_int("capacity", capacity)
    check_scalar("v_tol", v_tol, ge=0.0)
    check_forget(forget)
    dtype = float_dtype() if dtype is None else check_float_dtype("dtype", dtype)
    zeros = jnp.zeros((n, m), dtype)
    return EstimatorState(
        sign_net=zeros,
        mag_sum=zeros,
        mag_count=jnp.zeros((m,), dtype),
        S_vv=jnp.zeros((m, m), dtype),
        S_tv=zeros,
        s_tt=jnp.zeros((), dtype),
        dtheta_buf=jnp.zeros((capacity, n), dtype),
        v_buf=jnp.zeros((capacity, m), dtype),
        count=jnp.zeros((), jnp.int32),
        rejected=jnp.zeros((), jnp.int32),
        v_tol=jnp.asarray(v_tol, dtype),
        forget=jnp.asarray(forget, dtype),
        estimate=zeros,
        last_deltas=jnp.full((2,), jnp.inf, dtype),
        last_norms=jnp.zeros((2,), dtype),
        last_fresh=jnp.zeros((2,), bool),
        recorded_count=jnp.zeros((), jnp.int32),
        iteration=jnp.zeros((), jnp.int32),
        converged_at=jnp.full((), -1, jnp.int32),
    )


def check_nonnegative_int(name: str, value) -> int:
    """``value`` as int; ``ValueError`` unless it is a Python integer >= 0."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ValueError(f"{name}: expected a non-negative integer (0: no sample buffer), got {value!r}")
    return int(value)


def check_forget(forget):
    """Eager check of a forgetting factor where it is concrete: real, in ``(0, 1]``; returns it."""
    check_scalar("forget", forget, gt=0.0)
    if not is_traced(forget) and np.any(np.asarray(forget, np.float64) > 1.0):
        raise ValueError(f"forget: must be <= 1 (1: no forgetting), got {forget!r}")
    return forget


def sizes(state: EstimatorState) -> tuple[int, int, int]:
    """Static ``(n, m, capacity)`` of a (possibly batched) state; ``capacity`` is 0 without a buffer."""
    capacity, n = state.dtheta_buf.shape[-2:]
    return n, state.v_buf.shape[-1], capacity


def is_valid_sample(dtheta: jax.Array, V: jax.Array) -> jax.Array:
    """True iff the sample is usable: shapes ``(n,)``, ``(m,)``.

    Every entry finite and below ``sqrt`` of the dtype's largest value (so the
    ratios of Eq. 11 and the products of Eq. 14 cannot overflow: 1.8e19 in
    float32), and neither ``dtheta`` nor ``V`` all zero (subnormal entries,
    below ``finfo.tiny``, count as zero).
    """
    info = jnp.finfo(jnp.result_type(dtheta, V))
    big = float(np.sqrt(info.max))
    bounded = jnp.all(jnp.abs(dtheta) <= big) & jnp.all(jnp.abs(V) <= big)  # False for NaN too
    # subnormal entries count as zero (CPUs may flush them to zero anyway)
    return bounded & jnp.any(jnp.abs(dtheta) >= info.tiny) & jnp.any(jnp.abs(V) >= info.tiny)


def sample_contribution(dtheta: jax.Array, V: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Sign weights of one sample: ``(s (n, m) in {-1, 0, 1}, w (n, m) >= 0)`` (Eq. 6-9).

    ``s_ij = sign(dtheta_i) sign(V_j)`` (Eq. 6) and ``w_ij = w_theta_i w_V_j``
    with ``w_theta_i = |dtheta_i| / sum|dtheta|`` (Eq. 7) and
    ``w_V_j = |V_j| / sum|V|`` (Eq. 8). Eq. 9 adds ``w_ij`` to the bucket of sign
    ``s_ij``. Zero sums give zero weights (no NaN).
    """
    s = jnp.sign(dtheta)[:, None] * jnp.sign(V)[None, :]
    a_t, a_v = jnp.abs(dtheta), jnp.abs(V)
    sum_t, sum_v = jnp.sum(a_t), jnp.sum(a_v)
    w_t = a_t / jnp.where(sum_t > 0, sum_t, 1.0)
    w_v = a_v / jnp.where(sum_v > 0, sum_v, 1.0)
    return s, w_t[:, None] * w_v[None, :]


def tally(state, ok: jax.Array):
    """``state`` with ``count + 1`` if ``ok`` (the sample was accepted), else ``rejected + 1``.

    ``state`` is any ``NamedTuple`` with int32 scalar fields ``count`` and
    ``rejected``; ``ok`` is a ``()`` bool. The sample counter of every estimator.
    """
    return state._replace(
        count=jnp.where(ok, state.count + 1, state.count),
        rejected=jnp.where(ok, state.rejected, state.rejected + 1),
    )


def guarded_update(fold, state, dtheta, V, *, shape, dtype, tally=tally, admit=None, zero_is_identity=False,
                   once=None):
    """Fold one sample into ``state`` with ``fold`` if it is valid; else only count it as rejected.

    The sample screen shared by :func:`update` and every method of
    :mod:`selfid_jax.baselines`. ``dtheta (n,)`` (actuator units) and ``V (m,)``
    (task units), ``shape = (n, m)``, are checked eagerly (``ValueError`` naming
    the expected and received shape) and cast to ``dtype``. A sample with a
    non-finite entry, or an all-zero ``dtheta`` or ``V``
    (:func:`is_valid_sample`), or one that ``admit(state, dtheta, V) -> ()
    bool`` refuses (it sees the sample as given and must return False for a
    non-finite one), is zeroed before ``fold`` sees it, so no inf/NaN reaches
    any arithmetic (or its gradient), and the state is kept as it was.
    ``fold(state, dtheta, V) -> state`` folds a valid sample and leaves the
    counters alone; ``tally(state, ok) -> state`` then counts the sample
    (default :func:`tally`: the state's own ``count``/``rejected`` fields).
    ``zero_is_identity=True`` declares that ``fold`` returns ``state``
    unchanged for the all-zero sample, which skips selecting between the old
    and the folded state (one pass over the state less per sample).
    ``once`` (optional): applied to the ``()`` bool acceptance before it is
    used (see :func:`accumulate`'s ``once``).
    """
    n, m = shape
    check_array("dtheta", dtheta, (n,))
    check_array("V", V, (m,))
    dtheta = jnp.asarray(dtheta, dtype)
    V = jnp.asarray(V, dtype)
    ok = is_valid_sample(dtheta, V)
    if admit is not None:
        ok = ok & admit(state, dtheta, V)
    if once is not None:
        ok = once(ok)
    dtheta, V = jnp.where(ok, dtheta, 0.0), jnp.where(ok, V, 0.0)
    new = fold(state, dtheta, V)
    if not zero_is_identity:
        new = jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, state)
    return tally(new, ok)


def fits(state: EstimatorState, dtheta: jax.Array, V: jax.Array) -> jax.Array:
    """``()`` bool: folding ``(dtheta (n,), V (m,))`` keeps the sums of squares finite (False for a non-finite sample).

    ``forget (s_tt + tr S_vv) + ||dtheta||^2 + ||V||^2`` bounds every entry of
    the new sums (Cauchy-Schwarz): a sample that passes :func:`is_valid_sample`
    but would overflow a sum is rejected.
    """
    m = state.S_vv.shape[-1]
    trace = small_sum(jnp.stack([state.S_vv[j, j] for j in range(m)]))  # not jnp.trace: a masked reduction
    return jnp.isfinite(state.forget * (state.s_tt + trace) + jnp.sum(dtheta * dtheta) + jnp.sum(V * V))


def accumulate(state: EstimatorState, dtheta: jax.Array, V: jax.Array, *, once=None) -> EstimatorState:
    """Fold one *valid* sample ``(dtheta (n,), V (m,))`` into the sums and the ring buffer; counters untouched.

    Multiplies every sum by ``forget`` and adds the sample's signed weights
    ``s_ij w_ij`` (Eq. 6-9), its magnitude ratios ``|dtheta_i / V_j|`` where
    ``|V_j| > v_tol`` (Eq. 11), ``V V^T`` to ``S_vv``, ``dtheta V^T`` to
    ``S_tv`` and ``||dtheta||^2`` to ``s_tt``, and writes the pair to ring-buffer
    row ``count % capacity`` (if ``capacity > 0``). ``O(n m + m^2)`` operations.
    The all-zero sample (a rejected one, zeroed by :func:`guarded_update`)
    leaves the state unchanged, forgetting included. No checks: use :func:`update`.
    ``once`` (optional): a function that returns its array argument unchanged
    in value, applied to the per-sample terms (``s_ij w_ij`` factors, ratios'
    inverses) before they enter the sums, such as
    :func:`selfid_jax.identify.recursive.once`, which makes XLA compute each
    term once per estimator instead of once per entry of every sum it updates.
    """
    n, m, _ = sizes(state)
    dtype = state.sign_net.dtype
    # Per-sample values come out of reductions (computed once per estimator by XLA); what follows
    # them is recomputed inside each (n, m) sum below, so it stays short.
    a_t, a_v = jnp.abs(dtheta), jnp.abs(V)
    sum_t, sum_v = jnp.sum(a_t), jnp.sum(a_v)
    nonzero = sum_v > 0  # False only for the zeroed (rejected) sample
    lam = jnp.where(nonzero, state.forget, 1.0).astype(dtype)
    u_t = dtheta / jnp.where(sum_t > 0, sum_t, 1.0)  # sign(dtheta_i) w_theta_i (Eq. 7)
    u_v = V / jnp.where(sum_v > 0, sum_v, 1.0)  # sign(V_j) w_V_j (Eq. 8)
    big = (a_v > state.v_tol).astype(dtype)  # (m,)
    inv_v = jnp.where(big > 0, 1.0 / jnp.where(big > 0, a_v, 1.0), 0.0)  # Eq. 11 ratio = |dtheta_i| * inv_v_j
    if once is not None:
        u_t, u_v, inv_v = once(u_t), once(u_v), once(inv_v)
    sw = u_t[:, None] * u_v[None, :]  # s_ij w_ij (Eq. 6-8)
    new = state._replace(
        sign_net=lam * state.sign_net + sw,
        mag_sum=lam * state.mag_sum + a_t[:, None] * inv_v[None, :],
        mag_count=lam * state.mag_count + big,
        S_vv=lam * state.S_vv + V[:, None] * V[None, :],
        S_tv=lam * state.S_tv + dtheta[:, None] * V[None, :],
        s_tt=lam * state.s_tt + jnp.sum(dtheta * dtheta),
    )
    return _ring_write(state, new, dtheta, V, nonzero)


def _ring_write(state: EstimatorState, new: EstimatorState, dtheta, V, keep) -> EstimatorState:
    """``new`` with ``(dtheta, V)`` in ring-buffer row ``state.count % capacity`` where ``keep`` (``()`` bool: the
    sample was accepted); ``new`` itself without a buffer."""
    _, _, capacity = sizes(state)
    if capacity == 0:
        return new
    slot = state.count % capacity
    return new._replace(
        dtheta_buf=state.dtheta_buf.at[slot].set(jnp.where(keep, dtheta, state.dtheta_buf[slot])),
        v_buf=state.v_buf.at[slot].set(jnp.where(keep, V, state.v_buf[slot])),
    )


def update(state: EstimatorState, dtheta: ArrayLike, V: ArrayLike, *, once=None) -> EstimatorState:
    """Fold one self-ID sample ``(dtheta (n,) [actuator units], V (m,) [task units])`` into the state.

    Accumulates the sign weights (Eq. 6-9), the magnitude ratios
    ``|dtheta_i / V_j|`` where ``|V_j| > v_tol`` (Eq. 11) and the statistics
    ``S_vv``, ``S_tv``, ``s_tt`` of Eq. 14, and appends the pair to the ring
    buffer if there is one (:func:`accumulate`). A sample with a non-finite
    entry, with all-zero ``dtheta`` or ``V``, or so large that a sum of squares
    would overflow (:func:`fits`), is rejected: only ``rejected`` changes
    (:func:`guarded_update`). ``once``: see :func:`accumulate` (None: none;
    the result's value is the same either way).
    """
    n, m, _ = sizes(state)
    if once is not None:
        return guarded_update(functools.partial(accumulate, once=once), state, dtheta, V, shape=(n, m),
                              dtype=state.sign_net.dtype, admit=fits, zero_is_identity=True, once=once)
    check_array("dtheta", dtheta, (n,))
    check_array("V", V, (m,))
    dtype = state.sign_net.dtype
    dtheta, V = jnp.asarray(dtheta, dtype), jnp.asarray(V, dtype)
    # the sums: the native CPU kernel where it is built (selfid_jax.math.native), _update_sums elsewhere
    sums = native.call("update", _update_sums, *(getattr(state, f) for f in _UPDATE_IN), dtheta, V)
    new = state._replace(**dict(zip(_UPDATE_OUT, sums, strict=True)))
    return _ring_write(state, new, dtheta, V, new.count > state.count)


_UPDATE_OUT = ("sign_net", "mag_sum", "mag_count", "S_vv", "S_tv", "s_tt", "count", "rejected")
_UPDATE_IN = (*_UPDATE_OUT, "v_tol", "forget")


def _update_sums(*args):
    """:func:`update`'s sums, on the fields it reads (``_UPDATE_IN``, then ``dtheta``, ``V``): the fields it writes
    besides the ring buffer (``_UPDATE_OUT``), a tuple."""
    fields, dtheta, V = dict(zip(_UPDATE_IN, args[:-2], strict=True)), args[-2], args[-1]
    n, m = fields["S_tv"].shape
    dtype = fields["S_tv"].dtype
    state = init(n, m, capacity=0, dtype=dtype)._replace(**fields)  # the fields update does not read: unused
    new = guarded_update(accumulate, state, dtheta, V, shape=(n, m), dtype=dtype, admit=fits, zero_is_identity=True)
    return tuple(getattr(new, f) for f in _UPDATE_OUT)


def signed_inverse_jacobian(state: EstimatorState) -> jax.Array:
    """Signed inverse Jacobian ``(n, m)`` in {-1, +1}: the heavier sign bucket (``sign_net >= 0``), ties -> +1
    (Eq. 10)."""
    return jnp.where(state.sign_net >= 0, 1.0, -1.0).astype(state.sign_net.dtype)


def magnitude_inverse_jacobian(state: EstimatorState) -> jax.Array:
    """Magnitude inverse Jacobian ``(n, m)``: mean of ``|dtheta_i / V_j|`` (Eq. 12), 0 where no valid sample."""
    cnt = state.mag_count  # (m,)
    inv = jnp.where(cnt > 0, 1.0 / jnp.where(cnt > 0, cnt, 1.0), 0.0)
    return state.mag_sum * inv[..., None, :]


def initial_guess(state: EstimatorState) -> jax.Array:
    """Initial inverse-Jacobian guess ``(n, m)``: signed * magnitude, elementwise (Eq. 13)."""
    return signed_inverse_jacobian(state) * magnitude_inverse_jacobian(state)


def buffer_mask(state: EstimatorState) -> jax.Array:
    """``(capacity,)`` bool: which ring-buffer rows hold samples (``(0,)`` without a buffer)."""
    capacity = state.dtheta_buf.shape[-2]
    return jnp.arange(capacity) < jnp.minimum(state.count, capacity)


def samples(state: EstimatorState) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Buffered samples ``(dtheta (K, n), V (K, m), mask (K,))`` with ``K = capacity``; unused rows are zero."""
    return state.dtheta_buf, state.v_buf, buffer_mask(state)


def objective(state: EstimatorState, J: ArrayLike) -> jax.Array:
    """Eq. 14 objective ``sum_k w_k ||dtheta_k - J V_k||^2`` over every accepted sample (scalar, actuator units^2).

    From the statistics: ``s_tt - 2 <J, S_tv> + <J S_vv, J>`` (Frobenius inner
    products), floored at 0 against round-off; ``w_k = forget^(K - k)``
    (all 1 without forgetting). :func:`buffer_objective` is the same sum over
    the buffered samples only.
    """
    J = jnp.asarray(J, state.S_tv.dtype)
    f = state.s_tt - 2.0 * jnp.sum(J * state.S_tv) + jnp.sum((J @ state.S_vv) * J)
    return jnp.maximum(f, 0.0)


def buffer_objective(state: EstimatorState, J: jax.Array) -> jax.Array:
    """Eq. 14 objective ``sum_k ||dtheta_k - J V_k||^2`` over the buffered samples (scalar; 0 without a buffer)."""
    theta, V, mask = samples(state)
    r = theta - V @ J.T
    return jnp.sum(jnp.where(mask[:, None], r, 0.0) ** 2)


def check_thresholds(eps, eps_rel=0.0):
    """Eager check of the Sec. IV-D thresholds where they are concrete: ``eps >= 0``, ``eps_rel >= 0``, not both 0,
    no NaN."""
    check_scalar("eps", eps, ge=0.0, finite=False)
    check_scalar("eps_rel", eps_rel, ge=0.0, finite=False)
    if not (is_concrete_zero(eps) and is_concrete_zero(eps_rel)):
        return
    raise ValueError("eps and eps_rel are both 0: the Sec. IV-D test could never hold; set eps > 0 or eps_rel > 0")


def is_concrete_zero(x) -> bool:
    return not isinstance(x, jax.core.Tracer) and bool(np.all(np.asarray(x) == 0))


def _both_within(deltas: jax.Array, norms: jax.Array, fresh: jax.Array, eps, eps_rel) -> jax.Array:
    """The Sec. IV-D test on the last two records ``(..., 2)``: each followed new data and
    ``||J_t - J_{t-1}||_F <= eps + eps_rel ||J_t||_F`` -> ``(...)`` bool."""
    return jnp.all(fresh & (deltas <= eps + eps_rel * norms), axis=-1)


def record(state: EstimatorState, J: ArrayLike, eps: ArrayLike, eps_rel: ArrayLike = 0.0, *,
           delta: ArrayLike | None = None, norm: ArrayLike | None = None, min_count: ArrayLike = 0) -> EstimatorState:
    """Record estimate ``J_t (n, m)`` for the convergence test of Sec. IV-D.

    Stores ``delta_t = ||J_t - J_{t-1}||_F`` (with ``J_0 = 0``, Algorithm 1
    line 1) and, the first time the last two records both satisfy
    ``delta <= eps + eps_rel ||J||_F`` and both followed at least one newly
    accepted sample, the iteration number in ``converged_at`` (1-based count of
    recorded estimates). A record with no new data never counts, so a stream
    whose samples are all rejected never converges, and iteration 1 never
    converges (the test is twice in a row). ``eps`` is absolute
    (inverse-Jacobian units); ``eps_rel`` relative to the estimate's size, for
    systems whose inverse Jacobians are far from unit norm (a fingertip of
    40 rad/m, a large arm of 0.5 rad/m): one threshold then serves all.
    ``delta`` (optional, ``()``): ``||J - state.estimate||_F`` where the
    caller has it already (for a rank-one update ``e k^T`` it is
    ``||e|| ||k||``), which saves a pass over ``J``; default: computed here.
    ``norm`` (optional, ``()``): ``||J||_F`` where the caller has it (or
    computes it in a form that fuses better, as a plain reduction); default:
    computed here (equal up to summation order).
    ``min_count`` (``()`` int, may be traced): the test counts only once at
    least this many samples were accepted (0: from the start, the paper's).
    """
    n, m, _ = sizes(state)
    check_array("J", J, (n, m))
    check_thresholds(eps, eps_rel)
    dtype = state.estimate.dtype
    J = jnp.asarray(J, dtype)
    if delta is not None:
        check_array("delta", delta, ())
        delta = jnp.asarray(delta, dtype)
    if norm is not None:
        check_array("norm", norm, ())
        norm = jnp.asarray(norm, dtype)
    if delta is None and norm is None and _native_thresholds(dtype, eps, eps_rel, min_count):
        # the native CPU kernel where it is built (selfid_jax.math.native), _record_fields elsewhere
        fields = native.call("record", _record_fields, J, *(getattr(state, f) for f in _RECORD_IN),
                             jnp.asarray(eps, dtype), jnp.asarray(eps_rel, dtype), jnp.asarray(min_count, jnp.int32))
        return state._replace(**dict(zip(_RECORD_OUT, fields, strict=True)))
    return _record(state, J, eps, eps_rel, delta, norm, min_count)


def _native_thresholds(dtype, eps, eps_rel, min_count) -> bool:
    """Whether the native record (alone or in the fused step) takes these thresholds: ``eps``, ``eps_rel`` of the
    state's float ``dtype`` (no promotion) and an integer ``min_count``."""
    return (all(jnp.result_type(x, dtype) == dtype for x in (eps, eps_rel))
            and bool(jnp.issubdtype(jnp.result_type(min_count), jnp.integer)))


_RECORD_OUT = ("estimate", "last_deltas", "last_norms", "last_fresh", "recorded_count", "iteration", "converged_at")
_RECORD_IN = ("estimate", "last_deltas", "last_norms", "last_fresh", "count", "recorded_count", "iteration",
              "converged_at")


def _record_fields(J, *args):
    """:func:`record` on ``J``, the fields it reads (``_RECORD_IN``), ``eps``, ``eps_rel``, ``min_count``: the
    fields it writes (``_RECORD_OUT``, the first the new estimate ``J``), a tuple."""
    fields, (eps, eps_rel, min_count) = dict(zip(_RECORD_IN, args[:-3], strict=True)), args[-3:]
    n, m = J.shape
    state = init(n, m, capacity=0, dtype=J.dtype)._replace(**fields)  # the fields record does not read: unused
    new = _record(state, J, eps, eps_rel, None, None, min_count)
    return tuple(getattr(new, f) for f in _RECORD_OUT)


def _record(state: EstimatorState, J: jax.Array, eps, eps_rel, delta, norm, min_count) -> EstimatorState:
    """:func:`record` after its checks (``delta``, ``norm``: None or ``()`` arrays of the state's dtype)."""
    if delta is None:
        delta = jnp.sqrt(small_sum((J - state.estimate) ** 2))
    if norm is None:
        norm = jnp.sqrt(small_sum(J**2))
    iteration = state.iteration + 1
    deltas = jnp.stack([state.last_deltas[1], delta])
    norms = jnp.stack([state.last_norms[1], norm])
    fresh = jnp.stack([state.last_fresh[1], state.count > state.recorded_count])
    first = _both_within(deltas, norms, fresh, eps, eps_rel) & (state.converged_at < 0) & (state.count >= min_count)
    return state._replace(
        estimate=J,
        last_deltas=deltas,
        last_norms=norms,
        last_fresh=fresh,
        recorded_count=state.count,
        iteration=iteration,
        converged_at=jnp.where(first, iteration, state.converged_at),
    )


def converged(state: EstimatorState, eps: ArrayLike, eps_rel: ArrayLike = 0.0) -> jax.Array:
    """True iff the last two records pass the Sec. IV-D test of :func:`record` (``()`` bool, ``(...)`` if batched)."""
    check_thresholds(eps, eps_rel)
    return _both_within(state.last_deltas, state.last_norms, state.last_fresh, eps, eps_rel)


def convergence_iteration(estimates: jax.Array, eps, eps_rel=0.0, *, accepted=None) -> jax.Array:
    """First iteration at which the Sec. IV-D test holds over a sequence of estimates; ``()`` int32, -1 if never.

    ``estimates (T, n, m)``: ``J_1 .. J_T``, the estimate after each sample
    (inverse-Jacobian units); ``accepted (T,)`` bool: whether sample ``t`` was
    accepted (default: all). The test of :func:`record` (``eps``, ``eps_rel``
    may be traced): the smallest 1-based ``t >= 2`` where records ``t - 1`` and
    ``t`` both followed an accepted sample and both changed by at most
    ``eps + eps_rel ||J||_F``, with ``J_0 = 0``; equal to ``converged_at``
    after recording the sequence.
    """
    check_array("estimates", estimates, (None, None, None))
    check_thresholds(eps, eps_rel)
    T = np.shape(estimates)[0]
    if T == 0:  # static: an empty sequence never converges
        return jnp.full((), -1, jnp.int32)
    fresh = jnp.ones((T,), bool) if accepted is None else jnp.asarray(accepted, bool)
    check_array("accepted", fresh, (T,), floating=False)
    prev = jnp.concatenate([jnp.zeros_like(estimates[:1]), estimates[:-1]], axis=0)
    deltas = jnp.sqrt(jnp.sum((estimates - prev) ** 2, axis=(1, 2)))  # (T,)
    norms = jnp.sqrt(jnp.sum(estimates**2, axis=(1, 2)))

    def pairs(x, first):  # (T, 2): (value at t - 1, value at t), `first` before the sequence
        return jnp.stack([jnp.concatenate([jnp.full((1,), first, x.dtype), x[:-1]]), x], axis=-1)

    both = _both_within(pairs(deltas, jnp.inf), pairs(norms, 0.0), pairs(fresh, False), eps, eps_rel)
    return jnp.where(jnp.any(both), jnp.argmax(both) + 1, -1).astype(jnp.int32)
