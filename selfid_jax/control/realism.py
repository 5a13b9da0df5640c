"""The real loop's non-idealities: control period, tracker latency, noise and dropouts, servo lag, deadband.

:class:`Realism` is one set of values, shared by the batched simulations (the
``realism`` config section of ``valid_region``, ``tracking`` and
``peg_in_hole``, traced so that one compiled program serves a sweep over them)
and by the virtual robot (:mod:`selfid_jax.robot.virtual`). :data:`IDEAL`
(every field at its default) reproduces the ideal kinematic loop: the follow
loop and the self-ID samples bit for bit with the values traced (tests/test_realism.py); the
refined self-ID estimate to rounding (XLA's CPU backend contracts
multiply-adds into FMAs where it fuses them, and a program with traced
realism values may fuse the refinement differently).

Model, per control step of ``period`` seconds, actuator targets ``u``:

* deadband: a commanded change ``|u_i - q_i| <= deadband_i`` produces no motion;
* servo lag: the actuators move ``q <- q + (u - q) (1 - exp(-period / servo_tau))``
  (first order; ``servo_tau = 0`` reaches the target within the step);
* the tracker reports the pose of ``latency`` whole control steps ago, with
  Gaussian noise of ``noise_pos`` metres and ``noise_rot`` radians per axis
  (rotation noise as a random rotation vector), and with probability
  ``dropout`` per reading no pose at all (the reading is the last good one
  and the dropout is counted; the follow loop makes no waypoint test and no
  new command from it, as the live runner waits for a fresh pose, and a
  self-ID sample with it is rejected).

The controller commands relative to the *measured* actuator positions: each
step it reads ``q`` (the encoders: exact and without delay, as
:class:`selfid_jax.robot.protocol.Observation` reports it) and the tracker
pose, and sends the absolute target ``u = apply(q, dq)`` (the step clipped to
``dq_max``, the target to the actuator limits), as the robot protocol's
``move(target)`` does. So a step below the deadband never moves, however
often it is repeated, and under servo lag each step realises the fraction
``1 - exp(-period / servo_tau)`` of what was commanded. The virtual robot
follows the same rule.

What is traced and what is static: every field may be traced (and carry a
batch axis under ``vmap``) except what sizes a buffer: the tracker's history
holds ``max_latency + 1`` poses (:func:`tracker`, a static size), and a traced
``latency`` is clipped to ``[0, max_latency]``. One compiled program
therefore serves a sweep over every value, latency included, up to
``max_latency``.

The actuators are a :class:`Plant`: :func:`servo_plant` (the default) is
the kinematic model above (lag, deadband); :func:`dynamic_plant` steps an
arm's own physics instead (:class:`selfid_jax.systems.dynamic.DynamicArm`:
its position servos, inertia and gravity in MJX), so the joints lag and
overshoot as the servo gains and masses make them.

Functions (pure, jit- and vmap-able): :func:`servo` (one control step of the
actuators), :func:`tracker` / :func:`push` / :func:`read` (the tracker's
history and its readings; :func:`with_tracker_noise` adds an experiment's
noise levels to them), and :func:`self_id_sampler`, Algorithm 1's
move-then-observe sample under these effects (an ``observe`` for
:func:`selfid_jax.identify.algorithm.self_identify`). The follow loop uses them
in :func:`selfid_jax.control.loop.follow_law` (its ``realism`` argument).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.math.geometry import noisy_pose

__all__ = ["Realism", "IDEAL", "Plant", "SelfIdEnv", "Tracker", "check_max_latency", "check_plant", "check_realism",
           "dynamic_plant", "latency_bound", "push", "read", "self_id_sampler", "servo", "servo_gain", "servo_plant",
           "tracker", "with_tracker_noise"]


class Realism(NamedTuple):
    """Values of the non-idealities (scalars; any field may carry a batch axis under ``vmap`` where traced)."""

    period: Any = 0.0  # s, control period; 0: the ideal loop, where servo_tau has no effect
    # whole control steps between a pose and its tracker reading, >= 0; may be traced (int) under a static
    # max_latency, which sizes the tracker's history (see the module docstring)
    latency: Any = 0
    noise_pos: Any = 0.0  # m, standard deviation of the tracker position noise per axis
    noise_rot: Any = 0.0  # rad, standard deviation of the tracker rotation noise per axis
    dropout: Any = 0.0  # probability in [0, 1) that a tracker reading is missing
    servo_tau: Any = 0.0  # s, first-order servo time constant (0: no lag)
    deadband: Any = 0.0  # actuator units, commanded changes at most this large produce no motion


IDEAL = Realism()


def _concrete(value) -> np.ndarray | None:
    """``value`` as a float64 array, or None if it is traced (a jax Tracer has an ``aval``)."""
    if isinstance(value, jax.core.Tracer):
        return None
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        if hasattr(value, "aval"):
            return None
        raise ValueError(f"expected a number, got {value!r}") from None


def check_realism(r: Realism) -> Realism:
    """``r`` with concrete values checked (non-negative, finite, ``dropout < 1``, integer ``latency``).

    Fields may be scalars or arrays (a batch of values); each concrete one is
    checked elementwise. Raises ValueError naming the field and its value.
    Traced values are not checked. A concrete scalar ``latency`` comes back
    as a Python ``int``, an array of them as ``int32``.
    """
    if not isinstance(r, Realism):
        raise TypeError(f"realism must be a Realism, got {type(r).__name__}")
    for name in Realism._fields:
        value = getattr(r, name)
        try:
            arr = _concrete(value)
        except ValueError:
            raise ValueError(f"realism.{name}: expected a number, got {value!r}") from None
        if arr is None:
            continue
        if not np.all(np.isfinite(arr)) or np.any(arr < 0):
            raise ValueError(f"realism.{name}: must be finite and >= 0, got {value!r}")
    dropout = _concrete(r.dropout)
    if dropout is not None and np.any(dropout >= 1):
        raise ValueError(f"realism.dropout: must be < 1, got {r.dropout!r}")
    latency = _concrete(r.latency)
    if latency is None:
        return r
    if np.any(latency != np.round(latency)):
        raise ValueError(f"realism.latency: whole control steps, got {r.latency!r}")
    return r._replace(latency=int(latency) if latency.ndim == 0 else latency.astype(np.int32))


def latency_bound(r: Realism, max_latency: int | None) -> int:
    """The static history length ``max_latency`` for ``r``: as given, or ``r.latency``'s largest concrete value.

    ``ValueError`` if ``max_latency`` is None and ``latency`` is traced (its
    bound must be known before tracing), or if it is negative.
    """
    if max_latency is None:
        latency = _concrete(r.latency)
        if latency is None:
            raise ValueError("max_latency: required when realism.latency is traced (it sizes the tracker's history)")
        return int(np.max(latency, initial=0))
    if isinstance(max_latency, bool) or not isinstance(max_latency, (int, np.integer)) or max_latency < 0:
        raise ValueError(f"max_latency: expected an integer >= 0, got {max_latency!r}")
    return int(max_latency)


def check_max_latency(r: Realism, max_latency: int) -> None:
    """``ValueError`` if a concrete ``r.latency`` exceeds ``max_latency`` (a traced one is clipped to it)."""
    latency = _concrete(r.latency)
    if latency is not None and np.any(latency > max_latency):
        raise ValueError(f"realism.latency {r.latency!r} exceeds max_latency {max_latency}: the tracker keeps "
                         f"max_latency + 1 poses; raise max_latency")


# ------------------------------------------------------------------ actuators

def servo_gain(r: Realism) -> jax.Array:
    """``()`` fraction of a commanded change the actuators realise in one control step: ``1 - exp(-period /
    servo_tau)``, exactly 1 where ``servo_tau = 0`` or ``period = 0`` (no lag)."""
    period, tau = jnp.asarray(r.period), jnp.asarray(r.servo_tau)
    lag = (period > 0) & (tau > 0)
    return jnp.where(lag, -jnp.expm1(-period / jnp.where(lag, tau, 1.0)), 1.0)


def servo(q: jax.Array, u: jax.Array, r: Realism) -> jax.Array:
    """Actuator positions ``(n,)`` one control step after commanding targets ``u (n,)`` from ``q (n,)``.

    Deadband: an actuator with ``|u_i - q_i| <= deadband`` stays where it is;
    the others move the fraction :func:`servo_gain` of the way (first-order
    lag). Without lag the result is ``u`` itself, bit for bit. Actuator units
    (rad or m); ``deadband`` a scalar or ``(n,)``.
    """
    a = servo_gain(r)
    moved = jnp.where(a >= 1.0, u, q + a * (u - q))
    return jnp.where(jnp.abs(u - q) > r.deadband, moved, q)


class Plant(NamedTuple):
    """The actuators between two control steps, as three pure functions over the plant's own state (a pytree).

    ``init(q0 (n,)) -> state``: at rest at ``q0`` [rad / m].
    ``step(state, u (n,), r: Realism) -> state``: one control period under
    the commanded targets ``u`` [rad / m].
    ``q(state) -> (n,)``: the measured actuator positions [rad / m] (the encoders).
    """

    init: Callable[[jax.Array], Any]
    step: Callable[[Any, jax.Array, Realism], Any]
    q: Callable[[Any], jax.Array]


def servo_plant() -> Plant:
    """The kinematic actuators of the module docstring: the state is ``q (n,)`` itself and a step is :func:`servo`
    (lag ``servo_tau``, ``deadband``); without lag and deadband the actuators reach ``u`` exactly."""
    return Plant(init=lambda q0: q0, step=lambda q, u, r: servo(q, u, r), q=lambda q: q)


def dynamic_plant(arm, substeps: int) -> Plant:
    """An arm's own physics as the plant: each control step sets the position servos' targets to ``u`` and runs
    ``substeps`` (static) physics steps of ``arm`` (a :class:`~selfid_jax.systems.dynamic.DynamicArm`, or any object
    with its ``init(q0)``, ``control_step(state, u, substeps=k)`` and ``q(state)``).

    The servo lag and overshoot are the arm's (gains, inertia, damping,
    gravity not compensated); the :class:`Realism` ``servo_tau`` and
    ``deadband`` do not apply (the step ignores ``r``), and the control
    period is ``substeps`` times the arm's ``timestep`` (see
    :func:`~selfid_jax.systems.dynamic.substeps_for`). The state is an
    ``mjx.Data``; it starts at rest with ``ctrl = q0``.
    """
    if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise ValueError(f"dynamic_plant: substeps must be a positive integer (static), got {substeps!r}")
    k = int(substeps)
    for attr in ("init", "control_step", "q"):
        if not callable(getattr(arm, attr, None)):
            raise TypeError(f"dynamic_plant: {type(arm).__name__} has no {attr}(); expected a DynamicArm")
    return Plant(init=arm.init, step=lambda d, u, r: arm.control_step(d, u, substeps=k), q=arm.q)


def check_plant(plant: Plant | None, n_act: int) -> None:
    """Raise ``TypeError`` unless ``plant`` is None or a :class:`Plant`; ``ValueError`` if a dynamic arm's actuator
    count differs from the system's ``n_act`` (checked where the arm states it)."""
    if plant is None:
        return
    if not isinstance(plant, Plant):
        raise TypeError(f"plant must be a realism.Plant (servo_plant() or dynamic_plant(arm, substeps)), "
                        f"got {type(plant).__name__}")
    arm = getattr(plant.q, "__self__", None)
    n = getattr(arm, "n_act", None)
    if n is not None and int(n) != int(n_act):
        raise ValueError(f"plant: the dynamic arm {getattr(arm, 'name', '')!r} has {n} actuators, the system "
                         f"{n_act}: build both from the same robot file")


