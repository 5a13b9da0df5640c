"""One self-ID sample: update (Eq. 6-12), initial guess (Eq. 13), refine (Eq. 14), record (Sec. IV-D).

:func:`sample_step` is the per-sample identification step every path runs:
Algorithm 1 after each random actuation
(:func:`selfid_jax.identify.algorithm.self_identify`), the batch closed form of
the recursive estimator (:func:`selfid_jax.identify.recursive.exact_step`),
self-ID from a recorded log (:func:`selfid_jax.robot.offline.fit_samples`) and
the online runner (:mod:`selfid_jax.robot.live`). Pure: it jits, vmaps and
differentiates; the per-sample diagnostics go out in a :class:`StepInfo`, not
into the state.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from selfid_jax.identify import estimator
from selfid_jax.identify.refine import _minimum_norm_correction, refine
from selfid_jax.math import native
from selfid_jax.math.checks import check_array, check_scalar
from selfid_jax.math.linalg import default_rcond

__all__ = ["StepInfo", "sample_step"]


class StepInfo(NamedTuple):
    """Per-sample diagnostics of :func:`sample_step` (not carried forward)."""

    estimate: jax.Array  # (n, m) refined estimate J_t after the sample (Eq. 14)
    delta: jax.Array  # () ||J_t - J_{t-1}||_F, with J_0 = 0 (Sec. IV-D)
    threshold: jax.Array  # () eps + eps_rel ||J_t||_F: the bound delta is tested against
    accepted: jax.Array  # () bool: the estimator took the sample (not non-finite, all-zero or overflowing)


def sample_step(state: estimator.EstimatorState, dtheta: ArrayLike, V: ArrayLike, eps: ArrayLike,
                eps_rel: ArrayLike, *, method: str, options: tuple = (), min_count: ArrayLike = 0
                ) -> tuple[estimator.EstimatorState, StepInfo]:
    """One sample ``(dtheta (n,) actuator units, V (m,) task units)``: update, guess, refine, record.

    Update (Eq. 6-12), initial guess (Eq. 13), refinement (Eq. 14), record for the convergence test (Sec. IV-D).

    Returns the new state (its ``estimate (n, m)`` the refined ``J_t``) and a
    :class:`StepInfo`. ``method`` (``"closed_form"`` or ``"optax"``; see
    :data:`selfid_jax.identify.refine.METHODS`) and ``options`` (``(key,
    value)`` pairs of keyword options for
    :func:`~selfid_jax.identify.refine.refine`, sorted where they must hash,
    as a ``jit`` static argument) are static; ``eps`` (inverse-Jacobian units)
    and ``eps_rel`` (relative to ``||J_t||_F``) may be traced, and so may
    option values that :func:`~selfid_jax.identify.refine.refine` traces
    (``rcond``, ``ridge``) when ``sample_step`` is not jitted with ``options``
    static. A rejected sample (non-finite, all-zero) leaves the statistics
    as they were and is still recorded, as a record with no new data
    (:func:`selfid_jax.identify.estimator.record`). ``min_count`` (may be
    traced): convergence counts only from that many accepted samples on.

    With the closed form and no ridge, on CPU with the native kernels
    (:mod:`selfid_jax.math.native`), the update, guess, refinement and record
    run as one kernel that reads each field of the state once and writes it
    once (the ring buffer's write stays XLA code); values equal the four
    functions' to float round-off.
    """
    new = _fused_closed_form(state, dtheta, V, eps, eps_rel, method, options, min_count)
    if new is None:
        new = estimator.update(state, dtheta, V)
        J = refine(new, estimator.initial_guess(new), method=method, **dict(options))
        new = estimator.record(new, J, eps, eps_rel, min_count=min_count)
    return new, StepInfo(estimate=new.estimate, delta=new.last_deltas[1],
                         threshold=new.last_norms[1] * eps_rel + eps, accepted=new.count > state.count)


# the fields the fused closed-form step reads (update's, then record's besides count) and writes
_STEP_RECORD = ("estimate", "last_deltas", "last_norms", "last_fresh", "recorded_count", "iteration", "converged_at")
_STEP_IN = (*estimator._UPDATE_IN, *_STEP_RECORD)
_STEP_OUT = (*estimator._UPDATE_OUT, *_STEP_RECORD)


def _fused_closed_form(state, dtheta, V, eps, eps_rel, method, options, min_count):
    """The new state of :func:`sample_step` from the native ``"step"`` kernel where it applies (the closed form, no
    ridge, thresholds of the state's dtype, an integer ``min_count``, the kernels on), after the checks the four
    functions make; None elsewhere."""
    opts = dict(options)
    ridge = opts.get("ridge", 0.0)
    if not (method == "closed_form" and set(opts) <= {"rcond", "ridge"} and isinstance(ridge, (int, float))
            and ridge == 0 and native.enabled()):
        return None
    n, m, _ = estimator.sizes(state)
    dtype = state.sign_net.dtype
    if not estimator._native_thresholds(dtype, eps, eps_rel, min_count):
        return None
    check_array("dtheta", dtheta, (n,))
    check_array("V", V, (m,))
    estimator.check_thresholds(eps, eps_rel)
    rcond = opts.get("rcond")
    if rcond is not None:
        check_scalar("rcond", rcond, ge=0.0)
    dtheta, V = jnp.asarray(dtheta, dtype), jnp.asarray(V, dtype)
    rcond = jnp.asarray(default_rcond(m, dtype) if rcond is None else rcond, dtype)
    fields = native.call("step", _closed_form_fields, *(getattr(state, f) for f in _STEP_IN), dtheta, V, rcond,
                         jnp.asarray(eps, dtype), jnp.asarray(eps_rel, dtype), jnp.asarray(min_count, jnp.int32))
    new = state._replace(**dict(zip(_STEP_OUT, fields, strict=True)))
    return estimator._ring_write(state, new, dtheta, V, new.count > state.count)


def _closed_form_fields(*args):
    """The fused step in pure JAX, on the fields it reads (``_STEP_IN``), ``dtheta``, ``V``, ``rcond``, ``eps``,
    ``eps_rel``, ``min_count``: the fields it writes (``_STEP_OUT``), a tuple."""
    k = len(estimator._UPDATE_IN)
    update_in, record_in = args[:k], dict(zip(_STEP_RECORD, args[k:len(_STEP_IN)], strict=True))
    dtheta, V, rcond, eps, eps_rel, min_count = args[len(_STEP_IN):]
    sums = dict(zip(estimator._UPDATE_OUT, estimator._update_sums(*update_in, dtheta, V), strict=True))
    n, m = sums["S_tv"].shape
    state = estimator.init(n, m, capacity=0, dtype=dtheta.dtype)._replace(**sums, **record_in)
    J = _minimum_norm_correction(state.S_vv, state.S_tv, estimator.initial_guess(state), rcond)
    recorded = estimator._record_fields(J, *(getattr(state, f) for f in estimator._RECORD_IN), eps, eps_rel,
                                        min_count)
    return (*sums.values(), *recorded)
