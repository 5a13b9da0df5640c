"""Tac-Man (reactive) and TacMan-Turbo (proactive) tactile control, as pure JAX (seed 003, Eq. 8-27).

Conventions: a pose is a ``jaxlie.SE3``; a gripper twist ``u (6,) = [v, w]`` is
the velocity of the gripper origin and the angular velocity, both in the
current gripper frame (m/s, rad/s); applied over ``dt`` it moves the gripper
to ``T_g @ SE3(exp(w dt), v dt)`` (position and rotation decoupled, as Eq.
18-19 compute them). Marker arrays are ``(M, 3)`` in the gripper frame (m)
with a ``(M,)`` mask of the active contact set (Eq. 2).

Pieces (each jit- and vmap-able, no Python control flow on values):

* :func:`kabsch` -- in-hand pose from corresponding contact points (Eq. 9-12),
  with the ``>= 3`` non-collinear check as a flag;
* :func:`predict` -- constant-velocity SE(3) prediction (Eq. 14-15);
* :func:`offset_velocity` -- Eq. 16-21; :func:`keep_speed` -- the variant that
  keeps the base velocity ``u0`` (the literal law stalls on resisting objects);
  :func:`lead_update`, :func:`smooth_twist`, :func:`advance` -- the integral
  lead and the filtered screw of :func:`lead_step` (``turbo_lead``);
* :func:`alpha_scale` -- joint-velocity limit scaling (Eq. 25-26) and
  :func:`stretch_fraction` -- Eq. 27, the scaled step stretched over
  ``dt / alpha``;
* :func:`turbo_init`/:func:`turbo_step` (and :func:`lead_step` on the same
  state) and :func:`tacman_init`/:func:`tacman_step`:
  one control step of each controller: ``(state, reading) -> (state, u, info)``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import jaxlie
from jax.typing import ArrayLike

__all__ = [
    "Reading",
    "TacManParams",
    "TacManState",
    "TurboParams",
    "TurboState",
    "advance",
    "alpha_scale",
    "deviation",
    "kabsch",
    "keep_speed",
    "lead_step",
    "lead_update",
    "offset_velocity",
    "predict",
    "se3",
    "smooth_twist",
    "stretch_fraction",
    "tacman_init",
    "tacman_step",
    "turbo_init",
    "turbo_step",
]


def se3(p, R) -> jaxlie.SE3:
    """``jaxlie.SE3`` of a position ``(3,)`` [m] and a rotation matrix ``(3, 3)``."""
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(R), p)


def kabsch(ref, cur, mask, *, collinear_tol=1e-3):
    """Rigid transform ``T`` with ``T ref_k ~ cur_k`` over the masked pairs (Eq. 9, Kabsch): ``(T, valid)``.

    Args:
      ref: ``(M, 3)`` reference contact points ``c_1`` [m].
      cur: ``(M, 3)`` current points ``c_i`` [m].
      mask: ``(M,)`` bool: pairs in ``K_{1,i}`` (both in contact, Eq. 10).
      collinear_tol: the set counts as collinear when the second principal
        spread of ``ref`` is below ``collinear_tol`` times the first (ratio of
        standard deviations).

    Returns:
      ``(T, valid)``: ``jaxlie.SE3`` and a bool scalar, False when fewer than 3
      pairs are active (Eq. 11) or they are collinear (Eq. 12); ``T`` is then
      the identity (finite, never NaN).
    """
    w = mask.astype(ref.dtype)
    n = jnp.sum(w)
    safe_n = jnp.maximum(n, 1.0)
    a_bar = jnp.sum(w[:, None] * ref, 0) / safe_n
    b_bar = jnp.sum(w[:, None] * cur, 0) / safe_n
    a = (ref - a_bar[None]) * w[:, None]
    b = (cur - b_bar[None]) * w[:, None]
    spread = jnp.linalg.eigvalsh(a.T @ a / safe_n)  # ascending
    valid = (n >= 3) & (spread[1] > collinear_tol**2 * spread[2]) & (spread[2] > 0)
    H = a.T @ b
    U, _, Vt = jnp.linalg.svd(H)
    d = jnp.sign(jnp.linalg.det(Vt.T @ U.T))
    d = jnp.where(d == 0, 1.0, d)
    R = Vt.T @ jnp.diag(jnp.stack([jnp.ones_like(d), jnp.ones_like(d), d])) @ U.T
    t = b_bar - R @ a_bar
    R = jnp.where(valid, R, jnp.eye(3, dtype=ref.dtype))
    t = jnp.where(valid, t, jnp.zeros(3, ref.dtype))
    return se3(t, R), valid


def predict(T_prev: jaxlie.SE3, T_now: jaxlie.SE3) -> jaxlie.SE3:
    """Next handle pose under constant velocity: ``T_now @ (T_prev^-1 @ T_now)`` (Eq. 14-15)."""
    return T_now @ (T_prev.inverse() @ T_now)


def _decoupled(T: jaxlie.SE3):
    """``[p, rotation vector]`` of ``T`` (Eq. 17, 19-20: ``theta * omega_hat = log R``)."""
    return jnp.concatenate([T.translation(), T.rotation().log()])


def offset_velocity(T_g: jaxlie.SE3, T_pred: jaxlie.SE3, u0, dt):
    """Offset velocity ``u_i (6,)`` that brings the gripper onto the predicted handle pose in ``dt`` (Eq. 16-21).

    ``T_breve = T_g^-1 T_pred`` (Eq. 17), ``u_i = [p_breve, log R_breve] / dt
    - u0`` (Eq. 18-20), so the command ``u0 + u_i`` moves the gripper exactly
    onto the prediction (Eq. 16).
    """
    return _decoupled(T_g.inverse() @ T_pred) / dt - u0


def keep_speed(T_u: jaxlie.SE3, u0, dt, tiny=1e-7):
    """``T_u`` rescaled along its screw so it advances ``|v0| dt`` (the chord; exact without rotation): keeps ``u0``.

    The literal Eq. 14-18 make the gripper follow the handle's own last
    motion and drive the in-hand deviation to zero every step. On an object
    that resists (damping, friction loss) that deviation, the gel shear, is
    what carries the pulling force: without it the handle slows, the
    constant-velocity prediction follows it down and the manipulation
    stalls. Keeping the base speed in the prediction (``T_u -> exp(s log
    T_u)``, ``s = |v0| dt / |t(T_u)|``; ``exp(u0 dt)`` while the handle has not
    moved, ``|t(T_u)| < tiny`` m) aims the gripper ``(|v0| - v_handle) dt``
    ahead of the handle along the predicted screw: a shear that grows until
    it pulls the handle at about the base speed, and no faster (a speed loop
    of gain ``gel stiffness * dt``).
    """
    t = jnp.linalg.norm(T_u.translation())
    speed = jnp.linalg.norm(u0[:3])
    scaled = jaxlie.SE3.exp(T_u.log() * (speed * dt / jnp.maximum(t, tiny)))
    base = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.exp(u0[3:] * dt), u0[:3] * dt)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(t > tiny, a, b), scaled, base)


def alpha_scale(qdot, qdot_max, beta, eps=1e-9):
    """Eq. 25: ``alpha = min(min_j beta qdot_max_j / max(|qdot_j|, eps), 1)`` (scalar, dimensionless).

    ``qdot (n,)`` the unscaled joint velocities (Eq. 23), ``qdot_max (n,)`` the
    limits (rad/s), ``beta`` a safety factor. The executed command is ``alpha``
    times the full one (Eq. 26: ``u_i -> alpha u_i + (alpha - 1) u0``, i.e.
    ``u0 + u_i -> alpha (u0 + u_i)``), taking ``dt / alpha`` to reach the
    prediction (Eq. 27).
    """
    ratio = beta * qdot_max / jnp.maximum(jnp.abs(qdot), eps)
    return jnp.minimum(jnp.min(ratio), 1.0)


def stretch_fraction(alpha, k):
    """Eq. 27: the fraction of control interval ``k`` (0, 1, ...) that a step scaled by ``alpha`` still runs.

    A command scaled by ``alpha <= 1`` (Eq. 26) reaches its target in ``dt /
    alpha`` (Eq. 27), i.e. ``1 / alpha`` control intervals: the first
    ``floor(1 / alpha)`` in full and the last in part. Returns ``clip(1 / alpha
    - k, 0, 1)`` (scalar, dimensionless; 1 for ``k = 0`` at ``alpha = 1``), so
    ``sum_k alpha * stretch_fraction(alpha, k) = 1``: the whole unscaled
    displacement. ``alpha`` is floored at 1e-6.
    """
    return jnp.clip(1.0 / jnp.maximum(alpha, 1e-6) - k, 0.0, 1.0)


def deviation(T_in_hand: jaxlie.SE3, ref, mask):
    """Mean displacement ``|T c_1 - c_1|`` of the masked reference markers [m] (a scalar contact deviation)."""
    moved = jax.vmap(T_in_hand.apply)(ref) - ref
    w = mask.astype(ref.dtype)
    return jnp.sum(w * jnp.linalg.norm(moved, axis=-1)) / jnp.maximum(jnp.sum(w), 1.0)


class Reading(NamedTuple):
    """What the controller sees at one control step."""

    T_g: jaxlie.SE3  # gripper pose (tracker / arm), world frame
    ref: jax.Array  # (M, 3) reference markers c_1 (gripper frame) [m]
    cur: jax.Array  # (M, 3) current markers c_i, with sensor noise [m]
    mask: jax.Array  # (M,) bool active pairs K_{1,i}


# ----------------------------------------------------------------------------- TacMan-Turbo


class TurboParams(NamedTuple):
    """TacMan-Turbo's settings (:func:`turbo_step`, :func:`lead_step`): traced, sweepable under ``vmap``."""

    u0: jax.Array  # (6,) base velocity in the gripper frame [m/s, rad/s] (Eq. 4)
    dt: ArrayLike  # () control interval [s]
    keep_u0: ArrayLike  # () bool: keep the base speed in the prediction (see keep_speed)
    lead_max: ArrayLike = 0.0  # () lead_step: cap of the integral lead s [m]
    twist_tau: ArrayLike = 0.0  # () lead_step: time constant of the handle-twist smoothing [s] (0: none)


