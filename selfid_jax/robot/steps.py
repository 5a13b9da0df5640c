"""The live runner's per-sample steps: the pose change of a sample, the jitted identification step, the follow step.

:func:`sample_step` runs :func:`selfid_jax.identify.step.sample_step` (the
per-sample step of Algorithm 1 and ``fit``) jitted once per ``(n, m, method,
dtype)``; :func:`follow_command` runs :func:`selfid_jax.control.law.command`
(the simulated follow loop's control step) on the host in float64. The
session (:mod:`selfid_jax.robot.session`) calls them once per move.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import numpy as np

from selfid_jax.control.law import Command, command, inverse_jacobian_law
from selfid_jax.control.sources import fixed
from selfid_jax.control.task import ControllerParams, Task
from selfid_jax.identify import estimator
from selfid_jax.identify.refine import needs_samples
from selfid_jax.identify.step import StepInfo
from selfid_jax.identify.step import sample_step as identify_step
from selfid_jax.math import geometry
from selfid_jax.math.checks import float_dtype
from selfid_jax.robot.log import pairs_from_time_series, rotations
from selfid_jax.robot.protocol import Observation

__all__ = ["follow_command", "host_step", "init_state", "sample_step", "task_difference", "waypoint_errors"]


def task_difference(obs: Observation, prev: Observation, axes: Sequence[int]) -> np.ndarray:
    """``V (m,) = [p - p_prev, log(R R_prev^T)][axes]`` between two tracker poses (m; rad for rotation axes).

    :func:`selfid_jax.robot.log.pairs_from_time_series` on the two rows, so an
    online sample is exactly what ``fit`` would form from the same time series.
    """
    p = np.stack([prev.position, obs.position])
    R = None if all(a < 3 for a in axes) else rotations("quaternion", np.stack([prev.quaternion, obs.quaternion]))
    return pairs_from_time_series(np.zeros((2, 1)), p, R, axes)[1][0]


_step = jax.jit(identify_step, static_argnames=("method", "options"))


def init_state(n: int, m: int, *, method: str = "closed_form", v_tol: float = 1e-9, max_samples: int = 200,
               dtype=None) -> estimator.EstimatorState:
    """Empty estimator for a session: no sample buffer unless the refinement needs one (then ``max_samples``)."""
    capacity = max_samples if needs_samples(method) else 0
    return estimator.init(n, m, capacity=capacity, v_tol=v_tol, dtype=float_dtype() if dtype is None else dtype)


def sample_step(state: estimator.EstimatorState, dtheta, V, eps, eps_rel, *, method: str = "closed_form",
                min_count: int = 0) -> tuple[estimator.EstimatorState, StepInfo]:
    """One accepted sample ``(dtheta (n,), V (m,))`` through :func:`selfid_jax.identify.step.sample_step`, jitted.

    ``eps`` and ``eps_rel`` are passed as arrays of the state's dtype, so one
    compilation per ``(n, m, method, dtype)`` serves every threshold and every
    sample of every session in the process. The inputs are cast with numpy
    (``jit`` transfers numpy arguments on its fast path; ``jnp.asarray`` on
    each would cost more than the step itself at batch 1).
    """
    dtype = state.estimate.dtype
    return _step(state, np.asarray(dtheta, dtype), np.asarray(V, dtype), np.asarray(eps, dtype),
                 np.asarray(eps_rel, dtype), method=method, options=(), min_count=np.int32(min_count))


def host_step(state: estimator.EstimatorState, dtheta, V, eps, eps_rel, *, method: str = "closed_form",
              min_count: int = 0) -> tuple[estimator.EstimatorState, StepInfo, int]:
    """:func:`sample_step` and what the online loop reads back: ``(state, info as numpy, converged_at)``.

    One ``device_get`` of the info and ``converged_at`` together: the whole
    per-sample cost of the loop's estimator (``benchmarks/online_step.py``).
    """
    state, info = sample_step(state, dtheta, V, eps, eps_rel, method=method, min_count=min_count)
    info, conv = jax.device_get((info, state.converged_at))
    return state, info, int(conv)


@functools.partial(jax.jit, static_argnames=("axes",))
def _follow_command(Jinv, offsets, p0, quat0, waypoint, q, p, quat, ctrl, *, axes):
    R0, R = geometry.quaternion_to_rotation(quat0), geometry.quaternion_to_rotation(quat)
    law = inverse_jacobian_law(None, fixed(Jinv))
    task = Task.from_axes(offsets, (p0, R0), axes)
    state = law.init(q)
    observe = law.observe
    assert observe is not None  # a law on a fixed estimate observes without a model
    return command(law, task, ctrl, state, waypoint, q, (p, R), observe(state, q)), task.path_distance(p)


def follow_command(Jinv: np.ndarray, offsets: np.ndarray, anchor: Observation, waypoint: int, obs: Observation,
                   ctrl: ControllerParams, axes: tuple[int, ...]) -> tuple[Command, float]:
    """The follow loop's control step at the reading ``obs``, on the host in float64: ``(command, path distance)``.

    :func:`selfid_jax.control.law.command` with ``inverse_jacobian_law`` on the
    constant ``Jinv (n, m)``, towards waypoint offsets ``offsets (W, m)`` taken
    from the pose of ``anchor``; the path distance [m] is that of ``obs``'s
    position (:meth:`~selfid_jax.control.task.Task.path_distance`). The same
    function :func:`selfid_jax.control.loop.follow_law` runs under ``scan``,
    compiled once per ``(n, m, W, axes)``. Returned as numpy.
    """
    with jax.enable_x64(True):
        f64 = functools.partial(np.asarray, dtype=np.float64)
        ctrl = jax.tree.map(f64, ctrl)
        out = _follow_command(f64(Jinv), f64(offsets), f64(anchor.position), f64(anchor.quaternion),
                              np.int32(waypoint), f64(obs.q), f64(obs.position), f64(obs.quaternion), ctrl,
                              axes=tuple(axes))
        cmd, dist = jax.device_get(out)
    return cmd, float(dist)


@functools.partial(jax.jit, static_argnames=("axes",))
def _waypoint_errors(offsets, p0, quat0, p, quat, *, axes):
    task = Task.from_axes(offsets, (p0, geometry.quaternion_to_rotation(quat0)), axes)
    seen = (p, geometry.quaternion_to_rotation(quat))
    e_p, e_r = jax.vmap(lambda w: task.error(seen, w))(jax.numpy.arange(offsets.shape[0]))
    return jax.numpy.linalg.norm(e_p, axis=-1), jax.numpy.linalg.norm(e_r, axis=-1)


def waypoint_errors(offsets: np.ndarray, anchor: Observation, obs: Observation,
                    axes: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``(|e_p| (W,), |e_r| (W,))``: the norms of the position [m] and rotation [rad] errors from ``obs``'s pose to
    each of the ``W`` waypoints ``offsets (W, m)`` taken from ``anchor``'s pose, as
    :meth:`selfid_jax.control.task.Task.error` (the follow law's waypoint test) computes them; float64 numpy
    (rotation errors zero for a task without rotation axes)."""
    with jax.enable_x64(True):
        f64 = functools.partial(np.asarray, dtype=np.float64)
        out = _waypoint_errors(f64(offsets), f64(anchor.position), f64(anchor.quaternion), f64(obs.position),
                               f64(obs.quaternion), axes=tuple(axes))
        e_p, e_r = jax.device_get(out)
    return np.asarray(e_p, np.float64), np.asarray(e_r, np.float64)
