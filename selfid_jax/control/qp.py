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

:func:`follow` runs the controller along a path on a position task (task
dimension 2 or 3) with a model given as two functions: ``linearise(mstate,
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

from selfid_jax.math.checks import check_array, check_positive_int, check_scalar, is_traced
from selfid_jax.control.loop import DEFAULT_STEPS, ControllerParams, FollowResult
from selfid_jax.systems.system import System

__all__ = ["QPResult", "solve", "step_box", "follow"]


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


class _Carry(NamedTuple):
    q: jax.Array  # (n,) actuator positions
    model: Any  # the model's state (changes only with observe, online)
    waypoint: jax.Array  # () int32 current waypoint (W when done)
    failed: jax.Array  # () bool
    err_sum: jax.Array  # () sum of distances to the path over active steps [m]
    err_max: jax.Array  # () largest such distance [m]
    used: jax.Array  # () int32 active steps
    wp_err: jax.Array  # (W,) position error when each waypoint was reached [m]; -1 before


def _segment_distance(p, a, b):
    ab = b - a
    den = jnp.sum(ab * ab, axis=-1)
    t = jnp.clip(jnp.sum((p[None, :] - a) * ab, axis=-1) / jnp.where(den > 0, den, 1.0), 0.0, 1.0)
    return jnp.sqrt(jnp.sum((p[None, :] - (a + t[:, None] * ab)) ** 2, axis=-1))


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
    Returns ``(FollowResult, final model state)``.
    """
    steps = check_positive_int("steps", steps)
    n, m = system.n_act, system.task_dim
    if m not in (2, 3):
        raise ValueError(f"qp_control.follow: position tasks only (task_dim 2 or 3), got task_dim={m}")
    check_array("q0", q0, (n,))
    check_array("path", path, (None, m))
    for name, value in (("q0", q0), ("path", path)):
        if not is_traced(value) and not np.all(np.isfinite(np.asarray(value, np.float64))):
            raise ValueError(f"{name} holds non-finite values")
    for name in ("max_step", "tol", "gain"):
        check_scalar(f"controller.{name}", getattr(controller, name), gt=0.0)
    dtype = jnp.result_type(float)
    q0 = jnp.asarray(q0, dtype)
    path = jnp.asarray(path, dtype)
    W = path.shape[0]
    p0 = system.pose(q0)[0][:m]
    targets = p0[None, :] + path
    verts = jnp.concatenate([p0[None, :], targets], axis=0)
    ctrl = controller
    if ctrl.diverge_dist is None:
        ctrl = ctrl._replace(diverge_dist=2.0 * jnp.max(jnp.linalg.norm(path, axis=-1)) + 10.0 * ctrl.tol)

    def advance(c: _Carry, p):
        active = (c.waypoint < W) & ~c.failed
        wc = jnp.minimum(c.waypoint, W - 1)
        err = jnp.linalg.norm(targets[wc] - p)
        hit = active & (err <= ctrl.tol)
        c = c._replace(wp_err=jnp.where(hit, c.wp_err.at[wc].set(err), c.wp_err),
                       waypoint=c.waypoint + hit.astype(jnp.int32))
        return c, active & (c.waypoint < W)

    def step(c: _Carry, _):
        p = system.pose(c.q)[0][:m]
        dist = jnp.min(_segment_distance(p, verts[:-1], verts[1:]))
        c, active = advance(c, p)
        e = targets[jnp.minimum(c.waypoint, W - 1)] - p
        en = jnp.linalg.norm(ctrl.gain * e)
        v = ctrl.gain * e * jnp.minimum(1.0, ctrl.max_step / jnp.where(en > 0, en, 1.0))
        J, offset = linearise(c.model, c.q)
        lo, hi = step_box(system, c.q)
        da = solve(J, v - offset, lo, hi, weights, iters=qp_iters).da
        q_new = system.apply(c.q, da)
        finite = jnp.all(jnp.isfinite(q_new)) & jnp.all(jnp.isfinite(p))
        failed = c.failed | (active & (~finite | (dist > ctrl.diverge_dist)))
        move = active & ~failed
        model = c.model
        if observe is not None:
            V = system.pose(q_new)[0][:m] - p
            learned = observe(model, c.q, q_new - c.q, V)
            model = jax.tree.map(lambda a, b: jnp.where(move, a, b), learned, model)
        counted = jnp.where(active & jnp.isfinite(dist), dist, 0.0)
        return c._replace(q=jnp.where(move, q_new, c.q), model=model, failed=failed, err_sum=c.err_sum + counted,
                          err_max=jnp.maximum(c.err_max, counted), used=c.used + active.astype(jnp.int32)), None

    init = _Carry(q=q0, model=model_state, waypoint=jnp.zeros((), jnp.int32),
                  failed=~(jnp.all(jnp.isfinite(q0)) & jnp.all(jnp.isfinite(path))),
                  err_sum=jnp.zeros((), dtype), err_max=jnp.zeros((), dtype), used=jnp.zeros((), jnp.int32),
                  wp_err=jnp.full((W,), -1.0, dtype))
    c, _ = jax.lax.scan(step, init, None, length=steps)
    p_end = system.pose(c.q)[0][:m]
    c, _ = advance(c, p_end)
    end = jnp.linalg.norm(targets - p_end[None, :], axis=-1)
    wp_err = jnp.where(c.wp_err >= 0, c.wp_err, jnp.where(jnp.isfinite(end), end, 0.0))
    result = FollowResult(
        completion=c.waypoint.astype(dtype) / W, mean_error=c.err_sum / jnp.maximum(c.used, 1).astype(dtype),
        max_error=c.err_max, waypoint_error=jnp.mean(wp_err), steps_used=c.used, failed=c.failed,
        final_q=c.q, positions=None)
    return result, c.model
