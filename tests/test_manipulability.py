"""Manipulability and condition against numpy's SVD, closed forms and unit changes."""

import jax

jax.config.update("jax_enable_x64", True)

import chex  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from selfid_jax.systems import manipulability as mp  # noqa: E402
from selfid_jax.systems.ets import arm5  # noqa: E402
from selfid_jax.systems.two_link import two_link  # noqa: E402

TOL = 1e-12


@pytest.mark.parametrize("shape", [(6, 5), (3, 5), (6, 6), (2, 2), (6, 3)])
def test_metrics_match_numpy_svd(shape):
    rng = np.random.default_rng(sum(shape))
    J = rng.normal(size=(7,) + shape)  # a batch axis without vmap
    s = np.linalg.svd(J, compute_uv=False)
    np.testing.assert_allclose(mp.singular_values(J), s, rtol=TOL)
    np.testing.assert_allclose(mp.yoshikawa_manipulability(J), s.prod(-1), rtol=1e-10)
    np.testing.assert_allclose(mp.sqrt_manipulability(J), np.sqrt(s.prod(-1)), rtol=1e-10)
    np.testing.assert_allclose(mp.condition(J), s[:, 0] / s[:, -1], rtol=1e-10)
    if shape[0] <= shape[1]:  # full row rank: Yoshikawa's sqrt(det(J J^T))
        np.testing.assert_allclose(mp.yoshikawa_manipulability(J), np.sqrt(np.linalg.det(J @ np.swapaxes(J, 1, 2))),
                                   rtol=1e-9)
    else:  # more rows than columns: det(J J^T) = 0, the product is sqrt(det(J^T J))
        np.testing.assert_allclose(np.linalg.det(J @ np.swapaxes(J, 1, 2)), 0.0, atol=1e-9)
        np.testing.assert_allclose(mp.yoshikawa_manipulability(J), np.sqrt(np.linalg.det(np.swapaxes(J, 1, 2) @ J)),
                                   rtol=1e-9)


@pytest.mark.slow
def test_two_link_closed_form():
    s = two_link()  # unit links: Yoshikawa = l1 l2 |sin q2|
    q2 = np.array([0.3, 1.2, 2.5, -0.8])
    qs = jnp.stack([jnp.full(4, 0.4), jnp.asarray(q2)], axis=1)
    J, m = jax.jit(jax.vmap(lambda q: (s.jacobian(q), s.manipulability(q))))(qs)
    np.testing.assert_allclose(mp.yoshikawa_manipulability(J), np.abs(np.sin(q2)), rtol=1e-12)
    np.testing.assert_allclose(m, np.abs(np.sin(q2)), rtol=1e-12)  # System.manipulability is Yoshikawa's
    assert np.isinf(mp.condition(jnp.array([[1.0, 2.0], [2.0, 4.0]]) * 0 + jnp.array([[1.0, 0.0], [0.0, 0.0]])))


@pytest.mark.slow
def test_arm5_metrics_and_unit_consistency():
    s = arm5(task_dim=6)
    qs = np.random.default_rng(0).uniform(s.q_low, s.q_high, size=(64, 5))
    J = np.asarray(jax.jit(jax.vmap(s.jacobian))(qs))
    m = jax.jit(mp.metrics)(J, 0.1)
    sv = np.linalg.svd(J, compute_uv=False)
    s3 = np.linalg.svd(J[:, :3], compute_uv=False)
    scaled = J.copy()
    scaled[:, 3:] *= 0.1
    su = np.linalg.svd(scaled, compute_uv=False)
    np.testing.assert_allclose(m.sqrt_manipulability, np.sqrt(sv.prod(1)), rtol=1e-10)
    np.testing.assert_allclose(m.yoshikawa, sv.prod(1), rtol=1e-10)
    np.testing.assert_allclose(m.condition, sv[:, 0] / sv[:, -1], rtol=1e-10)
    np.testing.assert_allclose(m.position_yoshikawa, s3.prod(1), rtol=1e-10)
    np.testing.assert_allclose(m.position_condition, s3[:, 0] / s3[:, -1], rtol=1e-10)
    np.testing.assert_allclose(m.unit_consistent_condition, su[:, 0] / su[:, -1], rtol=1e-10)
    np.testing.assert_allclose(m.sigma_min, sv[:, -1], rtol=1e-10)
    # the mixed-unit 6x5 condition stays high (link lengths 0.1-0.15 m against unit rotation columns) ...
    assert m.condition.min() > 16.0
    # ... and the unit-consistent one does not depend on the length unit: metres -> millimetres, L too
    mm = J.copy()
    mm[:, :3] *= 1000.0
    np.testing.assert_allclose(mp.unit_consistent_condition(mm, 100.0), m.unit_consistent_condition, rtol=1e-9)
    assert not np.allclose(mp.condition(mm), m.condition, rtol=0.1)


@pytest.mark.parametrize(
    "fn, args, match",
    [
        (mp.condition, (np.ones(3),), r"shape \(\.\.\., m, n\)"),
        (mp.position_rows, (np.ones((3, 5)),), "6-row"),
        (mp.unit_consistent_condition, (np.ones((6, 5)), 0.0), "length: must be > 0"),
        (mp.unit_consistent_condition, (np.ones((3, 5)), 0.1), "6-row"),
    ],
)
def test_bad_input(fn, args, match):
    with pytest.raises(ValueError, match=match):
        fn(*args)


@pytest.mark.slow
class TestTraced(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    def test_jit_and_eager_agree(self):
        J = jnp.asarray(np.random.default_rng(3).normal(size=(6, 5)))
        got = self.variant(mp.metrics)(J, 0.2)
        want = mp.metrics(np.asarray(J), 0.2)
        chex.assert_trees_all_close(got, want, rtol=1e-12)

    def test_vmap_equals_batch_axes(self):
        J = jnp.asarray(np.random.default_rng(4).normal(size=(5, 6, 5)))
        lengths = jnp.array([0.1, 0.2, 0.3, 0.4, 0.5])  # traced length: one compilation for a sweep
        got = jax.jit(jax.vmap(mp.metrics))(J, lengths)
        for i in range(5):
            chex.assert_trees_all_close(jax.tree.map(lambda x, i=i: x[i], got), mp.metrics(J[i], float(lengths[i])),
                                        rtol=1e-12)
