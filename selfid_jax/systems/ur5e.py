"""Universal Robots UR5e from the shipped MJCF (``assets/ur5e.xml``, written from UR's DH data)."""

from __future__ import annotations

from importlib import resources

import numpy as np

from selfid_jax.systems.mjcf import from_mjcf
from selfid_jax.systems.system import System

__all__ = ["ur5e", "UR5E_XML", "UR5E_HOME"]

#: Path of the shipped MJCF (site "ee" = DH tool flange frame 6).
UR5E_XML = str(resources.files("selfid_jax.systems") / "assets" / "ur5e.xml")

#: A working configuration (rad): elbow bent, wrist bent, flange pointing down
#: at about (-0.49, -0.13, 0.49) m in the base frame.
UR5E_HOME = (0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0)

# Sampling box (rad) around UR5E_HOME, away from the three UR singularities:
# elbow q3 in [1.0, 2.1] (straight 0 / folded pi), wrist q5 in [-2.3, -0.8]
# (0 / -pi: joints 4 and 6 aligned), and shoulder: the wrist stays >= ~0.2 m in
# front of the base axis (a2 c2 + a3 c23 + d5 s234 <= -0.2 m over the box).
# The flange stays in front of the robot (x in about [-0.76, -0.17] m of the
# DH base frame, q1 in [-0.6, 0.6]) and above the base plane (z >= ~0.04 m).
# Over the box: sigma_min of the 3-D Jacobian >= ~0.18 m/rad and of the 6-D
# Jacobian >= ~0.13 (checked on 20k uniform draws), so the default thresholds
# below reject almost nothing inside the box; they guard user-supplied boxes.
_SAMPLE_LOW = (-0.6, -1.8, 1.0, -2.3, -2.3, -1.0)
_SAMPLE_HIGH = (0.6, -1.0, 2.1, -0.9, -0.8, 1.0)
_MIN_SIGMA = {2: 0.05, 3: 0.1, 6: 0.1}


def ur5e(
    *,
    task_dim: int = 3,
    m_a=0.03,
    dq_max: float = 0.1,
    sample_low=_SAMPLE_LOW,
    sample_high=_SAMPLE_HIGH,
    min_sigma: float | None = None,
    fk: str = "chain",
) -> System:
    """UR5e arm: 6 hinge actuators, POM = tool flange (site ``"ee"``).

    The actuators are the MJCF's six position servos ``act1..act6``, one per
    joint (``q = qpos``). Joint limits +-2 pi rad (joint ranges and servo
    ``ctrlrange`` of the MJCF). Forward kinematics reproduce the
    standard DH chain ``prod_i Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)`` exactly,
    world frame = DH base frame (no extra base transform).

    Args:
      task_dim: 3 (flange position, default), 6 (position + rotation vector)
        or 2 (xy only).
      m_a: safe self-ID magnitude (rad), scalar or ``(6,)``.
      dq_max: per-step actuator limit (rad).
      sample_low, sample_high: ``(6,)`` sampling box (rad), default a box of
        non-singular working configurations around :data:`UR5E_HOME`.
      min_sigma: ``sample_configs`` threshold on the Jacobian's smallest
        singular value; default 0.1 (task_dim 3: m/rad; task_dim 6: mixed
        m/rad and rad/rad units) or 0.05 m/rad (task_dim 2).
      fk: ``"chain"`` (plain-JAX joint chain, default, faster) or ``"mjx"``
        (``mjx.kinematics``); equal to 1e-12.

    Returns:
      A :class:`System` whose ``params`` is a
      :class:`~selfid_jax.systems.kinematics.ChainModel` (``fk="chain"``) or
      an ``mjx.Model`` (``fk="mjx"``).
    """
    if min_sigma is None:
        min_sigma = _MIN_SIGMA.get(task_dim, 0.05)
    return from_mjcf(
        UR5E_XML,
        "ee",
        task_dim=task_dim,
        m_a=m_a,
        dq_max=dq_max,
        sample_low=sample_low,
        sample_high=sample_high,
        min_sigma=min_sigma,
        fk=fk,
        name="ur5e",
    )
