"""Damped least-squares inverse kinematics, seed 004's feasibility-projected DLS and its base-yaw workaround.

One iteration at ``q`` with pose error ``e`` (world frame; ``[p* - p,
log(R* R^T)]`` for a pose target, ``p* - p`` for a position target, clamped to
``max_step`` m / ``max_rot_step`` rad) and Jacobian ``J``:

* ``"dls"``: ``dq = argmin |Wx (J dq - e)|^2 + lambda^2 |dq|^2``;
* ``"projected"`` (seed 004, "Feasibility-Projected IK"): first the achievable
  error ``e_a = J J^+ e`` (orthogonal projection onto the range of ``J``), then
  the same weighted DLS towards ``e_a``.

``Wx = diag(1, 1, 1, L, L, L)`` with ``L = rot_weight`` [m] turns rotation
errors into lengths (identity for a position target). With ``Wx = I`` the
projection changes nothing: ``J^T J J^+ = J^T``, so both give the same step.
With ``Wx != I`` it does: plain weighted DLS trades the unreachable part of
``e`` against the reachable one in the weighted metric, while the projected
step first drops it in the unweighted one, so (as ``lambda -> 0``) it is the
pseudo-inverse step ``J^+ e`` whatever the weights.

Joint limits are kept by a box-constrained step: the DLS objective
``1/2 dq^T H dq - g^T dq`` (``H = J^T W J + lambda^2 I``, ``W = Wx^T Wx``) is
minimised over ``q_low - q <= dq <= q_high - q`` by :func:`box_qp`, an exact
primal active-set method (checked against scipy's BVLS). Not qpax: a new
dependency whose interior point returns a ``1e-5``-tolerance step; not
projected gradient with optax's ``projection_box`` alone: it needs about
``cond(H) = sigma_max^2 / lambda^2`` iterations, thousands near singularities
(``box_qp`` uses that projection to stay feasible).

Every solver runs under ``lax.while_loop`` for one target; ``vmap`` it over
targets, starts or :class:`DLSParams` rows. :func:`base_yaw_ik` is seed 004's
workaround for an arm without tool yaw (a sideways move at fixed orientation
is out of reach): turn the base to ``atan2(y*, x*)``, solve the rest with the
base held, give up the orientation's yaw. A self-identified ``Jinv (n, 3)``
can stand in for the Jacobian (position targets): ``J = Jinv^+`` held fixed,
the pose measured.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from selfid_jax.math import geometry
from selfid_jax.math.checks import check_array, check_positive_int, check_scalar
from selfid_jax.systems.system import System

__all__ = [
    "DLSParams",
    "IKResult",
    "METHODS",
    "base_yaw_ik",
    "box_qp",
    "dls_step",
    "ik",
    "ik_restarts",
    "weighted_dls",
]

METHODS = ("dls", "projected")


class DLSParams(NamedTuple):
    """Traced settings of the IK solvers (any field may carry a batch axis under ``vmap``)."""

    damping: jax.Array | float = 0.01  # () lambda [m/rad]: H = J^T W J + lambda^2 I
    rot_weight: jax.Array | float = 0.1  # () L [m]: rotation rows weighted as a point L away (Wx = diag(1,1,1,L,L,L))
    max_step: jax.Array | float = 0.05  # () position error clamp per iteration [m]
    max_rot_step: jax.Array | float = 0.5  # () rotation error clamp per iteration [rad]
    tol: jax.Array | float = 0.0005  # () success: position error below this [m]
    rot_tol: jax.Array | float = 0.01  # () success: rotation error below this [rad] (pose targets)
    stall: jax.Array | float = 1e-9  # () stop when the joint step's norm falls below this [rad]


class IKResult(NamedTuple):
    """One solve (leading batch axes if vmapped)."""

    q: jax.Array  # (n,) final configuration [rad / m], within the joint limits
    position_error: jax.Array  # () |p* - p(q)| [m]
    rotation_error: jax.Array  # () angle of R* R(q)^T [rad] (0 for a position target)
    iterations: jax.Array  # () int32 iterations used
    success: jax.Array  # () bool: errors within tol (and rot_tol for a pose target)


# ------------------------------------------------------------------ the box-constrained step
def box_qp(H, g, lower, upper, *, max_iter: int | None = None):
    """``argmin 1/2 x^T H x - g^T x`` subject to ``lower <= x <= upper``, ``H`` symmetric positive definite.

    Primal active-set method (Nocedal and Wright, Alg. 16.3) from the feasible
    point nearest 0: solve on the free variables with the working set at its
    bounds; a step that leaves the box stops at the first bound, which joins
    the working set; at a working-set minimiser, release the bound with the
    most negative multiplier, or stop (KKT point = the unique minimiser).
    Variables with ``lower == upper`` stay fixed. One masked ``(n, n)`` solve
    per iteration; ``max_iter`` (static, default ``4 n + 4``) bounds the loop.

    Args:
      H, g: ``(n, n)`` SPD matrix, ``(n,)`` vector.
      lower, upper: ``(n,)`` bounds with ``lower <= upper`` (may be +-inf).

    Returns:
      ``(n,)`` minimiser.
    """
    H, g = jnp.asarray(H), jnp.asarray(g)
    n = g.shape[-1]
    check_array("H", H, (n, n))
    check_array("lower", lower, (n,))
    check_array("upper", upper, (n,))
    max_iter = 4 * n + 4 if max_iter is None else check_positive_int("max_iter", max_iter)
    dtype = jnp.result_type(H, g, lower, upper, float)
    H, g = H.astype(dtype), g.astype(dtype)
    lower, upper = jnp.asarray(lower, dtype), jnp.asarray(upper, dtype)
    fixed = lower >= upper
    x0 = optax.projections.projection_box(jnp.zeros(n, dtype), lower, upper)
    at_lo, at_hi = (x0 <= lower) | fixed, (x0 >= upper) & ~fixed & ~(x0 <= lower)
    eye = jnp.eye(n, dtype=dtype)
    mult_tol = 1e3 * jnp.finfo(dtype).eps * jnp.max(jnp.abs(g))  # multipliers are of the size of g

    def body(carry):
        x, at_lo, at_hi, _, k = carry
        act = at_lo | at_hi
        free = ~act
        xb = jnp.where(at_lo, lower, jnp.where(at_hi, upper, 0.0))
        M = jnp.where(free[:, None] & free[None, :], H, 0.0) + jnp.where(act, 1.0, 0.0)[:, None] * eye
        y = jnp.linalg.solve(M, jnp.where(free, g - H @ xb, xb))
        p = y - x
        # ratio test over free variables moving towards a bound
        safe_p = jnp.where(p == 0, 1.0, p)
        t_lo = jnp.where(free & (p < 0), (lower - x) / safe_p, jnp.inf)
        t_hi = jnp.where(free & (p > 0), (upper - x) / safe_p, jnp.inf)
        t = jnp.minimum(t_lo, t_hi)
        j = jnp.argmin(t)
        blocked = t[j] < 1.0
        alpha = jnp.where(blocked, jnp.maximum(t[j], 0.0), 1.0)
        x_new = optax.projections.projection_box(x + alpha * p, lower, upper)
        hit_lo = blocked & (t_lo[j] <= t_hi[j])
        onehot = jnp.arange(n) == j
        x_new = jnp.where(onehot & blocked, jnp.where(hit_lo, lower, upper), x_new)
        # at the working-set minimiser: multipliers of the bounds (>= 0 at the optimum); fixed ones never leave
        grad = H @ y - g
        mu = jnp.where(at_lo & ~fixed, grad, jnp.where(at_hi, -grad, jnp.inf))
        r = jnp.argmin(mu)
        release = ~blocked & (mu[r] < -mult_tol)
        drop = (jnp.arange(n) == r) & release
        new_lo = jnp.where(blocked, at_lo | (onehot & hit_lo), at_lo & ~drop)
        new_hi = jnp.where(blocked, at_hi | (onehot & ~hit_lo), at_hi & ~drop)
        done = ~blocked & ~release
        return x_new, new_lo, new_hi, done, k + 1

    def cond(carry):
        return ~carry[3] & (carry[4] < max_iter)

    x, *_ = jax.lax.while_loop(cond, body, (x0, at_lo, at_hi, jnp.asarray(False), jnp.asarray(0, jnp.int32)))
    return x


# ------------------------------------------------------------------ one step
def _task_weights(rows: int, rot_weight, dtype):
    """``diag(W) = diag(Wx)^2``: ``(rows,)``, ones for position rows, ``L^2`` for rotation rows."""
    w = jnp.ones((rows,), dtype)
    if rows == 6:
        w = w.at[3:].set(jnp.asarray(rot_weight, dtype) ** 2)
    return w


def _range_projector(J):
    """``J J^+ (m, m)``: orthogonal projector onto the range of ``J (m, n)`` (SVD, rank by numpy's pinv cutoff)."""
    U, s, _ = jnp.linalg.svd(J, full_matrices=False)
    keep = s > jnp.finfo(J.dtype).eps * max(J.shape) * s[0]
    Uk = U * keep[None, :]
    return Uk @ Uk.T


def weighted_dls(J, e, damping, weights):
    """``(H, g)`` of the DLS objective: ``H = J^T W J + lambda^2 I (n, n)``, ``g = J^T W e (n,)``,
    ``W = diag(weights)``."""
    JW = J.T * weights[None, :]
    n = J.shape[1]
    return JW @ J + damping**2 * jnp.eye(n, dtype=J.dtype), JW @ e


def dls_step(J, e, params: DLSParams = DLSParams(), *, method: str = "projected", lower=None, upper=None):
    """One DLS joint step ``dq (n,)`` towards the task error ``e (m,)`` with Jacobian ``J (m, n)``.

    ``method="dls"``: ``(J^T W J + lambda^2 I) dq = J^T W e``; ``"projected"``:
    the same with ``e`` replaced by ``J J^+ e`` (seed 004). ``m`` is 3
    (position, ``W = I``) or 6 (``[p; rotation vector]``, rotation rows
    weighted by ``rot_weight^2``). With ``lower``/``upper`` ``(n,)`` the step
    is the box-constrained minimiser (:func:`box_qp`), else the unconstrained
    one. Units: ``e`` in m and rad, ``dq`` in actuator units.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    J, e = jnp.asarray(J), jnp.asarray(e)
    if J.ndim != 2 or J.shape[0] not in (3, 6):
        raise ValueError(f"J: expected shape (3, n) or (6, n), got {J.shape}")
    check_array("e", e, (J.shape[0],))
    dtype = jnp.result_type(J, e, float)
    J, e = J.astype(dtype), e.astype(dtype)
    if method == "projected":
        e = _range_projector(J) @ e
    H, g = weighted_dls(J, e, params.damping, _task_weights(J.shape[0], params.rot_weight, dtype))
    if lower is None and upper is None:
        return jnp.linalg.solve(H, g)
    n = J.shape[1]
    lower = jnp.full((n,), -jnp.inf, dtype) if lower is None else lower
    upper = jnp.full((n,), jnp.inf, dtype) if upper is None else upper
    return box_qp(H, g, lower, upper)


# ------------------------------------------------------------------ the solve loop
class _Carry(NamedTuple):
    q: jax.Array  # (n,)
    e: jax.Array  # (m,) task error at q
    J: jax.Array  # (m, n) Jacobian at q
    it: jax.Array  # () int32
    done: jax.Array  # () bool


def _clamp(e, params: DLSParams):
    """``e`` scaled by one factor so ``|e_p| <= max_step`` and ``|e_r| <= max_rot_step``.

    One factor for both parts keeps the direction of ``e``: clamping each part
    alone would move the fixed point of an unreachable target (the weighted
    least-squares compromise) towards the clamped part.
    """
    pos, rot = _errors(e)
    scale = jnp.minimum(1.0, params.max_step / jnp.where(pos > 0, pos, 1.0))
    if e.shape[0] == 6:
        scale = jnp.minimum(scale, params.max_rot_step / jnp.where(rot > 0, rot, 1.0))
    return e * scale


def _evaluate(system: System, q, target_p, target_R, J_fixed):
    """``(e (m,), J (m, n))`` at ``q``: true 6-D / 3-D Jacobian, or the fixed one from a self-ID inverse."""
    if J_fixed is not None:
        p, _ = system.pose(q)
        return target_p - p, J_fixed
    if target_R is None:
        (p, _), J = system.with_task_dim(3).pose_and_jacobian(q)
        return target_p - p, J
    (p, R), J = system.with_task_dim(6).pose_and_jacobian(q)
    return geometry.pose_difference(target_p, target_R, p, R), J


def _errors(e):
    pos = jnp.linalg.norm(e[:3])
    rot = jnp.linalg.norm(e[3:]) if e.shape[0] == 6 else jnp.zeros((), e.dtype)
    return pos, rot


def _solve(system, q0, target_p, target_R, params, method, max_iters, J_fixed, lower_fix, upper_fix):
    dtype = jnp.result_type(float)
    q0 = jnp.clip(jnp.asarray(q0, dtype), system.q_low, system.q_high)
    e0, J0 = _evaluate(system, q0, target_p, target_R, J_fixed)

    def converged(e, p):
        pos, rot = _errors(e)
        ok = pos <= p.tol
        return ok & (rot <= p.rot_tol) if e.shape[0] == 6 else ok

    def body(c: _Carry) -> _Carry:
        e_step = _clamp(c.e, params)
        lower = system.q_low - c.q
        upper = system.q_high - c.q
        if lower_fix is not None:  # joints held where they are (base-yaw workaround)
            lower = jnp.where(lower_fix, 0.0, lower)
            upper = jnp.where(upper_fix, 0.0, upper)
        dq = dls_step(c.J, e_step, params, method=method, lower=lower, upper=upper)
        q = jnp.clip(c.q + dq, system.q_low, system.q_high)
        e_new, J_new = _evaluate(system, q, target_p, target_R, J_fixed)
        stalled = jnp.linalg.norm(q - c.q) < params.stall
        return _Carry(q, e_new, J_new, c.it + 1, converged(e_new, params) | stalled)

    def cond(c: _Carry):
        return ~c.done & (c.it < max_iters)

    c = jax.lax.while_loop(cond, body, _Carry(q0, e0, J0, jnp.asarray(0, jnp.int32), converged(e0, params)))
    pos, rot = _errors(c.e)
    return IKResult(c.q, pos, rot, c.it, converged(c.e, params))


def _prepare(what: str, system: System, q0, target_p, target_R, params, method, max_iters, jinv):
    """Eager checks shared by the solvers; returns ``(max_iters, J_fixed or None)``."""
    if not isinstance(system, System):
        raise ValueError(f"{what}: system must be a selfid_jax System, got {type(system).__name__}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    max_iters = check_positive_int("max_iters", max_iters)
    check_array("q0", q0, (system.n_act,))
    check_array("target_p", target_p, (3,))
    if target_R is not None:
        check_array("target_R", target_R, (3, 3))
        if not system.has_rotation:
            raise ValueError(f"{what}: a pose target needs a system with orientation (has_rotation=True)")
    _check_params(params)
    return max_iters, _fixed_jacobian(system, jinv, target_R)


def ik(
    system: System,
    q0,
    target_p,
    target_R=None,
    params: DLSParams = DLSParams(),
    *,
    method: str = "projected",
    max_iters: int = 200,
    jinv=None,
) -> IKResult:
    """Damped least-squares IK from ``q0`` to a position or pose target, joint limits kept (``lax.while_loop``).

    Iterates :func:`dls_step` (box-constrained to the joint limits) until the
    error is within ``params.tol`` (and ``rot_tol``), the step stalls below
    ``params.stall`` or ``max_iters`` iterations are spent. ``vmap`` over
    targets (and ``q0``, ``params``) to solve many at once.

    Args:
      system: a :class:`~selfid_jax.systems.System` (its ``task_dim`` is not
        used: the target decides).
      q0: ``(n,)`` start configuration [rad / m] (clipped to the limits).
      target_p: ``(3,)`` target position [m], world frame.
      target_R: ``(3, 3)`` target orientation, or None for a position target.
      params: :class:`DLSParams` (traced).
      method: ``"projected"`` (seed 004, default) or ``"dls"`` (static).
      max_iters: iteration budget (static).
      jinv: optional ``(n, 3)`` self-identified inverse Jacobian: the solver
        uses the fixed ``J = jinv^+`` instead of the true Jacobian (position
        targets only; the pose is still measured at every iteration).

    Returns:
      :class:`IKResult`.
    """
    max_iters, J_fixed = _prepare("ik", system, q0, target_p, target_R, params, method, max_iters, jinv)
    return _solve(system, q0, jnp.asarray(target_p), None if target_R is None else jnp.asarray(target_R), params,
                  method, max_iters, J_fixed, None, None)


def _fixed_jacobian(system: System, jinv, target_R):
    if jinv is None:
        return None
    if target_R is not None:
        raise ValueError("jinv: a self-identified inverse Jacobian serves position targets only (target_R=None)")
    check_array("jinv", jinv, (system.n_act, 3))
    jinv = jnp.asarray(jinv, jnp.result_type(float))
    return jnp.linalg.pinv(jinv)  # (3, n): the Jacobian whose minimum-norm inverse jinv is (J jinv = I at full rank)


def _check_params(params: DLSParams) -> None:
    if not isinstance(params, DLSParams):
        raise ValueError(f"params must be a DLSParams, got {type(params).__name__}")
    for name in ("damping", "rot_weight", "max_step", "max_rot_step", "tol", "rot_tol"):
        check_scalar(f"params.{name}", getattr(params, name), gt=0.0)
    check_scalar("params.stall", params.stall, ge=0.0)


def ik_restarts(
    system: System,
    key,
    q0,
    target_p,
    target_R=None,
    params: DLSParams = DLSParams(),
    *,
    restarts: int,
    method: str = "projected",
    max_iters: int = 200,
    jinv=None,
) -> IKResult:
    """:func:`ik` from ``q0`` and from ``restarts`` configurations uniform in the joint limits; the first success wins.

    All ``restarts + 1`` solves run at once (``vmap``); the result is that of
    ``q0`` if it succeeds, else of the first restart that does, else of the
    solve with the smallest position (then rotation) error. ``restarts`` is
    static; ``key`` a ``jax.random`` key. The joint limits must be finite.
    """
    restarts = check_positive_int("restarts", restarts)
    max_iters, J_fixed = _prepare("ik_restarts", system, q0, target_p, target_R, params, method, max_iters, jinv)
    dtype = jnp.result_type(float)
    starts = jax.random.uniform(key, (restarts, system.n_act), dtype=dtype, minval=system.q_low, maxval=system.q_high)
    starts = jnp.concatenate([jnp.asarray(q0, dtype)[None], starts])
    target_p = jnp.asarray(target_p)
    target_R = None if target_R is None else jnp.asarray(target_R)
    res = jax.vmap(lambda s: _solve(system, s, target_p, target_R, params, method, max_iters, J_fixed, None, None))(
        starts)
    score = jnp.where(res.success, 0.0, 1.0 + res.position_error + 1e-3 * res.rotation_error)
    best = jnp.argmin(score)  # first minimum: q0 when it succeeds, then restarts in order
    return jax.tree.map(lambda x: x[best], res)


def base_yaw_ik(
    system: System,
    q0,
    target_p,
    target_R=None,
    params: DLSParams = DLSParams(),
    *,
    method: str = "projected",
    max_iters: int = 200,
    jinv=None,
) -> IKResult:
    """Seed 004's workaround for an arm without tool yaw: aim the base, then DLS on the other joints.

    The base joint (actuator 0, a rotation about the world z axis through the
    origin, as in :func:`~selfid_jax.systems.ets.arm5`) turns by
    ``atan2(y*, x*) - atan2(y, x)`` (target and current tool positions), so the
    target lies in the arm's plane; the other joints then solve by :func:`ik`
    with the base held. For a pose target the orientation turns with the base:
    the solver aims at ``Rz(dpsi) R*``, i.e. the yaw of the orientation is
    given up: ``success`` says the aimed pose was reached, ``rotation_error``
    is against ``R*`` itself (about ``|dpsi|`` for a reachable aim). A base
    turn beyond its limits is clipped (the target is then missed).

    Args and returns as :func:`ik`; ``jinv (n, 3)``: self-identified inverse
    Jacobian for a position target (its base column is not used).
    """
    max_iters, J_fixed = _prepare("base_yaw_ik", system, q0, target_p, target_R, params, method, max_iters, jinv)
    if system.n_act < 2:
        raise ValueError("base_yaw_ik: needs a base joint and at least one more actuator")
    dtype = jnp.result_type(float)
    target_p = jnp.asarray(target_p, dtype)
    q0 = jnp.clip(jnp.asarray(q0, dtype), system.q_low, system.q_high)
    p0, _ = system.pose(q0)
    dpsi = jnp.arctan2(target_p[1], target_p[0]) - jnp.arctan2(p0[1], p0[0])
    dpsi = jnp.arctan2(jnp.sin(dpsi), jnp.cos(dpsi))  # shortest turn
    q_start = jnp.clip(q0.at[0].add(dpsi), system.q_low, system.q_high)
    held = jnp.arange(system.n_act) == 0
    aim_R = None
    if target_R is not None:
        c, s = jnp.cos(dpsi), jnp.sin(dpsi)
        Rz = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype)
        aim_R = Rz @ jnp.asarray(target_R, dtype)
    res = _solve(system, q_start, target_p, aim_R, params, method, max_iters, J_fixed, held, held)
    if target_R is None:
        return res
    _, R = system.pose(res.q)
    rot = jnp.linalg.norm(geometry.so3_log(jnp.asarray(target_R, dtype) @ R.T))
    return res._replace(rotation_error=rot)  # success: reached the aimed pose Rz(dpsi) R*