# ------------------------------------------------------------------ tracker

class Tracker(NamedTuple):
    """The tracker's recent history (true poses, one per control step) and its last good reading."""

    p: jax.Array  # (B, 3) true POM positions of the last B = max_latency + 1 control steps, a ring buffer [m]
    R: jax.Array  # (B, 3, 3) their orientations
    t: jax.Array  # () int32 poses pushed; the newest is in slot t % B
    held_p: jax.Array  # (3,) last good reading's position [m] (what a dropout reports)
    held_R: jax.Array  # (3, 3) last good reading's orientation


def with_tracker_noise(r: Realism | None, pose_noise=0.0, rot_noise=0.0) -> Realism:
    """``r`` (:data:`IDEAL` if None) with ``pose_noise`` [m] and ``rot_noise`` [rad] added to its tracker noise.

    The one tracker the experiments' self-ID samples and path following both
    read: an experiment's noise levels (``pose_noise``, ``rot_noise``) and a
    ``realism`` section's ``noise_pos``, ``noise_rot`` (configs set at most
    one of each pair) are the sd of one reading. Pure; every argument may be
    traced. Zero noise leaves ``r``'s values as they were, bit for bit.
    """
    r = IDEAL if r is None else r
    return r._replace(noise_pos=pose_noise + r.noise_pos, noise_rot=rot_noise + r.noise_rot)


