"""math.linalg.newton_root and implicit_root: the hands' Newton solve, the implicit-function-theorem derivative of a
root, and programs the persistent compilation cache can keep (no host callback) wherever the hands are
differentiated."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax.math.linalg import implicit_root, jacfwd_with_value, newton_root

A = np.array([[3.0, 1.0, 0.0], [0.5, 2.0, 0.2], [0.0, 0.3, 4.0]])


def _residual(y, args):
    M, b = args
    return M @ y + 0.1 * jnp.sin(y) - b


def _root(M, b):
    """Newton's method to round-off (no tangents reach it), then the root with its IFT derivative."""
    args = jax.lax.stop_gradient((M, b))
    step = lambda _, y: y - jnp.linalg.solve(jax.jacfwd(_residual)(y, args), _residual(y, args))
    y = jax.lax.fori_loop(0, 30, step, jnp.zeros(3, b.dtype))
    return implicit_root(_residual, y, (M, b))


def _numpy_root_jacobian(M, b):
    """Closed form: at the root, dy/db = (M + 0.1 diag(cos y))^-1 (numpy float64, y by numpy Newton)."""
    y = np.zeros(3)
    for _ in range(50):
        y = y - np.linalg.solve(M + 0.1 * np.diag(np.cos(y)), M @ y + 0.1 * np.sin(y) - b)
    return y, np.linalg.inv(M + 0.1 * np.diag(np.cos(y)))


class TestImplicitRoot(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_value_and_derivatives_match_the_closed_form(self):
        b = jnp.array([1.0, 2.0, 3.0])
        y_ref, dy_db = _numpy_root_jacobian(A, np.asarray(b))
        f = self.variant(lambda b_: _root(jnp.asarray(A), b_))
        np.testing.assert_allclose(f(b), y_ref, rtol=1e-12)
        np.testing.assert_allclose(self.variant(jax.jacfwd(lambda b_: _root(jnp.asarray(A), b_)))(b), dy_db,
                                   rtol=1e-10)
        np.testing.assert_allclose(self.variant(jax.jacrev(lambda b_: _root(jnp.asarray(A), b_)))(b), dy_db,
                                   rtol=1e-10)

    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_vmap_and_derivative_in_the_matrix(self):
        bs = jnp.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]])
        J = self.variant(jax.vmap(jax.jacfwd(lambda b_: _root(jnp.asarray(A), b_))))(bs)
        for k in range(2):
            np.testing.assert_allclose(J[k], _numpy_root_jacobian(A, np.asarray(bs[k]))[1], rtol=1e-10)
        # d y / d M_ij = -G[:, i] y_j with G = dy/db (differentiate M y = b - 0.1 sin y)
        b = bs[0]
        y, G = _numpy_root_jacobian(A, np.asarray(b))
        dM = self.variant(jax.jacfwd(lambda M_: _root(M_, b)))(jnp.asarray(A))
        np.testing.assert_allclose(dM, -np.einsum("ki,j->kij", G, y), rtol=1e-9, atol=1e-14)

    def test_value_is_the_given_root_bit_for_bit(self):
        y = jnp.array([0.1, -0.2, 0.3])
        out = jax.jit(lambda y_: implicit_root(_residual, y_, (jnp.asarray(A), jnp.ones(3))))(y)
        np.testing.assert_array_equal(out, y)

    @pytest.mark.slow
    def test_singular_operator_gives_non_finite_derivatives_not_an_error(self):
        f = lambda b_: implicit_root(lambda y, b: 0.0 * y - b, jnp.zeros(2), b_)  # F_y = 0
        assert not np.all(np.isfinite(jax.jacfwd(f)(jnp.ones(2))))


def _numpy_newton(M, b, y0, steps):
    """``steps`` Newton iterates of ``M y + 0.1 sin y = b`` from ``y0`` in numpy float64, and the last step."""
    y, dy = np.asarray(y0, float), None
    for _ in range(steps):
        dy = np.linalg.solve(M + 0.1 * np.diag(np.cos(y)), M @ y + 0.1 * np.sin(y) - b)
        y = y - dy
    return y, dy


