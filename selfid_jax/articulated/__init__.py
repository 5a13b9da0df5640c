"""Tactile control of articulated objects (seed 003: Tac-Man and TacMan-Turbo) on a self-identified arm.

Modules: :mod:`.scenes` (MJCF from parameters, populations), :mod:`.tactile`
(marker pads, Eq. 2), :mod:`.tacman` (Kabsch, prediction, offset velocity,
alpha, both controllers; pure JAX), :mod:`.sim` (the closed-loop rollout on
native MuJoCo or MJX).
"""

from selfid_jax.articulated import scenes, sim, tacman, tactile

__all__ = ["scenes", "sim", "tacman", "tactile"]
