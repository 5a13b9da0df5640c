"""math.linalg.implicit_root: the implicit-function-theorem derivative of a root, and programs the persistent
compilation cache can keep (no host callback) wherever the closed-chain hands are differentiated."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax.math.linalg import implicit_root

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

    def test_singular_operator_gives_non_finite_derivatives_not_an_error(self):
        f = lambda b_: implicit_root(lambda y, b: 0.0 * y - b, jnp.zeros(2), b_)  # F_y = 0
        assert not np.all(np.isfinite(jax.jacfwd(f)(jnp.ones(2))))


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
