"""Closed-loop helpers of the articulated tests: the tactile pads, the UR5e arm at home and batched rollout params.

Shared by tests/test_articulated.py, tests/test_articulated_mjx.py and tests/test_host_bound.py.
"""

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.articulated import scenes, sim, tactile

PADS = tactile.pads()


def ur5e_arm():
    """``(arm, q0, p1, R1)``: the UR5e with a 6-D task, its home configuration ``q0 (6,)`` [rad] and the home pose
    ``p1 (3,)`` [m], ``R1 (3, 3)`` (where the scene puts the handle)."""
    from selfid_jax.systems.ur5e import UR5E_HOME, ur5e

    arm = ur5e(task_dim=6)
    q0 = np.asarray(UR5E_HOME)
    p1, R1 = (np.asarray(a) for a in arm.pose(jnp.asarray(q0)))
    return arm, q0, p1, R1


def rollout_params(obj, controllers, *, use_estimate=False, jinv=None) -> sim.RolloutParams:
    """:class:`sim.RolloutParams` with a leading batch axis ``B = len(controllers)``: the objects ``obj`` (one per
    row), the controllers (``sim.Controller``) and the tests' fixed settings; ``jinv`` ``(6, 6)`` or ``(B, 6, 6)``
    is the estimated inverse Jacobian (zeros if None)."""
    B = len(controllers)
    full = lambda v: jnp.full((B,), v)
    return sim.RolloutParams(
        obj=scenes.ObjectParams(*(jnp.asarray(a) for a in obj)), controller=jnp.asarray(controllers, jnp.int32),
        use_estimate=jnp.full((B,), use_estimate),
        jinv_est=jnp.zeros((B, 6, 6)) if jinv is None else jnp.broadcast_to(jinv, (B, 6, 6)),
        key=jax.random.key_data(jax.random.split(jax.random.key(0), B)), speed=full(0.03), marker_noise=full(5e-6),
        contact_eps=full(3e-4), contact_points=jnp.zeros((B,), jnp.int32),
        qdot_max=jnp.ones((B, 6)), beta=full(0.9), dev_high=full(1e-3), dev_low=full(2e-4),
        recovery_gain=full(0.5), slip=full(5e-3), slip_rot=full(0.3), lead_max=full(1e-3), twist_tau=full(0.06),
        grasp=jnp.tile(jnp.array([2e4, 280.0, 5.0, 0.44]), (B, 1)))