def tracker(pose0, max_latency: int) -> Tracker:
    """A tracker whose history is ``max_latency + 1`` copies of ``pose0 = (p (3,), R (3, 3))`` (at rest before
    the start), which is also its last good reading. ``max_latency`` is static."""
    p0, R0 = pose0
    B = int(max_latency) + 1
    return Tracker(p=jnp.broadcast_to(p0, (B,) + p0.shape), R=jnp.broadcast_to(R0, (B,) + R0.shape),
                   t=jnp.zeros((), jnp.int32), held_p=p0, held_R=R0)


def push(tr: Tracker, pose) -> Tracker:
    """``tr`` with the true pose ``(p (3,), R (3, 3))`` of one more control step as its newest entry."""
    B = tr.p.shape[0]
    t = tr.t + 1
    slot = t % B
    return tr._replace(p=tr.p.at[slot].set(pose[0]), R=tr.R.at[slot].set(pose[1]), t=t)


def _replace_newest(tr: Tracker, pose) -> Tracker:
    """``tr`` with its newest entry set to ``pose`` (the same pose, recomputed)."""
    slot = tr.t % tr.p.shape[0]
    return tr._replace(p=tr.p.at[slot].set(pose[0]), R=tr.R.at[slot].set(pose[1]))


def read(tr: Tracker, key: jax.Array, r: Realism, *, always_noise: bool = False):
    """One tracker reading: ``((p (3,), R (3, 3)), dropped () bool, tracker)``.

    The pose ``r.latency`` entries before the newest (clipped to the history,
    ``[0, B - 1]``; before the start: the start pose), with
    :func:`~selfid_jax.math.geometry.noisy_pose` noise of ``r.noise_pos`` [m] and
    ``r.noise_rot`` [rad] drawn from ``key``; with probability ``r.dropout``
    (drawn from ``fold_in(key, 1)``) no pose: the reading is the last good
    one and ``dropped`` is True. A good reading becomes the last good one.
    Zero noise leaves the pose exactly as it was unless ``always_noise``
    (static; then ``p + 0 * n`` is added as the self-ID sampler always did).
    """
    B = tr.p.shape[0]
    L = jnp.clip(jnp.asarray(r.latency).astype(jnp.int32), 0, B - 1)
    slot = (tr.t - L) % B
    p, R = tr.p[slot], tr.R[slot]
    p_n, R_n = noisy_pose(key, (p, R), r.noise_pos, r.noise_rot)
    if always_noise:
        p, R = p_n, R_n
    else:
        p, R = jnp.where(jnp.asarray(r.noise_pos) > 0, p_n, p), jnp.where(jnp.asarray(r.noise_rot) > 0, R_n, R)
    dropped = jax.random.uniform(jax.random.fold_in(key, 1), (), p.dtype) < r.dropout
    p, R = jnp.where(dropped, tr.held_p, p), jnp.where(dropped, tr.held_R, R)
    return (p, R), dropped, tr._replace(held_p=p, held_R=R)