class TurboState(NamedTuple):
    T_h_prev: jaxlie.SE3  # previous handle pose estimate (Eq. 13)
    X_prev: jaxlie.SE3  # last valid in-hand pose estimate (held when Kabsch is invalid)
    i: jax.Array  # () int32 control steps taken
    xi: jax.Array  # (6,) lead_step: smoothed per-step handle twist log(T_h_prev^-1 T_h) = [v dt, w dt] [m, rad]
    s: jax.Array  # () lead_step: integral lead along the predicted screw [m]


def turbo_init(T_g: jaxlie.SE3) -> TurboState:
    """Eq. 1: the handle frame coincides with the gripper at the start (no lead, no twist yet)."""
    f = T_g.wxyz_xyz.dtype
    return TurboState(T_g, _identity(f), jnp.zeros((), jnp.int32), jnp.zeros(6, f), jnp.zeros((), f))


def turbo_step(state: TurboState, r: Reading, p: TurboParams):
    """One TacMan-Turbo step: ``(state, u_cmd (6,), (valid, X_hat))``; ``u_cmd = u0 + u_i`` before alpha scaling.

    Kabsch in-hand pose (Eq. 9-12; the last valid one is held when the set
    is invalid), handle pose (Eq. 13), constant-velocity prediction (Eq.
    14-15), offset velocity (Eq. 16-21). The first step uses ``u0`` alone.
    ``state.xi`` and ``state.s`` pass through unchanged (see :func:`lead_step`).
    """
    (X, valid), T_h = _in_hand(state, r)
    T_u = state.T_h_prev.inverse() @ T_h  # Eq. 15
    T_u = jax.tree_util.tree_map(lambda a, b: jnp.where(p.keep_u0, a, b), keep_speed(T_u, p.u0, p.dt), T_u)
    T_pred = T_h @ T_u  # Eq. 14
    u_i = offset_velocity(r.T_g, T_pred, p.u0, p.dt)
    u = jnp.where(state.i > 0, p.u0 + u_i, p.u0)
    return state._replace(T_h_prev=T_h, X_prev=X, i=state.i + 1), u, (valid, X)


