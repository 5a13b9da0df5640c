"""Self-ID data collection and estimation (Algorithm 1) as one ``lax.scan``.

Each iteration draws a random actuation ``dtheta ~ uniform(-m_a, m_a)``, lets
an ``observe`` step move the actuators and report the pose change ``V``, folds
the sample into the estimator (Eq. 6-12), forms the initial guess (Eq. 13),
refines it (Eq. 14) and records it for the convergence test (Sec. IV-D).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from selfid_jax import estimator
from selfid_jax._checks import check_positive_int, float_dtype
from selfid_jax.refine import refine

Observe = Callable[[Any, jax.Array, jax.Array], tuple[Any, jax.Array]]
"""``observe(env, key, dtheta (n,)) -> (env, V (m,))``: apply an actuation, return the pose change."""


class SelfIDResult(NamedTuple):
    """Output of :func:`self_identify` (leading batch axes if vmapped)."""

    state: estimator.EstimatorState  # estimator after the last iteration
    estimate: jax.Array  # (n, m) final refined inverse Jacobian (frozen at convergence if stop_at_convergence)
    estimates: jax.Array  # (iters, n, m) refined estimate after each iteration
    deltas: jax.Array  # (iters,) ||J_t - J_{t-1}||_F per iteration
    converged_at: jax.Array  # () int32: first iteration (1-based) meeting Sec. IV-D, -1 if none
    dtheta: jax.Array  # (iters, n) actuations drawn
    V: jax.Array  # (iters, m) pose changes observed
    env: Any  # final environment state


def stateless(fn: Callable[[jax.Array, jax.Array], jax.Array]) -> Observe:
    """Adapt ``fn(key, dtheta) -> V`` to the :data:`Observe` signature (no environment state)."""

    def observe(env, key, dtheta):
        return env, fn(key, dtheta)

    return observe


def self_identify(
    observe: Observe,
    key: jax.Array,
    m_a,
    eps,
    *,
    n_act: int,
    task_dim: int,
    iters: int,
    env: Any = None,
    capacity: int | None = None,
    v_tol=1e-9,
    method: str = "closed_form",
    stop_at_convergence: bool = True,
    refine_options: dict | None = None,
) -> SelfIDResult:
    """Run Algorithm 1 for ``iters`` self-ID iterations under ``lax.scan``.

    Args:
      observe: ``observe(env, key, dtheta) -> (env, V)`` (static; see :func:`stateless`).
      key: PRNG key; split for each actuation and observation.
      m_a: self-ID magnitude, scalar or ``(n_act,)``, actuator units: ``dtheta_i ~ uniform(-m_a_i, m_a_i)``.
      eps: convergence threshold on ``||J_t - J_{t-1}||_F`` (Sec. IV-D), inverse-Jacobian units.
      n_act, task_dim, iters: static sizes.
      env: initial environment state passed to ``observe`` (any pytree).
      capacity: samples kept for refinement (default ``iters``: all of them).
      v_tol: ``|V_j|`` threshold of the magnitude mean (Eq. 11).
      method: refinement method of :func:`selfid_jax.refine.refine` (``"closed_form"`` or ``"optax"``).
      stop_at_convergence: static; if True the estimator stops updating once
        converged (Algorithm 1 returns there), later iterations repeat that estimate.
      refine_options: static keyword options for :func:`~selfid_jax.refine.refine`.

    ``m_a``, ``eps`` and ``v_tol`` may be traced, so one compilation serves a sweep
    over them; vmap over ``key``, ``m_a``, ``eps`` or ``env``.
    """
    n_act = check_positive_int("n_act", n_act)
    task_dim = check_positive_int("task_dim", task_dim)
    iters = check_positive_int("iters", iters)
    if method == "slsqp":
        raise ValueError("self_identify runs under lax.scan: method must be 'closed_form' or 'optax', not 'slsqp'")
    capacity = iters if capacity is None else check_positive_int("capacity", capacity)
    options = dict(refine_options or {})
    dtype = float_dtype()
    m_a = jnp.broadcast_to(jnp.asarray(m_a, dtype), (n_act,))
    state0 = estimator.init(n_act, task_dim, capacity=capacity, v_tol=v_tol, dtype=dtype)

    def body(carry, k):
        state, env, done = carry
        k_act, k_obs = jax.random.split(k)
        dtheta = jax.random.uniform(k_act, (n_act,), dtype, -1.0, 1.0) * m_a
        env_new, V = observe(env, k_obs, dtheta)
        V = jnp.asarray(V, dtype)
        new = estimator.update(state, dtheta, V)
        J = refine(new, estimator.initial_guess(new), method=method, **options)
        new = estimator.record(new, J, eps)
        delta = new.last_deltas[1]
        if stop_at_convergence:
            new = jax.tree.map(lambda a, b: jnp.where(done, a, b), state, new)
            env_new = jax.tree.map(lambda a, b: jnp.where(done, a, b), env, env_new)
            delta = jnp.where(done, 0.0, delta)
            done = done | (new.converged_at > 0)
        return (new, env_new, done), (new.estimate, delta, dtheta, V)

    keys = jax.random.split(key, iters)
    (state, env, _), (estimates, deltas, dthetas, Vs) = jax.lax.scan(body, (state0, env, jnp.array(False)), keys)
    return SelfIDResult(
        state=state,
        estimate=state.estimate,
        estimates=estimates,
        deltas=deltas,
        converged_at=state.converged_at,
        dtheta=dthetas,
        V=Vs,
        env=env,
    )