# ------------------------------------------------------------------ self-ID sampling

class SelfIdEnv(NamedTuple):
    """The environment of :func:`self_id_sampler`: the robot and its tracker between self-ID samples."""

    q: jax.Array  # (n,) actuator positions (rad or m)
    tracker: Tracker
    dropouts: jax.Array  # () int32 tracker readings that dropped out (each rejects its sample)
    plant: Any = None  # with a Plant other than the kinematic servo: its state (e.g. an mjx.Data); q = plant.q(it)


def self_id_sampler(system, r: Realism, q0, *, pose_noise=0.0, rot_noise=0.0, settle=1, max_settle: int = 1,
                    max_latency: int | None = None, plant: Plant | None = None
                    ) -> tuple[Callable[[SelfIdEnv, jax.Array, jax.Array], tuple[SelfIdEnv, jax.Array]], SelfIdEnv]:
    """Algorithm 1's sample (move, then observe) under ``r``: ``(observe, env0)`` for
    :func:`~selfid_jax.identify.algorithm.self_identify`.

    ``observe(env, key, dtheta (n,)) -> (env, V (m,))``: read the tracker
    (``before``), command ``u = system.apply(q, dtheta)`` from the measured
    ``q``, let ``settle`` control steps pass (each: :func:`servo` towards
    ``u``, the true pose pushed to the tracker), read the tracker again
    (``after``) and return ``V = system.task_difference(after, before)``.
    The estimator receives the commanded ``dtheta``, as Algorithm 1 does,
    whether or not the actuators arrived. A dropout in either reading makes
    ``V`` NaN: the estimator rejects the sample and counts it
    (``state.rejected``) and the sampler counts the dropout
    (``env.dropouts``). Tracker noise per reading: ``pose_noise +
    r.noise_pos`` [m] and ``rot_noise + r.noise_rot`` [rad]
    (:func:`with_tracker_noise`: the noise of
    :func:`selfid_jax.identify.algorithm.run` plus the tracker's own;
    configs set at most one of each pair), with the keys that ``run`` uses,
    so under :data:`IDEAL` with ``settle = 1`` each sample is ``run``'s, bit
    for bit. With ``settle <= latency`` the after-reading still shows the
    pose before the move (a real loop has to wait out its tracker).

    ``settle`` may be traced: steps ``s < settle`` of a static ``max_settle``
    are taken (clipped to ``[1, max_settle]``); ``max_latency`` as for
    :func:`latency_bound`. ``env0`` starts at ``q0 (n,)`` at rest, its
    tracker history filled with the start pose.

    ``plant`` (default :func:`servo_plant`): the actuators' model per control
    step; with :func:`dynamic_plant` each step runs the arm's physics and the
    measured ``q`` is its joint positions (``env.plant`` its state).
    """
    check_plant(plant, system.n_act)
    max_latency = latency_bound(r, max_latency)
    check_max_latency(r, max_latency)
    if isinstance(max_settle, bool) or not isinstance(max_settle, (int, np.integer)) or max_settle < 1:
        raise ValueError(f"max_settle: expected a positive integer, got {max_settle!r}")
    max_settle = int(max_settle)
    sensed = with_tracker_noise(r, pose_noise, rot_noise)
    q0 = jnp.asarray(q0, jnp.result_type(float))
    settle = jnp.clip(jnp.asarray(settle).astype(jnp.int32), 1, max_settle)

    def observe(env: SelfIdEnv, key, dtheta):
        k_before, k_after = jax.random.split(key)
        # the newest entry is the pose at env.q; recomputed here, at the level where run() computes it, because
        # XLA's CPU kernels may round sin/cos differently in another loop (IDEAL then equals run() bit for bit)
        tr = _replace_newest(env.tracker, system.pose(env.q))
        before, drop_b, tr = read(tr, k_before, sensed, always_noise=True)
        u = system.apply(env.q, dtheta)
        # the actuators' state: q itself for the kinematic servo, the plant's own state otherwise
        x0 = env.q if plant is None else env.plant

        def advance(x):
            if plant is None:
                return servo(x, u, r)
            return plant.step(x, u, r)

        def q_of(x):
            return x if plant is None else plant.q(x).astype(q0.dtype)

        def wait(carry, s):  # the control steps before the last one: s < settle - 1
            x, tr = carry
            active = s < settle - 1
            x_next = jax.tree.map(lambda a, b: jnp.where(active, a, b), advance(x), x)
            tr = jax.tree.map(lambda a, b: jnp.where(active, a, b), push(tr, system.pose(q_of(x_next))), tr)
            return (x_next, tr), None

        x = x0
        if max_settle > 1:
            (x, tr), _ = jax.lax.scan(wait, (x, tr), jnp.arange(max_settle - 1))
        x = advance(x)  # the last control step, its pose computed at this level as run() does
        q = q_of(x)
        tr = push(tr, system.pose(q))
        after, drop_a, tr = read(tr, k_after, sensed, always_noise=True)
        V = system.task_difference(after, before)
        V = jnp.where(drop_b | drop_a, jnp.nan, V)
        dropouts = env.dropouts + drop_b.astype(jnp.int32) + drop_a.astype(jnp.int32)
        return SelfIdEnv(q, tr, dropouts, None if plant is None else x), V

    x0 = None if plant is None else plant.init(q0)
    env0 = SelfIdEnv(q0 if plant is None else plant.q(x0).astype(q0.dtype), tracker(system.pose(q0), max_latency),
                     jnp.zeros((), jnp.int32), x0)
    return observe, env0
