"""SO(3) helpers against scipy's Rotation (an independent implementation)."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from selfid_jax.math import geometry  # noqa: E402

TOL = 1e-12

# Compiled once per input shape and reused (eager op-by-op dispatch is slow on CPU).
exp = jax.jit(geometry.so3_exp)
log = jax.jit(geometry.so3_log)
pose_difference = jax.jit(geometry.pose_difference)


@jax.jit
def _derivatives(w):
    """Jacobians of exp and log(exp), and a reverse-mode gradient, at ``w (3,)``."""
    g_exp = jax.jacfwd(geometry.so3_exp)(w)
    g_rt = jax.jacfwd(lambda x: geometry.so3_log(geometry.so3_exp(x)))(w)
    g_rev = jax.grad(lambda x: jnp.sum(geometry.so3_log(geometry.so3_exp(x)) ** 2))(w)
    return g_exp, g_rt, g_rev
TINY_ANGLES = [0.0, 1e-15, 1e-12, 1e-8, 1e-5, 1e-3, 0.3, np.pi - 1e-6, np.pi - 1e-12]


def _rotvecs(shape, rng, max_angle=np.pi):
    axis = rng.normal(size=shape + (3,))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    return axis * rng.uniform(0.0, max_angle, size=shape + (1,))


@pytest.mark.slow
@pytest.mark.parametrize("shape", [(), (4,), (2, 3)])
def test_exp_log_match_scipy_with_batch_axes(shape):
    rng = np.random.default_rng(0)
    w = _rotvecs(shape, rng, max_angle=np.pi - 1e-3)
    R = exp(w)
    assert R.shape == shape + (3, 3)
    R_ref = Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(shape + (3, 3))
    np.testing.assert_allclose(R, R_ref, atol=TOL)
    w_back = log(R_ref)
    assert w_back.shape == shape + (3,)
    np.testing.assert_allclose(w_back, w, atol=1e-10)


@pytest.mark.slow
def test_log_of_random_rotations_matches_scipy():
    R = Rotation.random(200, random_state=1)
    np.testing.assert_allclose(log(R.as_matrix()), R.as_rotvec(), atol=1e-10)
    np.testing.assert_allclose(exp(log(R.as_matrix())), R.as_matrix(), atol=TOL)


@pytest.mark.parametrize("angle", TINY_ANGLES)
def test_round_trip_small_and_near_pi(angle):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    w = axis * angle
    np.testing.assert_allclose(log(exp(w)), w, atol=1e-11, rtol=1e-9)
    np.testing.assert_allclose(exp(w), Rotation.from_rotvec(w).as_matrix(), atol=TOL)


@pytest.mark.slow
@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, np.pi - 1e-6])
def test_gradients_finite(angle):
    w = np.array([0.6, 0.0, -0.8]) * angle
    g_exp, g_rt, g_rev = _derivatives(w)
    for g in (g_exp, g_rt, g_rev):
        assert np.all(np.isfinite(g))
    if angle < 1e-3:
        np.testing.assert_allclose(g_rt, np.eye(3), atol=1e-8)


@pytest.mark.slow
def test_exp_and_log_derivatives_at_identity():
    # d exp(w)/dw at 0 is the hat map; d log(R)/dR at I is vee of the skew part.
    g = _derivatives(np.zeros(3))[0]
    for i in range(3):
        np.testing.assert_allclose(g[..., i], geometry.hat(np.eye(3)[i]), atol=TOL)
    dR = np.array([[0.1, -0.3, 0.2], [0.7, 0.0, -0.4], [-0.5, 0.6, 0.3]])
    t = jax.jit(lambda v: jax.jvp(geometry.so3_log, (jnp.eye(3),), (v,))[1])(dR)
    skew = (dR - dR.T) / 2
    np.testing.assert_allclose(t, [skew[2, 1], skew[0, 2], skew[1, 0]], atol=TOL)


def test_pose_difference_values_and_batch():
    rng = np.random.default_rng(2)
    R_prev = Rotation.random(5, random_state=3).as_matrix()
    w = _rotvecs((5,), rng, max_angle=2.0)
    R_t = Rotation.from_rotvec(w).as_matrix() @ R_prev
    p_prev, p_t = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    V = pose_difference(p_t, R_t, p_prev, R_prev)
    assert V.shape == (5, 6)
    np.testing.assert_allclose(V[:, :3], p_t - p_prev, atol=TOL)
    np.testing.assert_allclose(V[:, 3:], w, atol=1e-10)  # world-frame rotation vector


@pytest.mark.slow
def test_pose_difference_rotational_derivative_is_world_angular_velocity():
    # R(t) = exp(t w) R0: d/dt log(R(t) R0^T) at 0 = w (world frame), compared
    # with a central finite difference of the scipy rotation vector too.
    R0 = Rotation.random(random_state=4).as_matrix()
    w = np.array([0.3, -1.2, 0.5])
    p0 = np.zeros(3)

    def rot_part(t):
        return geometry.pose_difference(p0, geometry.so3_exp(t * w) @ R0, p0, R0)[3:]

    d = jax.jit(jax.jacfwd(rot_part))(0.0)
    np.testing.assert_allclose(d, w, atol=1e-12)
    h = 1e-6
    fd = [
        Rotation.from_matrix(Rotation.from_rotvec(s * h * w).as_matrix() @ R0 @ R0.T).as_rotvec() for s in (1, -1)
    ]
    np.testing.assert_allclose(d, (fd[0] - fd[1]) / (2 * h), atol=1e-8)


def test_jit_equals_eager():
    w = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(exp(w), geometry.so3_exp(w), atol=TOL)
