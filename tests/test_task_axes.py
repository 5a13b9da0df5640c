"""Tasks made of chosen pose components (``System.with_task_axes``): the rows of the geometric Jacobian, the pose
difference, and a rotation-only path followed on the UR5e, checked against closed forms."""

import jax
import numpy as np
import pytest

from selfid_jax import control
from selfid_jax.control import paths
from selfid_jax.math import geometry
from selfid_jax.systems.ur5e import ur5e
from selfid_jax.systems.validation import check_task_axes

Q = np.array([0.3, -1.3, 1.8, -2.07, -1.57, 0.2])


def test_axes_names_and_checks():
    assert check_task_axes(["rx", "z", "ry"]) == (2, 3, 4)
    assert check_task_axes([5, 0]) == (0, 5)
    for bad, match in ((["z", "z"], "each once"), ([], "at least one"), (["w"], "not an axis"), ([6], "not an axis"),
                       (7, "list of axes")):
        with pytest.raises(ValueError, match=match):
            check_task_axes(bad)
    with pytest.raises(ValueError, match="position only"):
        check_task_axes(["rx"], has_rotation=False)


@pytest.mark.slow
def test_jacobian_rows_and_difference_are_the_chosen_components():
    full = ur5e(task_dim=6)
    part = full.with_task_axes(("z", "rx", "ry"))
    assert (part.task_dim, part.axes, part.position_axes, part.rotation_axes) == (3, (2, 3, 4), (2,), (0, 1))
    np.testing.assert_allclose(part.jacobian(Q), np.asarray(full.jacobian(Q))[[2, 3, 4]], atol=1e-12)
    q2 = Q + 0.01
    np.testing.assert_allclose(part.task_vector(q2, Q), np.asarray(full.task_vector(q2, Q))[[2, 3, 4]], atol=1e-12)
    assert full.with_task_axes(("x", "y", "z")).task_axes is None  # the plain 3-D task
    assert part.with_task_dim(6).axes == tuple(range(6))


@pytest.mark.slow
def test_rotation_only_task_reaches_the_rotation_and_leaves_position_free():
    system = ur5e(task_dim=6).with_task_axes(("rx", "ry", "rz"))
    path = np.asarray(paths.rotation(axis=(0.0, 1.0, 0.0), angle=0.3, steps=3))[:, 3:]
    ctrl = control.ControllerParams(max_rot_step=0.02, rot_tol=0.002)
    res = jax.jit(lambda q: control.follow(system, control.true_inverse(system), path, q, ctrl, steps=200,
                                           return_trajectory=True))(Q)
    assert float(res.completion) == 1.0 and not bool(res.failed)
    R0 = np.asarray(system.pose(Q)[1])
    goal = np.asarray(geometry.so3_exp(np.array([0.0, 0.3, 0.0]))) @ R0
    R_end = np.asarray(system.pose(res.final_q)[1])
    angle = np.degrees(np.arccos(np.clip((np.trace(goal @ R_end.T) - 1) / 2, -1, 1)))  # closed form
    assert angle <= np.degrees(0.002) + 1e-6
    # the pursued waypoint index only moves forward and ends past the last waypoint
    t = np.asarray(res.targets)[: int(res.steps_used) + 1]
    assert np.all(np.diff(t) >= 0) and t[-1] == 3
