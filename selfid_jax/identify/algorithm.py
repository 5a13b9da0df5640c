"""Self-ID data collection and estimation (Algorithm 1) as one ``lax.scan``.

Each iteration draws a random actuation ``dtheta ~ uniform(-m_a, m_a)``, lets
an ``observe`` step move the actuators and report the pose change ``V``, folds
the sample into the estimator (Eq. 6-12), forms the initial guess (Eq. 13),
refines it (Eq. 14) and records it for the convergence test (Sec. IV-D): the
one per-sample step :func:`selfid_jax.identify.step.sample_step` (or, with
``recursive``, its rank-one form in :mod:`~selfid_jax.identify.recursive`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from selfid_jax.identify import estimator
from selfid_jax.identify import recursive as rec_mod
from selfid_jax.identify.refine import needs_samples
from selfid_jax.identify.step import sample_step
from selfid_jax.math.checks import check_magnitude, check_positive_int, check_scalar, float_dtype
from selfid_jax.math.geometry import noisy_pose

if TYPE_CHECKING:  # the systems package loads the shipped robots (MuJoCo): not at run time
    from selfid_jax.systems.system import SelfIDSystem

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
    m_a: ArrayLike,
    eps: ArrayLike,
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
    eps_rel=0.0,
    forget=1.0,
    recursive: bool | None = None,
) -> SelfIDResult:
    """Run Algorithm 1 for ``iters`` self-ID iterations under ``lax.scan``.

    Args:
      observe: ``observe(env, key, dtheta) -> (env, V)`` (static; see :func:`stateless`).
      key: PRNG key; split for each actuation and observation.
      m_a: self-ID magnitude, scalar or ``(n_act,)``, actuator units: ``dtheta_i ~ uniform(-m_a_i, m_a_i)``.
      eps: convergence threshold on ``||J_t - J_{t-1}||_F`` (Sec. IV-D), inverse-Jacobian units.
      eps_rel: relative threshold: converged when ``||J_t - J_{t-1}||_F <=
        eps + eps_rel ||J_t||_F`` twice in a row (see :func:`estimator.record`).
      n_act, task_dim, iters: static sizes.
      env: initial environment state passed to ``observe`` (any pytree).
      capacity: samples kept in the estimator's ring buffer (default: none
        when the refinement reads the statistics, as the closed form and the
        L2 gradient refinement do, else ``iters``: all of them, for the Huber
        loss).
      v_tol: ``|V_j|`` threshold of the magnitude mean (Eq. 11).
      forget: exponential forgetting factor in ``(0, 1]`` of the estimator's
        sums (:func:`selfid_jax.identify.estimator.init`); 1 (default) never forgets.
      method: refinement method of :func:`selfid_jax.identify.refine.refine` (``"closed_form"`` or ``"optax"``).
      stop_at_convergence: static; if True the estimator stops updating once
        converged (Algorithm 1 returns there), later iterations repeat that estimate.
      refine_options: static keyword options for :func:`~selfid_jax.identify.refine.refine`.
      recursive: static; keep the plain closed form (``method="closed_form"``,
        no ridge) by rank-one steps once ``S_vv`` has full rank
        (:mod:`~selfid_jax.identify.recursive`: the batch form for the first
        ``task_dim + 5`` iterations, rank-one steps after, the batch form again
        for the rest if any step was not exact; equal to the batch path up to
        round-off). Default: when ``iters >= RECURSIVE_MIN_ITERS`` (64), where
        it pays for compiling the step three times (about 3x the compile time
        of the self-ID part); ignored for other refinements.

    ``m_a``, ``eps``, ``eps_rel``, ``v_tol`` and ``forget`` may be traced, so one compilation
    serves a sweep over them; vmap over ``key``, ``m_a``, ``eps`` or ``env``.
    Concrete values are checked first (``m_a`` finite, > 0, scalar or
    ``(n_act,)``; thresholds as :func:`estimator.check_thresholds`); traced bad
    values give rejected samples, counted in ``state.rejected``, and no
    convergence.
    """
    n_act = check_positive_int("n_act", n_act)
    task_dim = check_positive_int("task_dim", task_dim)
    iters = check_positive_int("iters", iters)
    if method == "slsqp":
        raise ValueError("self_identify runs under lax.scan: method must be 'closed_form' or 'optax', not 'slsqp'")
    options = dict(refine_options or {})
    if capacity is None:
        capacity = iters if needs_samples(method, options.get("loss", "l2")) else 0
    capacity = estimator.check_nonnegative_int("capacity", capacity)
    dtype = float_dtype()
    check_magnitude("m_a", m_a, n_act)
    estimator.check_thresholds(eps, eps_rel)
    m_a = jnp.broadcast_to(jnp.asarray(m_a, dtype), (n_act,))
    state0 = estimator.init(n_act, task_dim, capacity=capacity, v_tol=v_tol, forget=forget, dtype=dtype)

    recursive = _recursive_closed_form(method, options) and (iters >= RECURSIVE_MIN_ITERS if recursive is None
                                                             else bool(recursive))
    rec0 = rec_mod.init(task_dim, dtype)
    step_options = tuple(sorted(options.items()))

    def make_body(fast: bool):
        def body(carry, k):
            state, rec, env, done = carry
            k_act, k_obs = jax.random.split(k)
            dtheta = jax.random.uniform(k_act, (n_act,), dtype, -1.0, 1.0) * m_a
            env_new, V = observe(env, k_obs, dtheta)
            V = jnp.asarray(V, dtype)
            if not recursive:
                new, _ = sample_step(state, dtheta, V, eps, eps_rel, method=method, options=step_options)
                rec_new = rec
            elif fast:
                new, rec_new = rec_mod.fast_step(state, rec, dtheta, V, eps, eps_rel, rcond=options.get("rcond"))
            else:
                new, rec_new = rec_mod.exact_step(state, rec, dtheta, V, eps, eps_rel, rcond=options.get("rcond"))
            delta = new.last_deltas[1]
            if stop_at_convergence:
                new, rec_new = jax.tree.map(lambda a, b: jnp.where(done, a, b), (state, rec), (new, rec_new))
                env_new = jax.tree.map(lambda a, b: jnp.where(done, a, b), env, env_new)
                delta = jnp.where(done, 0.0, delta)
                done = done | (new.converged_at > 0)
            return (new, rec_new, env_new, done), (new.estimate, delta, dtheta, V)

        return body

    keys = jax.random.split(key, iters)
    carry0 = (state0, rec0, env, jnp.array(False))
    if recursive:
        # Eq. 14 by the rank-one step once S_vv has full rank (identify.recursive): the first
        # task_dim + 5 iterations, and the rest again if any rank-one step was not exact, run the batch closed form.
        carry, ys = rec_mod.fallback_scan(make_body(True), make_body(False), lambda c: c[1].full, carry0, keys,
                                          warmup=task_dim + 5)
    else:
        carry, ys = jax.lax.scan(make_body(False), carry0, keys)
    (state, _, env, _), (estimates, deltas, dthetas, Vs) = carry, ys
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


RECURSIVE_MIN_ITERS = 64
"""Default of :func:`self_identify`'s ``recursive``: the rank-one closed form from this many iterations on (the
experiments' 12-30 iterations keep the batch form, and its compile time)."""


