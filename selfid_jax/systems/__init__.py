"""Systems: the ``System`` pytree, builders, and the shipped robots."""

from collections.abc import Callable
from functools import partial
from typing import NamedTuple

from selfid_jax.systems import (  # noqa: F401  (public modules, reached as sj.systems.<module>)
    actuation,
    compose,
    kinematics,
    manipulability,
    model_files,
)
from selfid_jax.systems.dynamic import DynamicArm, dynamic_arm, dynamic_ur5e
from selfid_jax.systems.ets import arm5, from_ets
from selfid_jax.systems.hands import model_o, stewart_hand
from selfid_jax.systems.mjcf import from_mjcf
from selfid_jax.systems.system import System, from_pose_fn
from selfid_jax.systems.two_link import two_link
from selfid_jax.systems.ur5e import ur5e
from selfid_jax.systems.validation import Limits

__all__ = ["BUILTIN", "REGISTRY", "Builtin", "DynamicArm", "Limits", "System", "arm5", "dynamic_arm", "dynamic_ur5e",
           "from_ets", "from_pose_fn", "from_mjcf", "model_o", "stewart_hand", "two_link", "ur5e"]


class Builtin(NamedTuple):
    """One shipped robot under the name a config gives it (``systems: [ur5e_6d]``)."""

    factory: Callable[[], System]  # builds the robot as the config name means it
    description: str  # one line: the call it makes and what the robot is
    x64: bool = False  # built and run in float64 whatever the global setting (closed-chain hands)


REGISTRY: dict[str, Builtin] = {
    "two_link": Builtin(two_link, "two_link(): planar 2-link arm, unit links, task = xy position (Fig. 2)"),
    "ur5e": Builtin(ur5e, "ur5e(task_dim=3): UR5e from the published DH parameters, flange site 'ee', task = xyz"),
    "ur5e_6d": Builtin(partial(ur5e, task_dim=6), "ur5e(task_dim=6): the same UR5e, task = 6-D flange pose"),
    "stewart_hand": Builtin(stewart_hand, "stewart_hand(backend=...): 6-6 Stewart Hand, object pose (6-D) from six "
                            "leg lengths", x64=True),
    "model_o": Builtin(model_o, "model_o(backend=...): Yale Model O, 3 tendon-driven fingers, POM 30 mm above the "
                       "object", x64=True),
    "arm5": Builtin(arm5, "arm5(): seed 004's 5-DOF desktop arm from its ETS (no tool yaw), task = xyz"),
}
"""THE list of shipped robots: config name -> :class:`Builtin` (configs, their validation and ``selfid-jax list``)."""

BUILTIN = {name: b.description + (" [float64]" if b.x64 else "") for name, b in REGISTRY.items()}
"""Name -> one-line description of the robots shipped in the package (``selfid-jax list``)."""