class TestNewtonRoot(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    def test_root_and_its_jacobian_match_numpy(self):
        b = jnp.array([1.0, 2.0, 3.0])
        y, F_y, ok = self.variant(lambda b_: newton_root(_residual, jnp.zeros(3), (jnp.asarray(A), b_), rtol=1e-12,
                                                         atol=1e-12, max_steps=30))(b)
        y_ref, _ = _numpy_root_jacobian(A, np.asarray(b))
        assert bool(ok)
        np.testing.assert_allclose(y, y_ref, rtol=1e-13)
        np.testing.assert_allclose(F_y, A + 0.1 * np.diag(np.cos(np.asarray(y))), rtol=1e-14)  # at the returned y

    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_stops_at_the_cauchy_test_and_reports_max_steps(self):
        b = np.array([1.0, 2.0, 3.0])
        solve = self.variant(lambda b_, k: newton_root(_residual, jnp.zeros(3), (jnp.asarray(A), b_), rtol=1e-12,
                                                       atol=1e-12, max_steps=k), static_argnums=1)
        # the step count optimistix.Newton's test needs: step j small against y_j and |F(y_{j-1})| < atol
        need = next(j for j in range(1, 30) if np.all(np.abs(_numpy_newton(A, b, np.zeros(3), j)[1])
                                                      < 1e-12 + 1e-12 * np.abs(_numpy_newton(A, b, np.zeros(3), j)[0]))
                    and np.all(np.abs(A @ _numpy_newton(A, b, np.zeros(3), j - 1)[0]
                                      + 0.1 * np.sin(_numpy_newton(A, b, np.zeros(3), j - 1)[0]) - b) < 1e-12))
        y, _, ok = solve(jnp.asarray(b), need)
        assert bool(ok)
        np.testing.assert_allclose(y, _numpy_newton(A, b, np.zeros(3), need)[0], rtol=1e-13)
        y, F_y, ok = solve(jnp.asarray(b), 2)  # not enough steps: not converged, y the second iterate
        assert not bool(ok)
        y2 = _numpy_newton(A, b, np.zeros(3), 2)[0]
        np.testing.assert_allclose(y, y2, rtol=1e-13)
        np.testing.assert_allclose(F_y, A + 0.1 * np.diag(np.cos(y2)), rtol=1e-14)

    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_vmap_and_a_singular_jacobian_is_not_converged_not_an_error(self):
        bs = jnp.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]])
        y, _, ok = self.variant(jax.vmap(lambda b_: newton_root(_residual, jnp.zeros(3), (jnp.asarray(A), b_),
                                                                rtol=1e-12, atol=1e-12, max_steps=30)))(bs)
        assert np.all(np.asarray(ok))
        for k in range(2):
            np.testing.assert_allclose(y[k], _numpy_root_jacobian(A, np.asarray(bs[k]))[0], rtol=1e-12, atol=1e-15)
        y, _, ok = self.variant(lambda b_: newton_root(lambda y_, b: y_ * y_ - b, jnp.zeros(2), b_, rtol=1e-12,
                                                       atol=1e-12, max_steps=30))(jnp.ones(2))  # F_y = 0 at y0
        assert not bool(ok)

    def test_no_derivative_flows_through_the_iterations(self):
        g = jax.grad(lambda b_: jnp.sum(newton_root(_residual, jnp.zeros(3), (jnp.asarray(A), b_), rtol=1e-12,
                                                    atol=1e-12, max_steps=30)[0]))(jnp.ones(3))
        np.testing.assert_array_equal(g, 0.0)  # the caller wraps y in implicit_root for derivatives


def _host_callbacks(fn, *args) -> int:
    lowered = jax.jit(fn).lower(*args)
    return len(lowered._lowering.compile_args.get("host_callbacks") or ())


@pytest.mark.slow
@pytest.mark.parametrize("name", ["model_o", "stewart_hand"])
def test_differentiated_hand_pose_has_no_host_callback(name):
    """jacfwd and jacrev of the kinematic hands' pose maps: no host callback, so XLA's persistent compilation
    cache keeps every program that differentiates a hand (peg-in-hole, self-ID design)."""
    import selfid_jax as sj

    system = getattr(sj, name)()
    q = (system.sample_low + system.sample_high) / 2
    pos = lambda q_: system.pose(q_)[0]
    assert _host_callbacks(jax.jacfwd(pos), q) == 0
    assert _host_callbacks(jax.jacrev(pos), q) == 0
    assert _host_callbacks(lambda q_: jax.grad(lambda x: jnp.sum(pos(x) ** 2))(q_), q) == 0


def test_jacfwd_with_value_is_the_closed_form_jacobian_and_value_under_jit_and_vmap():
    """f(x) = (x0^2, x0 x1, sin x1): value and Jacobian ((2 x0, 0), (x1, x0), (0, cos x1)) from one call."""
    f = lambda x: jnp.stack([x[0] ** 2, x[0] * x[1], jnp.sin(x[1])])
    xs = jnp.array([[0.3, -1.2], [2.0, 0.5]])
    J, v = jax.jit(jax.vmap(jacfwd_with_value(f)))(xs)
    for x, Jx, vx in zip(np.asarray(xs), np.asarray(J), np.asarray(v)):
        np.testing.assert_allclose(vx, [x[0] ** 2, x[0] * x[1], np.sin(x[1])], rtol=1e-14)
        np.testing.assert_allclose(Jx, [[2 * x[0], 0.0], [x[1], x[0]], [0.0, np.cos(x[1])]], rtol=1e-14, atol=1e-15)
