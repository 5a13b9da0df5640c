"""A Model O mounted on the UR5e (``systems.compose``): the composed Jacobian against central differences of its
pose map, and each part (the other held) against the composed pose and Jacobian columns. float64."""

import jax
import numpy as np
import pytest

from selfid_jax.math import geometry
from selfid_jax.systems import compose, from_pose_fn, hands
from selfid_jax.systems.ur5e import ur5e

# compiles the closed-chain hand's implicit derivatives; one xdist worker for the module, so the program of the
# module fixture `evaluated` (both tests read it) is compiled once, not on each worker
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("compose")]


@pytest.fixture(scope="module")
def mounted():
    hand = hands.model_o(task_dim=6)
    system = compose.mount(ur5e(task_dim=6), hand, offset=(0.01, -0.02, 0.03), rotation_vector=(0.1, -0.2, 0.3))
    q_hand = np.asarray(hand.sample_low + hand.sample_high) / 2 + np.array([1e-3, -5e-4, 2e-4])
    return system, np.concatenate([[0.3, -1.3, 1.8, -2.07, -1.57, 0.2], q_hand])


@jax.jit
def _evaluate(system, q):
    """Everything the tests read, in one compiled program (the closed-chain hand's Newton solve and implicit
    derivatives compile once, not once per eager call): the composed pose and Jacobian and both parts' (the other
    part held at ``q``)."""
    arm, hand = compose.arm_part(system, q[6:]), compose.hand_part(system, q[:6], task_axes=("z", "rx", "ry"))
    return {"pose": system.pose(q), "J": system.jacobian(q), "arm_pose": arm.pose(q[:6]),
            "hand_pose": hand.pose(q[6:]), "arm_J": arm.jacobian(q[:6]), "hand_J": hand.jacobian(q[6:]),
            "n": (arm.n_act, hand.n_act, hand.task_dim)}


@pytest.fixture(scope="module")
def evaluated(mounted):
    return jax.tree.map(np.asarray, _evaluate(*mounted))


def central_differences(system, q, poses, h=1e-6):
    """``(6, len(q))`` central differences of ``system``'s pose at ``q`` (step ``h``): the ``2 len(q)`` perturbed
    poses in one vmapped call (the ``poses`` fixture)."""
    E = h * np.eye(len(q))
    p, R = poses(system, np.concatenate([q + E, q - E]))
    n = len(q)
    V = jax.vmap(geometry.pose_difference)(p[:n], R[:n], p[n:], R[n:])
    return np.asarray(V).T / (2 * h)


def test_composed_jacobian_equals_central_differences(mounted, evaluated, poses):
    system, q = mounted
    J = evaluated["J"]
    assert J.shape == (6, 9)
    np.testing.assert_allclose(J, central_differences(system, q, poses), atol=1e-6 * np.abs(J).max())


def test_parts_hold_the_other_and_match_the_composed_system(evaluated):
    out = evaluated
    p_full, R_full = out["pose"]
    for p, R in (out["arm_pose"], out["hand_pose"]):
        np.testing.assert_allclose(p, p_full, atol=1e-12)
        np.testing.assert_allclose(R, R_full, atol=1e-12)
    J = out["J"]
    np.testing.assert_allclose(out["arm_J"], J[:, :6], atol=1e-9)
    np.testing.assert_allclose(out["hand_J"], J[[2, 3, 4], 6:], atol=1e-9)
    assert tuple(int(v) for v in out["n"]) == (6, 3, 3)


def test_mount_checks_its_inputs():
    with pytest.raises(ValueError, match="no orientation"):
        compose.mount(from_pose_fn(lambda params, q: q, 3, task_dim=3, q_low=-1, q_high=1, dq_max=0.1, m_a=0.01),
                      ur5e(task_dim=6))
    with pytest.raises(ValueError, match="3-vectors"):
        compose.mount(ur5e(task_dim=6), ur5e(task_dim=6), offset=(0.0, 0.0))
    with pytest.raises(TypeError, match="mount"):
        compose.arm_part(ur5e(task_dim=6), np.zeros(3))
