"""Tracking metrics against brute-force numpy: per-axis distance to a path, rotation angles; jit and vmap."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from selfid_jax.control import metrics, paths


def numpy_closest(points, vertices, samples=2001):
    """Closest path point by dense sampling of every segment (independent of the projection formula)."""
    t = np.linspace(0.0, 1.0, samples)[:, None]
    dense = np.concatenate([a + t * (b - a) for a, b in zip(vertices[:-1], vertices[1:])])
    idx = np.argmin(((points[:, None, :] - dense[None]) ** 2).sum(-1), axis=1)
    return dense[idx]


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_axis_errors_match_numpy_on_a_letter_path():
    rng = np.random.default_rng(0)
    letters = np.asarray(paths.text("GRAB", height=0.012, dim=3))
    vertices = np.vstack([np.zeros(3), letters])
    points = vertices[rng.integers(0, len(vertices), 40)] + rng.normal(0, 1e-3, (40, 3))
    got = np.asarray(metrics.axis_errors(jnp.asarray(points), jnp.asarray(vertices)))
    want = np.abs(points - numpy_closest(points, vertices))
    np.testing.assert_allclose(got, want, atol=1e-5)  # the dense sampling's resolution (6 um)
    on_path = np.asarray(metrics.axis_errors(jnp.asarray(vertices), jnp.asarray(vertices)))
    np.testing.assert_allclose(on_path, 0.0, atol=1e-12)


@pytest.mark.slow
def test_rotation_error_matches_scipy_and_batches():
    rng = np.random.default_rng(1)
    A = Rotation.random(8, random_state=rng)
    B = Rotation.random(8, random_state=rng)
    got = np.asarray(metrics.rotation_errors_deg(jnp.asarray(A.as_matrix()), jnp.asarray(B.as_matrix())))
    want = np.degrees((A * B.inv()).magnitude())
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert float(metrics.rotation_error(jnp.eye(3), jnp.eye(3))) == 0.0


class MetricsJitVmap(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_jit_equals_eager_and_vmap_equals_loop(self):
        rng = np.random.default_rng(2)
        vertices = jnp.asarray(rng.normal(size=(6, 2)))
        points = jnp.asarray(rng.normal(size=(3, 5, 2)))
        fn = self.variant(metrics.axis_errors)
        batched = jax.vmap(fn, in_axes=(0, None))(points, vertices)
        for b in range(3):
            chex.assert_trees_all_close(batched[b], metrics.axis_errors(points[b], vertices), atol=1e-12)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="vertices: need at least 2"):
        metrics.closest_points(jnp.zeros((3, 2)), jnp.zeros((1, 2)))
    with pytest.raises(ValueError, match=r"vertices: expected shape"):
        metrics.closest_points(jnp.zeros((3, 2)), jnp.zeros((4, 3)))
