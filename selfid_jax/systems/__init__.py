"""Systems: the ``System`` pytree, builders, and the shipped robots."""

from selfid_jax.systems.base import System, from_mjcf, from_pose_fn
from selfid_jax.systems.two_link import two_link
from selfid_jax.systems.ur5e import ur5e

__all__ = ["System", "from_pose_fn", "from_mjcf", "two_link", "ur5e"]
