"""A hand mounted on an arm as one :class:`~selfid_jax.systems.System`, and each part seen with the other held.

:func:`mount` chains an arm's flange pose, a fixed mounting transform and a
hand's POM pose: for actuators ``q = [q_arm (n_a,), q_hand (n_h,)]``,

    ``p = p_f + R_f (t + R_m p_h)``,  ``R = R_f R_m R_h``

with ``(p_f, R_f)`` the arm's pose at ``q_arm``, ``(t, R_m)`` the hand base
in the flange frame and ``(p_h, R_h)`` the hand's POM pose at ``q_hand`` in
its base frame. :func:`arm_part` and :func:`hand_part` are the same POM seen
through one part's actuators while the other part is held still (the hand's
pose, or the arm's flange pose, is computed once and kept as a constant
transform), so self-ID and control can drive the parts in sequence as the
paper's peg-in-hole does. All three are ordinary systems: they jit, vmap and
differentiate; the parts may be built inside ``jit`` from a traced held
configuration.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.math import geometry
from selfid_jax.systems.system import System, make_system
from selfid_jax.systems.validation import Limits

__all__ = ["MountedPose", "ToolPose", "BasePose", "mount", "arm_part", "hand_part"]

Pose = tuple[jax.Array, jax.Array]


def _chain(a: Pose, b: Pose) -> Pose:
    """``a * b``: the pose ``b`` given in the frame of ``a``."""
    return a[0] + a[1] @ b[0], a[1] @ b[1]


@dataclasses.dataclass(frozen=True)
class MountedPose:
    """Pose map of a hand on an arm: ``params = (arm_params, hand_params, (t (3,), R_m (3, 3)))``."""

    arm: Callable[[Any, jax.Array], Pose]
    hand: Callable[[Any, jax.Array], Pose]
    n_arm: int

    def __call__(self, params, q):
        arm_params, hand_params, mount_tf = params
        flange = self.arm(arm_params, q[: self.n_arm])
        return _chain(_chain(flange, mount_tf), self.hand(hand_params, q[self.n_arm:]))


@dataclasses.dataclass(frozen=True)
class ToolPose:
    """An arm carrying a fixed tool transform: ``params = (arm_params, (t (3,), R (3, 3)))`` in the flange frame."""

    arm: Callable[[Any, jax.Array], Pose]

    def __call__(self, params, q):
        arm_params, tool = params
        return _chain(self.arm(arm_params, q), tool)


@dataclasses.dataclass(frozen=True)
class BasePose:
    """A hand on a fixed base: ``params = (hand_params, (p (3,), R (3, 3)))``, the base in the world frame."""

    hand: Callable[[Any, jax.Array], Pose]

    def __call__(self, params, q):
        hand_params, base = params
        return _chain(base, self.hand(hand_params, q))


def mount(arm: System, hand: System, *, offset=(0.0, 0.0, 0.0), rotation_vector=(0.0, 0.0, 0.0),
          name: str | None = None) -> System:
    """The hand ``hand`` mounted on the flange of ``arm``: ``n_a + n_h`` actuators, a 6-D task.

    Args:
      arm, hand: systems with orientations (``has_rotation``); their limits,
        step limits, self-ID magnitudes and sampling boxes are concatenated.
      offset: ``(3,)`` hand base position in the flange frame [m].
      rotation_vector: ``(3,)`` hand base orientation in the flange frame, as
        a rotation vector [rad].
      name: label (default ``"<arm>+<hand>"``).

    Returns:
      A :class:`System` with ``params = (arm.params, hand.params, (t, R_m))``
      and pose map :class:`MountedPose`; its Jacobian is the forward-mode
      derivative of the chained pose (``System.jacobian``).
    """
    for label, s in (("arm", arm), ("hand", hand)):
        if not isinstance(s, System):
            raise TypeError(f"{label} must be a System, got {type(s).__name__}")
        if not s.has_rotation:
            raise ValueError(f"{label} {s.name!r} has no orientation; mounting needs full poses")
    t = np.asarray(offset, np.float64)
    r = np.asarray(rotation_vector, np.float64)
    if t.shape != (3,) or r.shape != (3,) or not (np.all(np.isfinite(t)) and np.all(np.isfinite(r))):
        raise ValueError(f"offset and rotation_vector must be finite 3-vectors, got {t.tolist()}, {r.tolist()}")
    arm_pose, hand_pose = arm.pose_fn, hand.pose_fn
    if arm_pose is None or hand_pose is None:
        raise ValueError("arm and hand each need a pose_fn")
    dtype = jnp.result_type(float)
    mount_tf = (jnp.asarray(t, dtype), geometry.so3_exp(jnp.asarray(r, dtype)))
    cat = lambda f: np.concatenate([np.asarray(getattr(arm, f)), np.asarray(getattr(hand, f))])
    return make_system(
        name=name or f"{arm.name}+{hand.name}", params=(arm.params, hand.params, mount_tf),
        pose_fn=MountedPose(arm_pose, hand_pose, arm.n_act), has_rotation=True,
        limits=Limits(arm.n_act + hand.n_act, 6, cat("q_low"), cat("q_high"), cat("dq_max"), cat("m_a"),
                      cat("sample_low"), cat("sample_high"), min(arm.min_sigma, hand.min_sigma)),
    )


def _check_mounted(system: System) -> MountedPose:
    if not isinstance(system.pose_fn, MountedPose):
        raise TypeError(f"expected a system built by mount(), got {system.name!r} with pose map "
                        f"{type(system.pose_fn).__name__}")
    return system.pose_fn


def _part(system: System, sl: slice, *, name: str, params, pose_fn, task_dim: int, min_sigma: float) -> System:
    return System(
        params=params, q_low=system.q_low[sl], q_high=system.q_high[sl], dq_max=system.dq_max[sl],
        m_a=system.m_a[sl], sample_low=system.sample_low[sl], sample_high=system.sample_high[sl], name=name,
        n_act=sl.stop - sl.start, task_dim=task_dim, pose_fn=pose_fn, min_sigma=min_sigma, has_rotation=True,
    )


def arm_part(system: System, q_hand, *, task_dim: int = 6) -> System:
    """The mounted POM driven by the arm's actuators, the hand held at ``q_hand (n_h,)`` (may be traced).

    The hand's POM pose at ``q_hand`` becomes a fixed tool transform of the
    arm (:class:`ToolPose`), so the hand's kinematics are evaluated once.
    """
    mp = _check_mounted(system)
    arm_params, hand_params, mount_tf = system.params
    tool = _chain(mount_tf, mp.hand(hand_params, jnp.asarray(q_hand, system.q_low.dtype)))
    return _part(system, slice(0, mp.n_arm), name=f"{system.name}:arm", params=(arm_params, tool),
                 pose_fn=ToolPose(mp.arm), task_dim=task_dim, min_sigma=system.min_sigma)


def hand_part(system: System, q_arm, *, task_axes=None) -> System:
    """The mounted POM driven by the hand's actuators, the arm held at ``q_arm (n_a,)`` (may be traced).

    The arm's flange pose at ``q_arm`` times the mount becomes the hand's fixed
    base (:class:`BasePose`). ``task_axes`` (names or indices, see
    :meth:`System.with_task_axes`) picks the hand's task in world components;
    default the full 6-D pose.
    """
    mp = _check_mounted(system)
    arm_params, hand_params, mount_tf = system.params
    base = _chain(mp.arm(arm_params, jnp.asarray(q_arm, system.q_low.dtype)), mount_tf)
    part = _part(system, slice(mp.n_arm, system.n_act), name=f"{system.name}:hand", params=(hand_params, base),
                 pose_fn=BasePose(mp.hand), task_dim=6, min_sigma=system.min_sigma)
    return part if task_axes is None else part.with_task_axes(task_axes)