def _recursive_closed_form(method: str, options: dict) -> bool:
    """Whether the refinement is the plain closed form (no ridge), which :mod:`~selfid_jax.identify.recursive` keeps
    by rank-one steps."""
    if method != "closed_form" or set(options) - {"rcond", "ridge", "loss", "sign_project"}:
        return False
    ridge = options.get("ridge", 0.0)
    plain = isinstance(ridge, (int, float)) and ridge == 0
    return plain and options.get("loss", "l2") == "l2" and not options.get("sign_project", False)


def run(
    system: SelfIDSystem,
    key: jax.Array,
    q0: ArrayLike,
    *,
    iters: int,
    eps: ArrayLike,
    m_a: ArrayLike | None = None,
    pose_noise: ArrayLike = 0.0,
    rot_noise: ArrayLike = 0.0,
    method: str = "closed_form",
    capacity: int | None = None,
    v_tol=1e-9,
    stop_at_convergence: bool = True,
    refine_options: dict | None = None,
    eps_rel=0.0,
    forget=1.0,
    recursive: bool | None = None,
) -> SelfIDResult:
    """Algorithm 1 on a simulated :class:`~selfid_jax.systems.System` starting at ``q0 (n,)``.

    ``system``: a :class:`~selfid_jax.systems.System` or any
    :class:`~selfid_jax.systems.system.SelfIDSystem` (``n_act``, ``task_dim``,
    ``m_a``, ``pose``, ``apply``, ``task_difference``).

    Each iteration draws ``dtheta ~ uniform(-m_a, m_a)`` (default: the system's
    safe ``m_a``), reads the pose (with Gaussian position noise ``pose_noise``
    in m and rotation noise ``rot_noise`` in rad, as a tag tracker would add),
    moves the actuators (``system.apply``: clipped to the actuator limits),
    reads the pose again, and feeds ``V = task_difference(after, before)`` to
    the estimator. ``result.env`` is the configuration where self-ID ended.
    ``m_a``, ``eps``, ``eps_rel``, ``pose_noise``, ``rot_noise``, ``forget`` and
    ``q0`` may be traced: vmap over them and over ``key``. Concrete noise levels must be
    finite and >= 0. ``recursive``: as :func:`self_identify`.
    """
    from selfid_jax.math.checks import check_array

    check_array("q0", q0, (system.n_act,))
    check_scalar("pose_noise", pose_noise, ge=0.0)
    check_scalar("rot_noise", rot_noise, ge=0.0)
    m_a = system.m_a if m_a is None else m_a

    def observe(q, k, dtheta):
        k_before, k_after = jax.random.split(k)
        q_new = system.apply(q, dtheta)
        # both poses from one vmapped call: a closed-chain hand's pose is a Newton solve, compiled once per call site
        (p, R) = jax.vmap(system.pose)(jnp.stack([q, q_new]))
        before = noisy_pose(k_before, (p[0], R[0]), pose_noise, rot_noise)
        after = noisy_pose(k_after, (p[1], R[1]), pose_noise, rot_noise)
        return q_new, system.task_difference(after, before)

    return self_identify(
        observe,
        key,
        m_a,
        eps,
        n_act=system.n_act,
        task_dim=system.task_dim,
        iters=iters,
        env=jnp.asarray(q0, float_dtype()),
        capacity=capacity,
        v_tol=v_tol,
        method=method,
        stop_at_convergence=stop_at_convergence,
        refine_options=refine_options,
        eps_rel=eps_rel,
        forget=forget,
        recursive=recursive,
    )