def _in_hand(state: TurboState, r: Reading):
    """``((X, valid), T_h)``: Kabsch in-hand pose (the last valid one held) and the handle pose ``T_g X`` (Eq. 13)."""
    X, valid = kabsch(r.ref, r.cur, r.mask)
    X = jax.tree_util.tree_map(lambda a, b: jnp.where(valid, a, b), X, state.X_prev)
    return (X, valid), r.T_g @ X


def lead_update(s, speed, v_handle, dt, lead_max):
    """Integral lead ``clip(s + (speed - v_handle) dt, 0, lead_max)`` [m] (all scalars; m, m/s, s).

    The gripper is aimed ``speed dt + s`` ahead of the handle, so at the end
    of a step the gel shear is about ``s + (speed - v_handle) dt``: ``s``
    integrates the speed deficit until the shear carries whatever force the
    object's resistance needs at ``v_handle = speed``, never beyond ``lead_max``.
    """
    return jnp.clip(s + (speed - v_handle) * dt, 0.0, lead_max)


def smooth_twist(xi_prev, xi, dt, tau):
    """Exponential smoothing ``xi_prev + a (xi - xi_prev)``, ``a = 1 - exp(-dt / tau)`` (``a = 1`` at ``tau = 0``):
    ``(6,)``."""
    a = jnp.where(tau > 0, -jnp.expm1(-dt / jnp.maximum(tau, 1e-12)), 1.0)
    return xi_prev + a * (xi - xi_prev)


