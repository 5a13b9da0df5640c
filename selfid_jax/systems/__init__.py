"""Systems: the ``System`` pytree, builders, and the shipped robots."""

from selfid_jax.systems.ets import arm5, from_ets
from selfid_jax.systems.hands import model_o, stewart_hand
from selfid_jax.systems.mjcf import from_mjcf
from selfid_jax.systems.system import System, from_pose_fn
from selfid_jax.systems.two_link import two_link
from selfid_jax.systems import manipulability  # noqa: E402,F401
from selfid_jax.systems.ur5e import ur5e
from selfid_jax.systems.validation import Limits

__all__ = ["BUILTIN", "Limits", "System", "arm5", "from_ets", "from_pose_fn", "from_mjcf", "model_o", "stewart_hand",
           "two_link", "ur5e"]

BUILTIN = {
    "two_link": "two_link(): planar 2-link arm, unit links, task = xy position (Fig. 2)",
    "ur5e": "ur5e(task_dim=3 | 6): UR5e from the published DH parameters, flange site 'ee'",
    "stewart_hand": "stewart_hand(backend=...): 6-6 Stewart Hand, object pose (6-D) from six leg lengths [float64]",
    "model_o": "model_o(backend=...): Yale Model O, 3 tendon-driven fingers, POM 30 mm above the object [float64]",
    "arm5": "arm5(task_dim=3 | 6): seed 004's 5-DOF desktop arm from its ETS (no tool yaw)",
}
"""Name -> one-line description of the robots shipped in the package (``selfid-jax list``)."""
