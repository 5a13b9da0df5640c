"""SOGP (Csato & Opper 2002): equals the full GP posterior (plain numpy) while every point is kept,
stays bounded under pruning, gives no NaN on repeated, collinear or non-finite inputs, jit == vmap ==
loop, and bad arguments raise before any compute."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax.baselines import sogp

TOL = 1e-6  # float64 agreement with the full GP


def numpy_gp(X, Y, Xs, lengthscale, variance, noise):
    """Full GP posterior mean (s, P) and latent variance (s,) at Xs: plain numpy, Cholesky solve."""
    ls = np.broadcast_to(np.asarray(lengthscale, float), (X.shape[1],))

    def k(A, B):
        d = (A[:, None, :] - B[None, :, :]) / ls
        return variance * np.exp(-0.5 * np.sum(d * d, axis=-1))

    L = np.linalg.cholesky(k(X, X) + noise**2 * np.eye(len(X)))
    Ks = k(X, Xs)
    A = np.linalg.solve(L, Ks)
    mean = Ks.T @ np.linalg.solve(L.T, np.linalg.solve(L, Y))
    var = variance - np.sum(A * A, axis=0)
    return mean, var


@jax.jit
def fold(state, X, Y):
    return jax.lax.scan(lambda s, xy: (sogp.update(s, *xy), None), state, (X, Y))[0]


predict_many = jax.jit(jax.vmap(sogp.predict, in_axes=(None, 0)))
update = jax.jit(sogp.update)


@pytest.mark.slow
def test_equals_full_gp_while_every_point_is_kept_and_repeats_are_projected_exactly():
    rng = np.random.default_rng(0)
    D, P = 3, 2
    X = rng.uniform(-2, 2, (16, D))
    X = np.concatenate([X, X[:3], X[:3], X[5:6]])  # 7 repeats of basis inputs: projected (gamma = 0), still exact
    Y = np.stack([np.sin(X[:, 0]) + X[:, 1], np.cos(X[:, 2])], axis=1) + 0.01 * rng.normal(size=(len(X), P))
    Xs = rng.uniform(-2.5, 2.5, (40, D))
    kern = sogp.RBF(lengthscale=np.array([0.8, 1.2, 1.0]), variance=1.5)
    state = fold(sogp.init(D, P, capacity=len(X), kernel=kern, noise=0.05, novelty_tol=0.0), X, Y)
    assert int(sogp.size(state)) == 16 and int(state.count) == len(X) and int(state.unstable) == 0
    mean, var = predict_many(state, Xs)
    ref_mean, ref_var = numpy_gp(X, Y, Xs, kern.lengthscale, 1.5, 0.05)
    np.testing.assert_allclose(mean, ref_mean, atol=TOL)
    np.testing.assert_allclose(var, ref_var, atol=TOL)


@pytest.mark.slow
def test_collinear_and_nearly_identical_inputs_give_no_nan():
    t = np.linspace(0, 1, 60)
    X = np.stack([t, 2 * t, -t], axis=1)  # on a line
    X[30:] = X[30] + 1e-9 * np.arange(30)[:, None]  # then nearly the same point
    Y = np.sin(3 * t)[:, None]
    for tol in (0.0, 1e-4):
        state = fold(sogp.init(3, 1, capacity=8, kernel=sogp.RBF(0.3, 1.0), noise=1e-3, novelty_tol=tol), X, Y)
        mean, var = predict_many(state, X)
        assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(np.asarray(var) >= 0)
        assert np.all(np.isfinite(np.asarray(state.C))) and np.all(np.isfinite(np.asarray(state.Q)))


@pytest.mark.parametrize("M", [6, pytest.param(3, marks=pytest.mark.slow), pytest.param(12, marks=pytest.mark.slow)])
def test_pruning_at_small_capacity_keeps_the_error_bounded(M):
    rng = np.random.default_rng(2)
    X = rng.uniform(-3, 3, (300, 1))
    Y = np.sin(X) + 0.05 * rng.normal(size=X.shape)
    Xs = np.linspace(-3, 3, 101)[:, None]
    state = fold(sogp.init(1, 1, capacity=M, kernel=sogp.RBF(1.0, 1.0), noise=0.05, novelty_tol=1e-4), X, Y)
    assert int(sogp.size(state)) == M and int(state.count) == 300
    mean, var = predict_many(state, Xs)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var))
    err = np.max(np.abs(np.asarray(mean)[:, 0] - np.sin(Xs[:, 0])))
    assert err < (0.5 if M == 3 else 0.1), (M, err)  # sin on [-3, 3] needs ~6 RBF bases of length 1


@pytest.mark.slow
def test_non_finite_samples_are_counted_and_change_nothing_else():
    state = sogp.init(2, 1, capacity=4, noise=0.1)
    state = update(state, np.array([0.1, 0.2]), np.array([1.0]))
    for x, y in (([np.nan, 0.0], [1.0]), ([0.0, 0.0], [np.inf])):
        new = update(state, np.array(x), np.array(y))
        assert int(new.rejected) == int(state.rejected) + 1 and int(new.count) == int(state.count)
        chex.assert_trees_all_equal(new._replace(rejected=state.rejected), state)
    mean, var = predict_many(state, np.array([[np.nan, 0.0]]))
    np.testing.assert_array_equal(mean, [[0.0]])
    np.testing.assert_array_equal(var, [1.0])


@pytest.mark.slow
def test_mean_gradient_matches_finite_differences_and_vmap_equals_one_by_one():
    rng = np.random.default_rng(3)
    X, Y = rng.uniform(-1, 1, (12, 2)), rng.normal(size=(12, 2))
    states = jax.vmap(lambda n: sogp.init(2, 2, capacity=6, noise=n))(jnp.array([0.1, 0.3]))
    batched = jax.jit(jax.vmap(fold, in_axes=(0, None, None)))(states, X, Y)
    alone = fold(sogp.init(2, 2, capacity=6, noise=0.3), X, Y)  # fold is jitted: jit == vmap
    chex.assert_trees_all_close(jax.tree.map(lambda a: a[1], batched), alone, atol=1e-12)
    x, h = np.array([0.2, -0.3]), 1e-6
    pts = np.concatenate([x + h * np.eye(2), x - h * np.eye(2), x[None]])
    means = np.asarray(predict_many(alone, pts)[0])
    fd = ((means[:2] - means[2:4]) / (2 * h)).T  # (P, D)
    J = jax.jit(jax.jacfwd(sogp.mean, argnums=1))(alone, x)
    np.testing.assert_allclose(J, fd, atol=1e-7)


@pytest.mark.slow
def test_one_compilation_for_every_hyperparameter_value():
    @jax.jit
    @chex.assert_max_traces(n=1)
    def run(noise, tol, ls):
        st = sogp.init(1, 1, capacity=4, kernel=sogp.RBF(ls, 1.0), noise=noise, novelty_tol=tol)
        return sogp.predict(fold(st, jnp.ones((5, 1)), jnp.ones((5, 1))), jnp.zeros(1))

    for v in (0.1, 0.2, 0.3):
        run(v, v / 10, v * 3)


def test_bad_arguments_raise_before_compute():
    with pytest.raises(ValueError, match="capacity: expected a positive integer, got 0"):
        sogp.init(2, 1, capacity=0)
    with pytest.raises(ValueError, match="noise: must be > 0"):
        sogp.init(2, 1, capacity=3, noise=-0.1)
    with pytest.raises(ValueError, match="novelty_tol: must be < 1"):
        sogp.init(2, 1, capacity=3, novelty_tol=1.5)
    with pytest.raises(ValueError, match=r"lengthscale: expected shape \(\) or \(2,\)"):
        sogp.init(2, 1, capacity=3, kernel=sogp.RBF(np.ones(3), 1.0))
    with pytest.raises(ValueError, match="variance: must be > 0"):
        sogp.init(2, 1, capacity=3, kernel=sogp.RBF(1.0, 0.0))
    with pytest.raises(ValueError, match="dim_in"):
        sogp.init(0, 1, capacity=3)
    with jax.enable_x64(False), pytest.raises(ValueError, match="float64"):
        sogp.init(2, 1, capacity=3)
    state = sogp.init(2, 1, capacity=3)
    with pytest.raises(ValueError, match=r"sogp: x: expected shape \(2,\), got \(3,\)"):
        sogp.update(state, np.zeros(3), np.zeros(1))
    with pytest.raises(ValueError, match=r"sogp: y: expected shape \(1,\), got \(2,\)"):
        sogp.update(state, np.zeros(2), np.zeros(2))