def advance(xi, length, u0, tiny=1e-9) -> jaxlie.SE3:
    """``exp(xi length / |xi_v|)``: the motion along the screw ``xi = [v, w] (6,)`` whose origin travels ``length`` [m].

    The origin of ``T exp(c xi)`` moves at the constant speed ``|v|`` (body
    twist), so the scaled screw moves it an arc ``length`` along the same
    helix. While ``|xi_v| < tiny`` (no motion measured yet) the screw is ``u0
    (6,)``'s, scaled the same way.
    """
    n = jnp.linalg.norm(xi[:3])
    n0 = jnp.maximum(jnp.linalg.norm(u0[:3]), tiny)
    tw = jnp.where(n > tiny, xi * (length / jnp.maximum(n, tiny)), u0 * (length / n0))
    return jaxlie.SE3.exp(tw)


def lead_step(state: TurboState, r: Reading, p: TurboParams):
    """One ``turbo_lead`` step: ``(state, u_cmd (6,), (valid, X_hat))``; ``u_cmd = u0 + u_i`` before alpha scaling.

    As :func:`turbo_step` (Kabsch, Eq. 13-21), with the prediction ``T_pred =
    T_h advance(xi, |v0| dt + s)``: ``xi`` the per-step handle twist
    ``log(T_h_prev^-1 T_h)`` smoothed over ``p.twist_tau`` (:func:`smooth_twist`;
    it starts from ``u0 dt``), ``s`` the integral lead (:func:`lead_update`,
    ``v_handle = |xi_raw_v| / dt``, capped at ``p.lead_max``). The first step
    uses ``u0`` alone and leaves ``xi = u0 dt``, ``s = 0``.
    """
    (X, valid), T_h = _in_hand(state, r)
    speed = jnp.linalg.norm(p.u0[:3])
    first = state.i == 0
    xi_raw = (state.T_h_prev.inverse() @ T_h).log()
    xi_prev = jnp.where(state.i > 1, state.xi, p.u0 * p.dt)
    xi = jnp.where(first, p.u0 * p.dt, smooth_twist(xi_prev, xi_raw, p.dt, p.twist_tau))
    v_h = jnp.linalg.norm(xi_raw[:3]) / p.dt
    s = jnp.where(first, 0.0, lead_update(state.s, speed, v_h, p.dt, p.lead_max))
    T_pred = T_h @ advance(xi, speed * p.dt + s, p.u0)
    u_i = offset_velocity(r.T_g, T_pred, p.u0, p.dt)
    u = jnp.where(first, p.u0, p.u0 + u_i)
    return TurboState(T_h, X, state.i + 1, xi, s), u, (valid, X)


