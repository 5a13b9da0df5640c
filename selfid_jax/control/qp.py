"""The constrained optimal controller of the E-KM baseline (seed 002, Eq. 10-11), as a small QP in JAX.

Each control step solves for the actuator step ``da (n,)``::

    minimise  sum_i w_i da_i^2                      (Eq. 11, W = diag(w), w > 0)
    subject to J da = v                             (the task equality of Eq. 10)
               lo <= da <= hi                       (a_min <= a + da <= a_max)

with ``J (m, n)`` the model's (linearised) task Jacobian, ``v (m,)`` the
desired task step (after the limiting function) and the box the joint limits
and the per-step actuator limit. :func:`solve` is exact, jits and vmaps.

Solver (why not qpax): the weight is diagonal, so for multipliers ``lam``
the box-constrained minimiser of the Lagrangian is explicit,
``da(lam) = clip(J^T lam / w, lo, hi)``, and the dual
``g(lam) = lam^T v - eps/2 |lam|^2 + min_box (1/2 da^T W da - lam^T J da)`` is
concave, piecewise quadratic in ``m <= 6`` variables. We maximise it by a
semismooth Newton method: direction ``(J_F W_F^-1 J_F^T + eps I)^-1 grad g``
over the free actuators ``F``, and an exact line search (the dual's slope
along the direction is piecewise linear, kinked where an actuator meets a
bound: evaluated at all ``2n`` kinks at once, no data-dependent loop); a fixed
number of iterations. Every iterate ``da(lam)`` lies in the box. The ridge
``eps`` (relative to ``trace(J W^-1 J^T) / m``, default ``finfo.eps^(2/3)``:
3.7e-11 in float64, 2.4e-5 in float32) makes the dual bounded when the task step cannot be
reached inside the box: then the result is the elastic solution,
``min_box 1/2 da^T W da + |J da - v|^2 / (2 eps)`` (the reachable task step
closest to ``v`` in least squares, then the least weighted effort), and when
it can be reached it is Eq. 10's solution up to a relative ``O(eps)``. A general QP solver (qpax's
interior point) would be a new run-time dependency for a 2-6 variable
problem, needs its iteration tolerance, and returns nothing usable on an
infeasible step; this solve has no dependency and degrades gracefully.

:func:`constrained_law` is this controller as a step law of the one follow
loop (:func:`selfid_jax.control.loop.follow_law`), and :func:`follow` runs it
along a path on a position task (task dimension 2 or 3) with a model given as
two functions: ``linearise(mstate,
q) -> (J (m, n), offset (m,))`` (the predicted task step is ``offset + J
da``: a model nonlinear in ``da``, as the E-KM's incremental GP, is
linearised at ``da = 0`` every step) and, for online learning,
``observe(mstate, q, da, V) -> mstate``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.control.law import StepLaw
from selfid_jax.control.loop import DEFAULT_STEPS, ControllerParams, FollowResult, follow_law
from selfid_jax.math.checks import check_array, check_positive_int, check_scalar
from selfid_jax.systems.system import System

__all__ = ["QPResult", "solve", "step_box", "constrained_law", "follow"]


class QPResult(NamedTuple):
    """Solution of :func:`solve` (leading batch axes if vmapped)."""

    da: jax.Array  # (n,) actuator step, inside [lo, hi]
    residual: jax.Array  # () |J da - v|, task units: ~0 when the task step is reachable
    grad_norm: jax.Array  # () |grad g| of the dual at the end (0 at the optimum), task units


def solve(J, v, lo, hi, weights=1.0, *, iters: int = 20, ridge=None) -> QPResult:
    """Eq. 10-11: ``argmin sum w_i da_i^2`` s.t. ``J da = v``, ``lo <= da <= hi`` (module docstring: method).

    Args:
      J: ``(m, n)`` task Jacobian (task units per actuator unit).
      v: ``(m,)`` desired task step (task units).
      lo, hi: ``(n,)`` box on the step (actuator units), ``lo <= 0 <= hi`` so
        that ``da = 0`` is feasible for the box.
      weights: ``()`` or ``(n,)`` positive actuator weights ``w`` (``W = diag(w)``).
      iters: Newton iterations (static); the active set settles in at most
        a few per bound that binds.
      ridge: dual ridge ``eps`` relative to ``trace(J W^-1 J^T) / m``;
        default ``finfo.eps^(2/3)``. Smaller: closer to Eq. 10 on reachable
        steps, but ``|lam| ~ residual / eps`` on unreachable ones loses digits.

    Returns:
      :class:`QPResult`. Shapes are checked eagerly (``ValueError``); a
      non-finite ``J`` or ``v`` gives ``da = 0`` (clipped into the box).
    """
    check_array("J", J, (None, None))
    m, n = np.shape(J)
    check_array("v", v, (m,))
    check_array("lo", lo, (n,))
    check_array("hi", hi, (n,))
    if np.ndim(weights) not in (0, 1) or np.size(weights) not in (1, n):
        raise ValueError(f"weights: expected shape () or ({n},), got {np.shape(weights)}")
    check_scalar("weights", weights, gt=0.0)
    iters = check_positive_int("iters", iters)
    dtype = jnp.result_type(J, v, lo, hi, float)
    J, v, lo, hi = (jnp.asarray(a, dtype) for a in (J, v, lo, hi))
    w = jnp.broadcast_to(jnp.asarray(weights, dtype), (n,))
    ok = jnp.all(jnp.isfinite(J)) & jnp.all(jnp.isfinite(v))
    J = jnp.where(ok, J, 0.0)
    v = jnp.where(ok, v, 0.0)
    scale = jnp.sum(J * J / w[None, :]) / m
    scale = jnp.where(scale > jnp.finfo(dtype).tiny, scale, 1.0)  # J = 0: any ridge, da = 0
    eps = scale * (jnp.finfo(dtype).eps ** (2.0 / 3.0) if ridge is None else jnp.asarray(ridge, dtype))

    def newton(lam, _):
        a = (J.T @ lam) / w
        grad = v - eps * lam - J @ jnp.clip(a, lo, hi)
        free = (a > lo) & (a < hi)
        H = (J * (free / w)[None, :]) @ J.T + eps * jnp.eye(m, dtype=dtype)
        d = jnp.linalg.solve(H, grad)
        return lam + _line_search(J, v, w, lo, hi, eps, lam, a, d) * d, None

    lam, _ = jax.lax.scan(newton, jnp.zeros((m,), dtype), None, length=iters)
    da = jnp.clip((J.T @ lam) / w, lo, hi)
    res = J @ da - v
    return QPResult(da=da, residual=jnp.sqrt(res @ res), grad_norm=jnp.linalg.norm(res + eps * lam))


def _line_search(J, v, w, lo, hi, eps, lam, a, d):
    """Exact maximiser ``t >= 0`` of the dual along ``d``: its slope is piecewise linear in ``t``, kinked where
    an actuator meets a bound, so the root is found from the slopes at the kinks (no value comparisons, which
    lose all precision once ``|lam|`` is large)."""
    b = (J.T @ d) / w
    nz = b != 0
    sb = jnp.where(nz, b, 1.0)
    kinks = jnp.concatenate([(lo - a) / sb, (hi - a) / sb])
    kinks = jnp.where(jnp.concatenate([nz, nz]) & (kinks > 0), kinks, jnp.inf)
    T = jnp.concatenate([jnp.zeros((1,), kinks.dtype), jnp.sort(kinks)])  # (2n + 1,) ascending, inf last
    Tf = jnp.where(jnp.isfinite(T), T, 0.0)
    da = jnp.clip(a[None, :] + Tf[:, None] * b[None, :], lo[None, :], hi[None, :])
    slope = (v - eps * lam) @ d - eps * Tf * (d @ d) - da @ (J.T @ d)  # d/dt of the dual at each kink
    j = jnp.max(jnp.where(jnp.isfinite(T) & (slope >= 0), jnp.arange(T.shape[0]), 0))
    nxt = T[jnp.minimum(j + 1, T.shape[0] - 1)]
    mid = jnp.where(jnp.isfinite(nxt) & (j + 1 < T.shape[0]), 0.5 * (T[j] + nxt), T[j] + 1.0)
    free = (a + mid * b > lo) & (a + mid * b < hi)
    curv = eps * (d @ d) + jnp.sum(jnp.where(free, w * b * b, 0.0))
    t = T[j] + jnp.maximum(slope[j], 0.0) / jnp.maximum(curv, jnp.finfo(curv.dtype).tiny)
    return jnp.where(j + 1 < T.shape[0], jnp.minimum(t, nxt), t)


def step_box(system: System, q):
    """The box of Eq. 10 for a step from ``q (n,)``: ``max(-dq_max, q_low - q) <= da <= min(dq_max, q_high - q)``."""
    return jnp.maximum(-system.dq_max, system.q_low - q), jnp.minimum(system.dq_max, system.q_high - q)


Linearise = Callable[[Any, jax.Array], tuple[jax.Array, jax.Array]]
Observe = Callable[[Any, jax.Array, jax.Array, jax.Array], Any]


def constrained_law(system: System, linearise: Linearise, model_state, *, observe: Observe | None = None,
                    weights=1.0, iters: int = 20) -> StepLaw:
    """The Eq. 10-11 controller as a :class:`~selfid_jax.control.law.StepLaw` of the one follow loop; position tasks.

    Law state: the model's state, starting at ``model_state``. Each step:
    ``J, offset = linearise(model, q)``; ``da = solve(J, V - offset,
    *step_box(system, q), weights, iters=iters).da``. With ``observe``
    (online mode) the model then learns from the executed step: ``model =
    observe(model, q, q_new - q, dp)``, ``q_new = system.apply(q, da)``, ``dp``
    the measured change of the task's position components (kept only on
    steps that move). ``solve`` turns a non-finite ``J`` into ``da = 0``, so
    the law itself never fails a rollout (``ok`` is True).
    """
    pos = list(system.position_axes)

    def sense(model, q):
        return system.pose(q), None

    def step(model, q, pose, _, v):
        J, offset = linearise(model, q)
        lo, hi = step_box(system, q)
        da = solve(J, v - offset, lo, hi, weights, iters=iters).da
        if observe is not None:
            q_new = system.apply(q, da)
            model = observe(model, q, q_new - q, system.pose(q_new)[0][..., pos] - pose[0][..., pos])
        return da, model, jnp.ones((), bool)

    return StepLaw(init=lambda q0: model_state, sense=sense, step=step)


def follow(
    system: System,
    linearise: Linearise,
    model_state,
    path,
    q0,
    controller: ControllerParams = ControllerParams(),
    *,
    observe: Observe | None = None,
    weights=1.0,
    steps: int = DEFAULT_STEPS,
    qp_iters: int = 20,
) -> tuple[FollowResult, Any]:
    """Follow waypoint offsets ``path (W, m)`` from ``q0 (n,)`` with the Eq. 10-11 controller; position tasks.

    Each step: the desired task step ``v`` is the error to the current
    waypoint times ``controller.gain``, clipped to ``max_step`` [m] (the
    seed's limiting function); ``J, offset = linearise(model, q)``;
    ``da = solve(J, v - offset, *step_box(system, q), weights)``; the arm
    moves by ``system.apply(q, da)``; the waypoint advances within ``tol``.
    With ``observe`` (online mode) the model then learns from the executed
    step: ``model = observe(model, q, q_new - q, V)``, ``V`` the measured task
    change. Metrics as :func:`selfid_jax.control.follow` (``positions`` is
    None); a non-finite state or a distance to the path above
    ``diverge_dist`` (default ``2 max|path| + 10 tol``) fails the rollout.
    :func:`~selfid_jax.control.loop.follow_law` with :func:`constrained_law`.
    Returns ``(FollowResult, final model state)``.
    """
    if system.task_dim not in (2, 3) or system.rotation_axes:
        raise ValueError(f"qp_control.follow: position tasks only (task_dim 2 or 3), got task_dim={system.task_dim}"
                         + (f", axes {system.axes}" if system.rotation_axes else ""))
    law = constrained_law(system, linearise, model_state, observe=observe, weights=weights, iters=qp_iters)
    return follow_law(system, law, path, q0, controller, steps=steps)
