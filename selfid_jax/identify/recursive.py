"""The full self-ID step with Eq. 14's closed form kept recursively once ``S_vv`` has full rank.

Once the Gram matrix ``S_vv = sum w_k V_k V_k^T`` has full rank, the
closed-form refinement (Eq. 14, :func:`selfid_jax.identify.refine.statistics_closed_form`)
is the least-squares solution ``J = S_tv S_vv^-1`` whatever the initial guess.
Folding one more sample ``(dtheta, V)`` with forgetting ``lam`` changes it by a
rank-one (Sherman-Morrison) step at recursive-least-squares cost::

    g = P V,   k = g / (lam + V^T g),   e = dtheta - J V
    J <- J + e k^T,   P <- (P - k g^T) / lam        (P = S_vv^-1, symmetrised)

:func:`step` is one sample of Algorithm 1 (``update``, ``initial_guess``, the
closed-form refinement and ``record``, as :func:`selfid_jax.identify.algorithm.self_identify`
runs them) that takes this step where it is exact and re-solves from the
statistics where it is not: before ``S_vv`` reaches full rank (the
rank-deficient start, where the minimum-norm correction of the initial guess
is the estimate), when the conditioning test below fails, when the step is
not finite, and every ``resolve_every`` accepted samples if asked (a bound on
float drift). The re-solve is the batch closed form itself, so the estimate
equals it up to round-off (float64: 1e-9 relative; see ``tests/test_recursive.py``).

The rank test: the batch closed form counts a direction as excited when its
Rayleigh quotient exceeds ``rcond tr(S_vv)``. Every Rayleigh quotient is at
least ``lambda_min(S_vv) >= 1 / tr(P)``, so the step is taken only while
``rcond tr(S_vv) tr(P) < 1/2``, where the batch form keeps every direction by
a margin of 2 (forgetting that lets a direction fade hands it back to the
batch form, as it should). The steps start only from a batch solve whose
round-off bound ``eps tr(P) tr(S_vv)`` is below :data:`ENTER_TOL`, since their
error is that of the solve they start from (decaying as later samples
outweigh it): float32 data too ill-conditioned for that stays on the batch form.

Under ``vmap`` the choice between the two is made for the whole batch at once
(:func:`cond_any`, a custom batching rule): the re-solve runs, for every
member, only where at least one member needs it, and the recursive step
alone otherwise (a plain ``lax.cond`` under ``vmap`` would run both every
time). Derivatives go through a ``custom_jvp`` whose rule differentiates the
plain ``lax.cond``, so ``grad`` and ``jvp`` work (through the same formula
either way).

Two forms. :func:`step` decides per sample, before the step, from the carry
and the sample alone (the bound ``tr(P_new) <= tr(P) / lam`` and the new
trace): the live loop's form, one sample per call. :func:`run` takes a block
of samples: the first few by the batch form (:func:`exact_step`), the rest by
the branch-free rank-one step (:func:`fast_step`), and re-runs the block's
tail by the batch form if any rank-one step was not exact
(:func:`fallback_scan`): one branch per block, the fleet form under ``vmap``,
and the form :func:`selfid_jax.identify.algorithm.self_identify` runs. On
XLA's CPU backend a conditional inside the per-sample loop splits the
step's one fused pass over the state into one pass per field (and copies
the carry), which costs more than the rank-one step saves; hence the block.
Within :func:`fast_step` the sample's terms (its acceptance and weights, and
``P V``, the gain and the residual of the rank-one step) pass through
:func:`once`, so that XLA computes each once per estimator instead of once
per entry of every field it updates.
:func:`pack` and :func:`packed_step` pass the state through ``jit`` as two
flat arrays instead of 21, for the per-call cost at batch 1. A live loop that
waits for every result should also run its process with synchronous CPU
dispatch (``jax.config.update("jax_cpu_enable_async_dispatch", False)`` before
JAX's first computation): each call then runs on the calling thread, without
a hand-off to the CPU client's thread (``benchmarks/rls_floor.py``: p50 about
0.05 ms async, 0.02 ms sync for the packed step, n = 6, m = 3).

Size: about 500 lines, one algorithm: the recursive step, its exact fallback, the scan that switches between
them and the packed state form share private helpers (``cond_any``, the rank-one update).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from selfid_jax.identify import estimator as E
from selfid_jax.identify.refine import statistics_closed_form
from selfid_jax.identify.step import sample_step
from selfid_jax.math.checks import check_array, check_positive_int, check_scalar
from selfid_jax.math.kernels import small_sum
from selfid_jax.math.linalg import default_rcond, psd_pinv

ENTER_TOL = 1e-3
"""The rank-one steps start from a batch solve only where ``eps tr(P) tr(S_vv)`` (a bound on its relative round-off)
is below this: in float32 a Gram matrix of condition number up to about 17,000, in float64 any the rank test keeps."""


class Recursion(NamedTuple):
    """What the recursive step carries besides the :class:`~selfid_jax.identify.estimator.EstimatorState`.

    ``P (m, m)``: ``S_vv^-1`` (task units^-2) while ``full``, else unused;
    ``full ()`` bool: ``state.estimate`` is ``S_tv S_vv^-1`` and ``P`` its
    inverse Gram matrix, so the next sample may take the rank-one step.
    """

    P: jax.Array
    full: jax.Array


def init(m: int, dtype=None) -> Recursion:
    """Empty :class:`Recursion` for ``m`` task dimensions (``full = False``: the first samples re-solve)."""
    from selfid_jax.math.checks import float_dtype

    dtype = float_dtype() if dtype is None else dtype
    return Recursion(P=jnp.zeros((m, m), dtype), full=jnp.zeros((), bool))


def cond_any(pred: jax.Array, true_fn: Callable, false_fn: Callable, operands: Any):
    """``true_fn(operands)`` if ``pred`` else ``false_fn(operands)``; under ``vmap``, one branch choice per batch.

    Unbatched it is ``lax.cond``. Under ``vmap`` (any depth) member ``b`` gets
    ``true_fn`` of its operands where ``pred[b]`` and ``false_fn`` elsewhere,
    as ``lax.cond`` would give, but ``true_fn`` is evaluated (for the whole
    batch, then selected) only when ``any(pred)``; otherwise only ``false_fn``
    runs. Use it where ``true_fn`` is expensive and rarely needed. Both
    branches must return the same pytree structure, shapes and dtypes.
    Differentiable (``jvp`` and ``grad``: the rule differentiates ``lax.cond``).
    """
    # Values the branches close over (traced ones, batched under an outer vmap, say) become explicit
    # operands: a custom batching rule sees only its arguments.
    t_fn, t_consts = _hoist(true_fn, operands)
    f_fn, f_consts = _hoist(false_fn, operands)
    return _cond_any_jvp(lambda o: t_fn(o[0], o[1]), lambda o: f_fn(o[0], o[2]), pred, (operands, t_consts, f_consts))


def _hoist(fn, operands):
    """``(g, consts)`` with ``g(operands, consts) == fn(operands)`` and every value ``fn`` closes over in ``consts``."""
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(operands)
    out_tree = jax.tree.structure(out_shape)

    def g(ops, consts):
        return jax.tree.unflatten(out_tree, jax.core.eval_jaxpr(closed.jaxpr, consts, *jax.tree.leaves(ops)))

    return g, list(closed.consts)


def _select(pred, a, b):
    return jax.tree.map(lambda x, y: jnp.where(pred, x, y), a, b)


def _make_cond_any(true_fn, false_fn):
    @jax.custom_batching.custom_vmap
    def f(pred, operands):
        return jax.lax.cond(pred, true_fn, false_fn, operands)

    @f.def_vmap
    def rule(axis_size, in_batched, pred, operands):
        pred_b, ops_b = in_batched
        operands = jax.tree.map(lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)),
                                operands, ops_b)
        preds = pred if pred_b else jnp.broadcast_to(pred, (axis_size,))
        sel = jax.vmap(lambda p, o: _select(p, true_fn(o), false_fn(o)))
        inner = _make_cond_any(lambda po: sel(*po), lambda po: jax.vmap(false_fn)(po[1]))
        out = inner(jnp.any(preds), (preds, operands))  # itself batched again under an outer vmap
        return out, jax.tree.map(lambda _: True, out)

    return f


def _cond_any_jvp(true_fn, false_fn, pred, operands):
    @jax.custom_jvp
    def f(pred, operands):
        return _make_cond_any(true_fn, false_fn)(pred, operands)

    @f.defjvp
    def f_jvp(primals, tangents):
        p, ops = primals
        return jax.jvp(lambda o: jax.lax.cond(p, true_fn, false_fn, o), (ops,), (tangents[1],))

    return f(pred, operands)


def _trace(S):
    return small_sum(jnp.stack([S[k, k] for k in range(S.shape[-1])]))


def once(x: jax.Array) -> jax.Array:
    """``x`` (any shape, float or bool) with the same values, as a value XLA's CPU backend computes once.

    Vmapped, a per-estimator value that feeds the update of a field (``k`` in
    ``J + e k^T``, a sample's weights in the sums) is fused by XLA into that
    update and recomputed for every entry of every field it feeds. XLA does
    not duplicate a division into its consumers, so ``x / (1 + 0 x)``
    (exactly ``x`` where finite; a non-finite entry stays non-finite, ``inf``
    reads ``nan``) is computed once per estimator and read by them; a bool is
    passed as 0.0 / 1.0. ``once(x)`` equals ``x``; a step with it equals the
    step without it up to round-off, since XLA rounds the arithmetic it fuses
    around it differently (1 to 2 ulp seen in float32;
    ``tests/test_recursive.py`` bounds the vmapped block's state at 1e-5
    relative), and a later XLA that simplified the division away would only
    lose the speed. In :func:`fast_step`'s loop body: about 970 -> 790 flops
    and 3.1 -> 2.1 kB per estimator-step as XLA counts them (n = 6, m = 3).
    """
    if x.dtype == jnp.bool_:
        return once(x.astype(jnp.float32)) > 0
    return x / (1.0 + 0.0 * x)


def _rank_one(J, P, dtheta, V, lam, fence=None):
    """The Sherman-Morrison step of the module docstring: ``(J (n, m), P (m, m), denominator (), ||e k^T||_F ())``.

    ``fence`` (optional, e.g. :func:`once`) is applied to ``g``, the denominator, ``k`` and ``e``.
    """
    m = P.shape[-1]
    fence = (lambda x: x) if fence is None else fence
    g = fence(small_sum(P * V[None, :], axis=1))  # P V (P symmetric)
    den = fence(lam + small_sum(V * g))
    k = fence(g / jnp.where(den > 0, den, 1.0))
    e = fence(dtheta - small_sum(J * V[None, :], axis=1))
    J = J + e[:, None] * k[None, :]
    P = (P - k[:, None] * g[None, :]) / lam
    P = 0.5 * (P + P.T) if m > 1 else P
    # the change of a rank-one update, ||e k^T||_F = ||e|| ||k|| (Sec. IV-D's delta without a pass over J)
    return J, P, den, jnp.sqrt(small_sum(e * e) * small_sum(k * k))


def _resolve(S_vv, S_tv, J0, rcond):
    """Batch closed form (Eq. 14) and the inverse Gram matrix: ``(J (n, m), P (m, m), full ())``."""
    J = statistics_closed_form(S_vv, S_tv, J0, rcond=rcond)
    return (J, *_inverse_gram(S_vv, J, rcond))


def _inverse_gram(S_vv, J, rcond):
    """``(P (m, m), full ())`` for the rank-one steps after the batch closed form ``J (n, m)`` of ``S_vv``."""
    P, N = psd_pinv(S_vv, rcond=rcond)
    # Enter the rank-one steps only from a well-posed solve: their error is that of the solve they start
    # from, decaying as later samples outweigh it (eps cond(S_vv) <= eps tr(P) tr(S_vv) < ENTER_TOL).
    entry = _trace(P) * _trace(S_vv) * jnp.finfo(S_vv.dtype).eps < ENTER_TOL
    full = jnp.all(N == 0) & _conditioned(P, S_vv, rcond) & entry & jnp.all(jnp.isfinite(J))
    return P, full


def _conditioned(P, S, rcond):
    t = _trace(P) * _trace(S) * rcond
    return jnp.isfinite(t) & (t < 0.5) & (t > 0)


def step(
    state: E.EstimatorState,
    rec: Recursion,
    dtheta: ArrayLike,
    V: ArrayLike,
    eps: ArrayLike,
    eps_rel: ArrayLike = 0.0,
    *,
    rcond: ArrayLike | None = None,
    resolve_every: int = 0,
) -> tuple[E.EstimatorState, Recursion]:
    """One self-ID sample ``(dtheta (n,) actuator units, V (m,) task units)``: update, refine, record.

    Equal, up to round-off, to ``record(update(state, dtheta, V), J, eps,
    eps_rel)`` with ``J = statistics_closed_form(S_vv, S_tv, initial_guess(.),
    rcond=rcond)`` of the updated state (the closed-form step of
    :func:`selfid_jax.identify.algorithm.self_identify`), where ``rec`` is the
    :class:`Recursion` returned with ``state`` by the previous call (or
    :func:`init` with a fresh state). Returns ``(state, rec)``; the refined
    estimate is ``state.estimate`` ``(n, m)``. See the module docstring for
    when the rank-one step is taken. ``resolve_every`` (static, >= 0): also
    re-solve after every ``resolve_every``-th accepted sample (0: never).
    The sample screen, forgetting and the convergence record are those of
    :mod:`~selfid_jax.identify.estimator`. Jit, vmap and differentiate.
    """
    n, m, _ = E.sizes(state)
    check_array("P", rec.P, (m, m))
    E.check_thresholds(eps, eps_rel)
    if rcond is not None:
        check_scalar("rcond", rcond, ge=0.0)
    resolve_every = E.check_nonnegative_int("resolve_every", resolve_every)
    dtype = state.S_tv.dtype
    rcond = default_rcond(m, dtype) if rcond is None else jnp.asarray(rcond, dtype)
    check_array("dtheta", dtheta, (n,))
    check_array("V", V, (m,))
    dt, vv = jnp.asarray(dtheta, dtype), jnp.asarray(V, dtype)
    # Whether the rank-one step will be exact, from the carry and the sample alone (no part of the
    # step itself), so that the branch below only feeds the one fused pass of the step: with
    # lam = forget, tr(S_vv) becomes lam tr(S_vv) + ||V||^2 and tr(P) at most tr(P) / lam.
    lam = state.forget
    sq = small_sum(vv * vv)
    bound = _trace(rec.P) / lam * (lam * _trace(state.S_vv) + sq) * rcond
    ok = rec.full & (bound < 0.5) & (bound > 0)  # False for a non-finite sample too
    if resolve_every:
        ok = ok & ((state.count + 1) % resolve_every != 0)

    def batch(ops):
        old, _, d_, v_ = ops
        nw = E.update(old, d_, v_)
        return _resolve(nw.S_vv, nw.S_tv, E.initial_guess(nw), rcond)

    def keep(ops):
        old, r, _, _ = ops
        return old.estimate, r.P, r.full

    J_fix, P_fix, full_fix = cond_any(~ok, batch, keep, (state, rec, dt, vv))
    new = E.update(state, dt, vv)
    accepted = new.count > state.count
    d = jnp.where(accepted, dt, 0.0)
    v = jnp.where(accepted, vv, 0.0)
    lam = jnp.where(accepted, state.forget, 1.0).astype(dtype)
    J, P, _, _ = _rank_one(state.estimate, rec.P, d, v, lam)
    J = jnp.where(ok, J, J_fix)
    P = jnp.where(ok, P, P_fix)
    return E.record(new, J, eps, eps_rel), Recursion(P=P, full=ok | full_fix)


def exact_step(state, rec, dtheta, V, eps, eps_rel=0.0, *, rcond=None):
    """The step of :func:`step` by the batch closed form, branch-free: ``(state, rec)``.

    :func:`selfid_jax.identify.step.sample_step` with the closed form (the
    step of the closed-form path of
    :func:`selfid_jax.identify.algorithm.self_identify`, so bit for bit its
    estimate) and the :class:`Recursion` for the next sample
    (``P = S_vv^+``, ``full`` per the rank test).
    """
    m = state.S_vv.shape[-1]
    rc = default_rcond(m, state.S_vv.dtype) if rcond is None else rcond
    new, _ = sample_step(state, dtheta, V, eps, eps_rel, method="closed_form", options=(("rcond", rc),))
    P, full = _inverse_gram(new.S_vv, new.estimate, rc)
    return new, Recursion(P=P, full=full)


def fast_step(state, rec, dtheta, V, eps, eps_rel=0.0, *, rcond=None, resolve_every: int = 0):
    """The rank-one step alone, branch-free: ``(state, rec)`` with ``rec.full`` False where it was not exact.

    Where the returned ``rec.full`` is True the estimate equals that of
    :func:`exact_step` up to round-off; where it is False (the rank test of the
    module docstring failed, the step was not finite, ``rec.full`` was already
    False, or a ``resolve_every``-th accepted sample) the result must be
    discarded and the sample re-run by :func:`exact_step`, as :func:`run` does.
    """
    m = state.S_vv.shape[-1]
    # the per-sample terms computed once per estimator, not per entry of each field they update (see `once`)
    new = E.update(state, dtheta, V, once=once)
    dtype = new.S_vv.dtype
    rc = default_rcond(m, dtype) if rcond is None else rcond
    accepted = new.count > state.count
    d = jnp.where(accepted, jnp.asarray(dtheta, dtype), 0.0)
    v = jnp.where(accepted, jnp.asarray(V, dtype), 0.0)
    lam = jnp.where(accepted, state.forget, 1.0).astype(dtype)
    J, P, den, delta = _rank_one(state.estimate, rec.P, d, v, lam, fence=once)
    t = _trace(P) * _trace(new.S_vv) * rc
    # ||J||_F as one reduction, which XLA fuses with J's square (the record's unrolled sum takes a pass of its own)
    new = E.record(new, J, eps, eps_rel, delta=delta, norm=jnp.sqrt(jnp.sum(J * J)))
    # ||J||_F is finite iff J is, or overflows: then the batch form re-runs
    ok = rec.full & (den > 0) & (t < 0.5) & (t > 0) & jnp.isfinite(new.last_norms[1])
    if resolve_every:
        ok = ok & ~(accepted & (new.count % resolve_every == 0))
    return new, Recursion(P=P, full=ok)


def fallback_scan(fast_body: Callable, exact_body: Callable, ok_of: Callable, carry, xs, *, warmup: int,
                  block: int | None = None):
    """``lax.scan`` of ``exact_body`` over ``xs``, computed where it can be by the cheaper ``fast_body``.

    ``exact_body(carry, x) -> (carry, y)`` and ``fast_body`` (same signature
    and types) are scan bodies; ``ok_of(carry) -> ()`` bool says whether the
    fast step just taken was exact. The first ``warmup`` (static) elements of
    ``xs`` run ``exact_body``; the rest run in blocks of ``block`` (static;
    default: one block) elements by ``fast_body``, and a block any of whose steps was not exact
    is run again by ``exact_body`` from where it started (under ``vmap`` by
    :func:`cond_any`: for the whole batch, only when a member needs it).
    Returns ``(carry, ys)`` as ``lax.scan`` does, equal to the exact scan up
    to round-off.
    """
    T = jax.tree.leaves(xs)[0].shape[0]
    warmup = min(max(int(warmup), 0), T)
    block = max(T - warmup, 1) if block is None else max(int(block), 1)
    carry, ys_head = jax.lax.scan(exact_body, carry, jax.tree.map(lambda x: x[:warmup], xs))

    def fast(c, x):
        c, good = c
        c, y = fast_body(c, x)
        return (c, good & ok_of(c)), y

    def one_block(c0, xs_b):
        (c_f, good), ys_f = jax.lax.scan(fast, (c0, jnp.ones((), bool)), xs_b)

        def redo(ops):
            c, xs_, _ = ops
            return jax.lax.scan(exact_body, c, xs_)

        return cond_any(~good, redo, lambda ops: ops[2], (c0, xs_b, (c_f, ys_f)))

    n_blocks, rest = divmod(T - warmup, block)
    parts = [ys_head]
    if n_blocks:
        body = jax.tree.map(lambda x: x[warmup:warmup + n_blocks * block].reshape((n_blocks, block) + x.shape[1:]),
                            xs)
        carry, ys = jax.lax.scan(one_block, carry, body)
        parts.append(jax.tree.map(lambda y: y.reshape((n_blocks * block,) + y.shape[2:]), ys))
    if rest:
        carry, ys = one_block(carry, jax.tree.map(lambda x: x[T - rest:], xs))
        parts.append(ys)
    return carry, jax.tree.map(lambda *a: jnp.concatenate(a), *parts)


def run(
    state: E.EstimatorState,
    rec: Recursion,
    dtheta: ArrayLike,
    V: ArrayLike,
    eps: ArrayLike,
    eps_rel: ArrayLike = 0.0,
    *,
    warmup: int | None = None,
    block: int | None = None,
    rcond: ArrayLike | None = None,
    resolve_every: int = 0,
    history: bool = True,
) -> tuple[E.EstimatorState, Recursion, jax.Array | None, jax.Array | None]:
    """:func:`step` over a block of samples ``dtheta (T, n)``, ``V (T, m)``: ``(state, rec, estimates, deltas)``.

    ``estimates (T, n, m)``: the refined estimate after each sample;
    ``deltas (T,)``: its ``||J_t - J_{t-1}||_F``. The first ``warmup``
    samples (static; default ``m + 5`` for a state with no sample yet, else 0;
    a traced ``state`` counts as one with samples, so pass ``warmup`` when
    ``state`` is a ``jit`` argument: the estimates agree to round-off, the speed does not)
    run the batch closed form (:func:`exact_step`), the rest the rank-one step
    (:func:`fast_step`) in blocks of ``block`` (static; default one block), a block re-run by the
    batch form if any of its steps was not exact (:func:`fallback_scan`). Equal to ``T`` calls of :func:`step` up to
    round-off; under ``vmap`` it is the fleet form (one branch per block, not
    per sample). ``history=False`` (static) keeps no per-sample record:
    ``estimates`` and ``deltas`` are None and the block writes only the state
    (the final estimate is ``state.estimate``). Jit, vmap and differentiate.
    """
    n, m, _ = E.sizes(state)
    check_array("dtheta", dtheta, (None, n))
    T = jnp.shape(dtheta)[0]
    check_array("V", V, (T, m))
    check_array("P", rec.P, (m, m))
    E.check_thresholds(eps, eps_rel)
    if rcond is not None:
        check_scalar("rcond", rcond, ge=0.0)
    resolve_every = E.check_nonnegative_int("resolve_every", resolve_every)
    if warmup is None:
        warmup = m + 5 if (not isinstance(state.count, jax.core.Tracer) and int(state.count) == 0) else 0
    warmup = E.check_nonnegative_int("warmup", warmup)
    if block is not None:
        block = check_positive_int("block", block)
    dtype = state.S_tv.dtype
    xs = (jnp.asarray(dtheta, dtype), jnp.asarray(V, dtype))

    def out(c):
        return (c[0].estimate, c[0].last_deltas[1]) if history else ()

    def exact(c, x):
        (s, r), (dth, v) = c, x
        c = exact_step(s, r, dth, v, eps, eps_rel, rcond=rcond)
        return c, out(c)

    def fast(c, x):
        (s, r), (dth, v) = c, x
        c = fast_step(s, r, dth, v, eps, eps_rel, rcond=rcond, resolve_every=resolve_every)
        return c, out(c)

    (state, rec), ys = fallback_scan(fast, exact, lambda c: c[1].full, (state, rec), xs, warmup=warmup, block=block)
    return (state, rec, *ys) if history else (state, rec, None, None)


def pack(state: E.EstimatorState, rec: Recursion) -> tuple[jax.Array, jax.Array]:
    """``(state, rec)`` as two flat arrays: ``floats (L,)`` (state dtype) and ``ints (K,)`` int32.

    For the live loop at batch 1, where each array passed through ``jit``
    costs dispatch time: :func:`packed_step` takes and returns these two
    instead of the 21 leaves. :func:`unpack` inverts it.
    """
    leaves = jax.tree.leaves((state, rec))
    dtype = state.S_tv.dtype
    floats = [x.ravel() for x in leaves if jnp.issubdtype(x.dtype, jnp.floating)]
    ints = [x.astype(jnp.int32).ravel() for x in leaves if not jnp.issubdtype(x.dtype, jnp.floating)]
    return jnp.concatenate(floats).astype(dtype), jnp.concatenate(ints)


def unpack(floats: jax.Array, ints: jax.Array, n: int, m: int, capacity: int = 0) -> tuple[E.EstimatorState, Recursion]:
    """Inverse of :func:`pack` for ``n`` actuators, ``m`` task dimensions and a ``capacity``-row buffer."""
    template = jax.eval_shape(lambda: (E.init(n, m, capacity=capacity, dtype=floats.dtype), init(m, floats.dtype)))
    leaves, tree = jax.tree.flatten(template)
    sizes = [(int(np.prod(t.shape, dtype=int)), bool(jnp.issubdtype(t.dtype, jnp.floating))) for t in leaves]
    fo, io = sum(k for k, f in sizes if f), sum(k for k, f in sizes if not f)
    if (fo, io) != (floats.shape[-1], ints.shape[-1]):
        raise ValueError(f"unpack: expected {fo} floats and {io} ints for n={n}, m={m}, capacity={capacity}, "
                         f"got {floats.shape[-1]} and {ints.shape[-1]}")
    out, fo, io = [], 0, 0
    for t in leaves:
        size = int(np.prod(t.shape, dtype=int))
        if jnp.issubdtype(t.dtype, jnp.floating):
            out.append(floats[fo:fo + size].reshape(t.shape))
            fo += size
        else:
            out.append(ints[io:io + size].reshape(t.shape).astype(t.dtype))
            io += size
    return jax.tree.unflatten(tree, out)


def packed_step(floats, ints, dtheta, V, eps, eps_rel=0.0, *, n: int, m: int, capacity: int = 0, **options):
    """:func:`step` on the packed form of :func:`pack`: returns the new ``(floats, ints)``.

    ``n``, ``m``, ``capacity`` are static; ``options`` as :func:`step`. Jit it
    (with ``static_argnames=("n", "m", "capacity")``); the estimate is
    ``unpack(...)[0].estimate`` or, without unpacking, ``floats[k:k + n m]``
    at the offset of ``estimate``.
    """
    state, rec = unpack(floats, ints, n, m, capacity)
    return pack(*step(state, rec, dtheta, V, eps, eps_rel, **options))