# ----------------------------------------------------------------------------- Tac-Man


class TacManParams(NamedTuple):
    """Tac-Man's settings: numbers, numpy or traced arrays (sweepable under ``vmap``)."""

    speed: ArrayLike  # () exploration speed |v0| [m/s]
    dt: ArrayLike  # () control interval [s]
    dev_high: ArrayLike  # () contact deviation that ends an exploration stage [m]
    dev_low: ArrayLike  # () deviation at which a recovery stage ends [m]
    recovery_gain: ArrayLike  # () fraction of the in-hand pose removed per recovery step (0, 1]
    max_speed: ArrayLike  # () recovery speed cap [m/s] (the rotation is capped at max_speed / 0.05 m)
    reaim: ArrayLike = False  # () bool: after a recovery, re-aim along the handle's net motion (tacman_reaim)


class TacManState(NamedTuple):
    recovering: jax.Array  # () bool: in a recovery (compensation) stage
    direction: jax.Array  # (3,) unit exploration direction, gripper frame
    p_start: jax.Array  # (3,) handle position estimate (world) where the current cycle began [m]
    X_prev: jaxlie.SE3  # last valid in-hand pose estimate


def tacman_init(T_g: jaxlie.SE3, direction) -> TacManState:
    d = jnp.asarray(direction, T_g.wxyz_xyz.dtype)
    return TacManState(jnp.zeros((), bool), d / jnp.linalg.norm(d), T_g.translation(),
                       _identity(T_g.wxyz_xyz.dtype))


def tacman_step(state: TacManState, r: Reading, p: TacManParams):
    """One Tac-Man step (exploration-compensation): ``(state, u_cmd (6,), (valid, X_hat))``.

    Exploration: move at ``speed`` along ``direction`` (gripper frame) until the
    contact deviation exceeds ``dev_high``. Recovery (stop-and-go): the object
    is not driven; the gripper only moves onto the handle (``recovery_gain``
    of the in-hand pose per step, capped at ``max_speed``) until the
    deviation is below ``dev_low``. With ``p.reaim`` False (``tacman``, as the
    Tac-Man papers describe it) the exploration direction stays the fixed
    gripper-frame ``direction``, so the drift off a curved path is corrected
    only in recovery (the zig-zag); with ``p.reaim`` True (``tacman_reaim``,
    our departure) the direction becomes the handle's net displacement over
    the cycle (in the new gripper frame) at the end of each recovery.
    """
    X, valid = kabsch(r.ref, r.cur, r.mask)
    X = jax.tree_util.tree_map(lambda a, b: jnp.where(valid, a, b), X, state.X_prev)
    dev = deviation(X, r.ref, r.mask)
    T_h = r.T_g @ X
    start_rec = (~state.recovering) & (dev > p.dev_high)
    end_rec = state.recovering & (dev < p.dev_low)
    recovering = (state.recovering | start_rec) & ~end_rec
    moved = T_h.translation() - state.p_start
    moved_g = r.T_g.rotation().inverse() @ moved
    dist = jnp.linalg.norm(moved_g)
    new_dir = jnp.where(dist > 1e-4, moved_g / jnp.maximum(dist, 1e-12), state.direction)
    direction = jnp.where(end_rec & jnp.asarray(p.reaim, bool), new_dir, state.direction)
    p_start = jnp.where(end_rec, T_h.translation(), state.p_start)
    rec = _decoupled(X) * p.recovery_gain / p.dt
    v_lim, w_lim = p.max_speed, p.max_speed / 0.05
    rec = jnp.concatenate([_clip(rec[:3], v_lim), _clip(rec[3:], w_lim)])
    explore = jnp.concatenate([p.speed * direction, jnp.zeros(3, direction.dtype)])
    u = jnp.where(recovering, rec, explore)
    return TacManState(recovering, direction, p_start, X), u, (valid, X)


def _identity(dtype) -> jaxlie.SE3:
    return jaxlie.SE3(jnp.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype))


def _clip(v, limit):
    n = jnp.linalg.norm(v)
    return v * jnp.minimum(1.0, limit / jnp.maximum(n, 1e-12))
