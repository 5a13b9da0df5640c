"""Self-ID from recorded data: the estimator of Eq. 6-14 over a log's sample pairs, with the Sec. IV-D test.

:func:`fit_samples` is the pure core: one ``lax.scan`` of the per-sample
:func:`selfid_jax.identify.step.sample_step` (``estimator.update`` ->
``initial_guess`` (Eq. 13) -> ``refine`` (Eq. 14) -> ``record`` (Sec. IV-D))
over ``(dtheta (T, n), V (T, m))``, the same step Algorithm 1 takes after each random actuation
(:func:`selfid_jax.identify.algorithm.self_identify`), without the actuation.
``eps``, ``eps_rel`` and ``v_tol`` are traced, so one compilation serves
every threshold and every log of the same length, and it vmaps over a batch
of logs. Unlike Algorithm 1 it does not stop at convergence: a recorded log
has no more moves to save, so the final estimate uses every sample, and the
convergence iteration says how many would have sufficed.

:func:`fit` reads a log (:mod:`selfid_jax.robot.log`) and runs it; exported as ``sj.fit``.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from selfid_jax.identify import estimator
from selfid_jax.identify.refine import METHODS, needs_samples, refine
from selfid_jax.identify.step import sample_step
from selfid_jax.math.checks import check_array, float_dtype
from selfid_jax.robot.log import Samples, load_log, samples_from_table

__all__ = ["FitResult", "FitTrace", "fit", "fit_samples"]


class FitTrace(NamedTuple):
    """Output of :func:`fit_samples` (leading batch axes if vmapped)."""

    state: estimator.EstimatorState  # estimator after the last sample
    estimate: jax.Array  # (n, m) final refined inverse Jacobian (every sample)
    initial_guess: jax.Array  # (n, m) Eq. 13 guess after the last sample
    estimates: jax.Array  # (T, n, m) refined estimate after each sample
    deltas: jax.Array  # (T,) ||J_t - J_{t-1}||_F per sample
    thresholds: jax.Array  # (T,) eps + eps_rel ||J_t||_F per sample
    accepted: jax.Array  # (T,) bool: samples the estimator took
    converged_at: jax.Array  # () int32: first 1-based sample index meeting Sec. IV-D, -1 if never


class FitResult(NamedTuple):
    """Output of :func:`fit`: the trace as numpy plus where its samples came from."""

    estimate: np.ndarray  # (n, m) final refined inverse Jacobian (Eq. 14, every sample)
    initial_guess: np.ndarray  # (n, m) Eq. 13 guess from every sample
    estimates: np.ndarray  # (T, n, m) refined estimate after each sample
    deltas: np.ndarray  # (T,) ||J_t - J_{t-1}||_F per sample
    thresholds: np.ndarray  # (T,) eps + eps_rel ||J_t||_F per sample
    accepted: np.ndarray  # (T,) bool: samples the estimator took (the others: all-zero dtheta or V)
    converged_at: int  # first 1-based sample index meeting Sec. IV-D, -1 if never
    samples: Samples  # the sample pairs and the log's row screens (rejected rows, window, gap limit)
    eps: float
    eps_rel: float
    method: str
    state: estimator.EstimatorState  # final estimator state

    @property
    def converged(self) -> bool:
        return self.converged_at > 0

    @property
    def converged_time(self) -> float | None:
        """Log time (s) of the sample at which the test first held; None if never or the log has no time."""
        if self.converged_at < 1:
            return None
        t = float(self.samples.t[self.converged_at - 1])
        return t if np.isfinite(t) else None


@functools.partial(jax.jit, static_argnames=("method", "options", "capacity"))
def _scan(dtheta, V, eps, eps_rel, v_tol, min_count, *, method: str, options: tuple, capacity: int) -> FitTrace:
    n, m = dtheta.shape[-1], V.shape[-1]
    dtype = dtheta.dtype
    state0 = estimator.init(n, m, capacity=capacity, v_tol=v_tol, dtype=dtype)

    def body(state, sample):
        return sample_step(state, sample[0], sample[1], eps, eps_rel, method=method, options=options,
                           min_count=min_count)

    state, info = jax.lax.scan(body, state0, (dtheta, V))
    return FitTrace(state=state, estimate=state.estimate, initial_guess=estimator.initial_guess(state),
                    estimates=info.estimate, deltas=info.delta, thresholds=info.threshold, accepted=info.accepted,
                    converged_at=state.converged_at)


def fit_samples(dtheta: ArrayLike, V: ArrayLike, eps: ArrayLike = 0.0, eps_rel: ArrayLike = 0.05, *,
                method: str = "closed_form", refine_options: Mapping[str, Any] | None = None, v_tol: ArrayLike = 1e-9,
                dtype=None, min_samples: ArrayLike = 0) -> FitTrace:
    """Run the estimator over sample pairs ``dtheta (T, n)``, ``V (T, m)``: a :class:`FitTrace`.

    ``eps`` (inverse-Jacobian units) and ``eps_rel`` (relative to ``||J_t||_F``)
    are the Sec. IV-D thresholds of :func:`selfid_jax.identify.estimator.record`:
    converged at the first sample ``t`` where ``||J_s - J_{s-1}||_F <= eps +
    eps_rel ||J_s||_F`` for ``s = t - 1, t``, both after an accepted sample,
    and at least ``min_samples`` samples accepted (0: the paper's test; the
    live runner's default is 5 per task axis, ``selfid_jax.robot.options``).
    ``method`` names the refinement (:data:`selfid_jax.identify.refine.METHODS`):
    ``"closed_form"`` and ``"optax"`` run in the scan; ``"slsqp"`` (eager
    scipy, the paper's) refines only the final estimate, on every sample, while
    the per-sample estimates and the convergence test use ``"closed_form"``
    (the same L2 minimiser once ``V`` spans the task). Under ``jit``/``vmap``
    (``eps``, ``eps_rel``, ``v_tol``, the data may be traced; batch them with
    ``vmap``), ``"slsqp"`` is refused.
    """
    if method not in METHODS:
        raise ValueError(f"refine method: expected one of {METHODS}, got {method!r}")
    options = dict(refine_options or {})
    dtype = float_dtype() if dtype is None else dtype
    dtheta = jnp.asarray(dtheta, dtype)
    V = jnp.asarray(V, dtype)
    check_array("dtheta", dtheta, (None, None))
    check_array("V", V, (dtheta.shape[0], None))
    estimator.check_thresholds(eps, eps_rel)
    T = dtheta.shape[0]
    if T == 0:
        raise ValueError("no samples to fit")
    scan_method = "closed_form" if method == "slsqp" else method
    scan_options = {} if method == "slsqp" else options
    capacity = T if needs_samples(method, options.get("loss", "l2")) else 0
    trace = _scan(dtheta, V, jnp.asarray(eps, dtype), jnp.asarray(eps_rel, dtype), jnp.asarray(v_tol, dtype),
                  jnp.asarray(min_samples, jnp.int32),
                  method=scan_method, options=tuple(sorted(scan_options.items())), capacity=capacity)
    if method == "slsqp":
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(trace)):
            raise ValueError("method='slsqp' runs scipy eagerly and cannot be used under jit/vmap/grad")
        final = refine(trace.state, trace.initial_guess, method="slsqp", **options)
        trace = trace._replace(estimate=final)
    return trace


def fit(
    log: str | Path | Mapping[str, Any] | Samples,
    *,
    task=None,
    task_dim: int | None = None,
    eps: float = 0.0,
    eps_rel: float = 0.05,
    method: str = "closed_form",
    refine_options: Mapping[str, Any] | None = None,
    start: float | None = None,
    stop: float | None = None,
    max_gap: float | str | None = "auto",
    v_tol: float = 1e-9,
    dtype=None,
) -> FitResult:
    """Self-identify an inverse Jacobian ``(n, m)`` from a recorded log: ``sj.fit("log.csv", task="x,y,z")``.

    ``log``: a CSV/Parquet/NPZ path, a table of columns (dict, DataFrame) or
    :class:`~selfid_jax.robot.log.Samples`; layouts, screens and the options
    ``task``, ``task_dim``, ``start``, ``stop``, ``max_gap`` as in
    :func:`selfid_jax.robot.log.samples_from_table`. ``eps``, ``eps_rel``,
    ``method``, ``refine_options``, ``v_tol`` as in :func:`fit_samples`.
    ``dtype``: default JAX's default float (float64 needs ``jax_enable_x64``).

    Raises:
      LogError: the log cannot be used (one line naming file, column, row).
      ValueError: an option out of range, or no sample pair survives the screens.
    """
    screens = dict(task=task, task_dim=task_dim, start=start, stop=stop, max_gap=max_gap)
    if isinstance(log, Samples):
        samples = log
    elif isinstance(log, (str, Path)):
        samples = load_log(log, **screens)
    else:
        samples = samples_from_table(log, **screens)
    if samples.dtheta.shape[0] == 0:
        kinds = "; ".join(r.line() for r in samples.rejected) or "no rows in the time window"
        raise ValueError(f"{samples.source}: no usable sample pair ({kinds})")
    trace = fit_samples(samples.dtheta, samples.V, eps, eps_rel, method=method, refine_options=refine_options,
                        v_tol=v_tol, dtype=dtype)
    host = jax.device_get(trace)
    return FitResult(
        estimate=np.asarray(host.estimate), initial_guess=np.asarray(host.initial_guess),
        estimates=np.asarray(host.estimates), deltas=np.asarray(host.deltas), thresholds=np.asarray(host.thresholds),
        accepted=np.asarray(host.accepted), converged_at=int(host.converged_at), samples=samples,
        eps=float(eps), eps_rel=float(eps_rel), method=method, state=host.state,
    )
