"""The follow loop's per-step law: what it senses, and the one control step shared by simulation and the robot.

:class:`StepLaw` is the pluggable actuator law (``dq = Jinv(q) @ V`` from
:func:`inverse_jacobian_law`; the E-KM's QP from
:func:`selfid_jax.control.qp.constrained_law`). :func:`command` is one control
step around it, the same function under :func:`selfid_jax.control.loop.follow_law`'s
``lax.scan`` and on the host in the live runner (:mod:`selfid_jax.robot.session`),
so a simulated tracking result describes what the robot does with the same
settings: the waypoint test, the twist with its position and rotation parts
clipped separately, the law's step, and the per-actuator cap.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from selfid_jax.control.sources import FromFunction, JinvFn, JinvSource
from selfid_jax.control.task import ControllerParams, Task, cap_actuator_step

__all__ = ["Command", "StepLaw", "command", "inverse_jacobian_law"]


class StepLaw(NamedTuple):
    """A per-step actuator law of the follow loop: pure functions over the law's own state (optax-style).

    ``init(q0 (n,)) -> state``: the law's state at the start (a pytree of
    fixed-shape arrays; ``()`` for a memoryless law).

    ``sense(state, q (n,)) -> (pose, aux)``: the POM pose ``(p (3,), R (3, 3))``
    at ``q`` from the system's model and whatever the law computed with it
    (e.g. the Jacobian from the same kinematics pass), handed back to ``step``.

    ``step(state, q, pose, aux, V (m,)) -> (dq (n,), state, ok ())``: the
    actuator step for the commanded twist ``V`` (before the per-actuator cap
    and ``system.apply``), the state after a move, and a bool that is False
    where the law's own quantities are unusable (a non-finite Jacobian), which
    fails the rollout or stops the robot. The loop keeps the new state only on
    steps that move.

    ``observe(state, q) -> aux`` (optional): ``aux`` without the model, for a
    pose measured elsewhere (a tracker): what the law needs to run on a robot.
    None: the law needs the system's model and runs in simulation only.
    """

    init: Callable[[jax.Array], Any]
    sense: Callable[[Any, jax.Array], tuple[tuple[jax.Array, jax.Array], Any]]
    step: Callable[[Any, jax.Array, tuple[jax.Array, jax.Array], Any, jax.Array], tuple[jax.Array, Any, jax.Array]]
    observe: Callable[[Any, jax.Array], Any] | None = None


def inverse_jacobian_law(system, jinv: JinvSource | JinvFn) -> StepLaw:
    """``dq = Jinv(q) @ V``, ``Jinv (n, m)`` from :func:`~selfid_jax.control.sources.fixed`,
    :func:`~selfid_jax.control.sources.true_inverse`, :func:`~selfid_jax.control.sources.scaled_true_inverse`,
    any object with ``pose_and_jinv(system, q)`` or a plain ``jinv_fn(q) -> (n, m)``; stateless.

    ``system``: the :class:`~selfid_jax.systems.System` whose pose map ``sense``
    evaluates; None for a law that only runs live (``observe``; a source that
    needs no model: a fixed estimate or a function of ``q``). A non-finite
    ``Jinv`` fails the rollout; one of the wrong shape raises ``ValueError``
    while tracing.
    """
    source = jinv if hasattr(jinv, "pose_and_jinv") else FromFunction(jinv)

    def sense(state, q):
        if system is None:
            raise ValueError("inverse_jacobian_law: no system to sense the pose with (built for a robot: observe)")
        pose, J = source.pose_and_jinv(system, q)
        n, m = system.n_act, system.task_dim
        if J.shape != (n, m):  # static: raised while tracing, before any compute
            raise ValueError(f"jinv: the inverse Jacobian has shape {J.shape}, expected ({n}, {m}) = (n_act, task_dim)")
        return pose, J

    def step(state, q, pose, J, V):
        return J @ V, state, jnp.all(jnp.isfinite(J))

    observe = (lambda state, q: source(q)) if callable(source) and not hasattr(source, "system") else None
    return StepLaw(init=lambda q0: (), sense=sense, step=step, observe=observe)


class Command(NamedTuple):
    """One control step's decision (:func:`command`)."""

    waypoint: jax.Array  # () int32 waypoint pursued after this step's test (W once the last is reached)
    reached: jax.Array  # () bool: the waypoint pursued before this step was reached by the pose seen
    error: jax.Array  # (P,) position error [m] from the pose seen to the waypoint pursued before this step
    V: jax.Array  # (m,) commanded twist towards the waypoint pursued after the test
    dq: jax.Array  # (n,) actuator step from the law, capped to ctrl.max_dq (before the limits)
    law: Any  # the law's state after the move
    ok: jax.Array  # () bool: the law's quantities were usable (False fails a rollout / stops the robot)


def command(law: StepLaw, task: Task, ctrl: ControllerParams, law_state, waypoint, q, seen, aux,
            active=True) -> Command:
    """One control step from the pose ``seen = (p (3,), R (3, 3))`` at actuator positions ``q (n,)``.

    The waypoint ``waypoint ()`` counts as reached where ``active`` and the
    seen error is within ``ctrl.tol`` [m] (and ``ctrl.rot_tol`` [rad]), and
    the next one is pursued (one waypoint per step); the twist ``V`` towards
    it is ``ctrl.gain`` times the error, position part clipped to
    ``ctrl.max_step`` [m] and rotation part to ``ctrl.max_rot_step`` [rad]
    (:meth:`Task.twist`); ``law.step`` turns it into ``dq``, which
    :func:`~selfid_jax.control.task.cap_actuator_step` scales to
    ``ctrl.max_dq``. The caller applies ``dq`` within the actuator limits, and
    moves only while a waypoint remains and the path distance
    (:meth:`Task.path_distance`) is within ``diverge_dist``. Pure: the
    simulated loop runs it traced, the live runner eagerly.
    """
    W = task.path.shape[0]
    e_p, e_r = task.error(seen, waypoint)
    reached = active & (waypoint < W) & task.reached(e_p, e_r, ctrl)
    waypoint = waypoint + reached.astype(jnp.asarray(waypoint).dtype)
    e_p_next, e_r_next = task.error(seen, waypoint)
    V = task.twist(e_p_next, e_r_next, ctrl)
    dq, learned, ok = law.step(law_state, q, seen, aux, V)
    return Command(waypoint=waypoint, reached=reached, error=e_p, V=V, dq=cap_actuator_step(dq, ctrl.max_dq),
                   law=learned, ok=ok)
