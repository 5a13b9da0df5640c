"""Algorithm 1 under lax.scan: recovery, convergence bookkeeping, jit/vmap, no retracing."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import selfid_jax as sj

J_TRUE = jnp.array([[1.0, 0.5, 0.0], [-0.3, 2.0, 0.4], [0.2, -0.1, 1.5]])
OBSERVE = sj.stateless(lambda key, d: J_TRUE @ d)


def noisy(sigma):
    return sj.stateless(lambda key, d: J_TRUE @ d + sigma * jax.random.normal(key, (3,)))


@jax.jit
@chex.assert_max_traces(n=1)
def identify_batch(keys, m_a, eps):
    run = lambda k, a, e: sj.self_identify(OBSERVE, k, a, e, n_act=3, task_dim=3, iters=12)
    return jax.vmap(run)(keys, m_a, eps)


@pytest.mark.slow
def test_recovers_linear_system_and_converges():
    res = sj.self_identify(OBSERVE, jax.random.key(0), 0.05, 1e-6, n_act=3, task_dim=3, iters=12)
    np.testing.assert_allclose(res.estimate, jnp.linalg.inv(J_TRUE), rtol=1e-6, atol=1e-8)
    # exact from the 3rd sample on: deltas at 4 and 5 are ~0, so convergence is declared at 5
    assert int(res.converged_at) == 5
    # Algorithm 1 stops there: later estimates repeat the converged one
    np.testing.assert_allclose(res.estimates[-1], res.estimates[4])
    assert res.estimates.shape == (12, 3, 3) and res.dtheta.shape == (12, 3) and res.V.shape == (12, 3)
    assert np.all(np.abs(res.dtheta) <= 0.05)


@pytest.mark.slow
def test_vmap_over_keys_m_a_and_eps_equals_loop_without_retracing():
    keys = jax.random.split(jax.random.key(1), 4)
    m_a = jnp.array([0.01, 0.02, 0.05, 0.1])
    eps = jnp.array([1e-6, 1e-3, 1e-6, 1e-3])
    batched = identify_batch(keys, m_a, eps)
    identify_batch(keys, m_a * 2, eps * 3)  # new sweep values, same compiled function
    for b in range(4):
        single = sj.self_identify(OBSERVE, keys[b], m_a[b], eps[b], n_act=3, task_dim=3, iters=12)
        np.testing.assert_allclose(batched.estimate[b], single.estimate, rtol=1e-9, atol=1e-12)
        assert int(batched.converged_at[b]) == int(single.converged_at)
        assert np.all(np.abs(batched.dtheta[b]) <= m_a[b])


@pytest.mark.slow
def test_noise_and_optax_refinement_stay_finite_and_close():
    res = jax.jit(
        lambda k: sj.self_identify(noisy(1e-4), k, 0.05, 1e-3, n_act=3, task_dim=3, iters=40, method="optax",
                                   stop_at_convergence=False)
    )(jax.random.key(2))
    assert np.all(np.isfinite(res.estimates))
    err = np.abs(np.asarray(res.estimate) - np.linalg.inv(J_TRUE)).max()
    assert err < 0.05


@pytest.mark.slow
def test_environment_state_is_threaded_through():
    # observe integrates actuations: env = theta, V = (J @ theta_new) - (J @ theta_old)
    def observe(theta, key, d):
        return theta + d, J_TRUE @ (theta + d) - J_TRUE @ theta

    res = sj.self_identify(observe, jax.random.key(3), 0.05, 1e-3, n_act=3, task_dim=3, iters=6,
                           env=jnp.zeros(3), stop_at_convergence=False)
    np.testing.assert_allclose(res.env, res.dtheta.sum(0), atol=1e-12)


def test_bad_arguments():
    with pytest.raises(ValueError, match="iters"):
        sj.self_identify(OBSERVE, jax.random.key(0), 0.05, 1e-3, n_act=3, task_dim=3, iters=0)
    with pytest.raises(ValueError, match="slsqp"):
        sj.self_identify(OBSERVE, jax.random.key(0), 0.05, 1e-3, n_act=3, task_dim=3, iters=2, method="slsqp")
    with pytest.raises(ValueError, match=r"V: expected shape \(2,\)"):
        sj.self_identify(OBSERVE, jax.random.key(0), 0.05, 1e-3, n_act=3, task_dim=2, iters=2)


@pytest.mark.parametrize("observe", [
    sj.stateless(lambda key, d: jnp.full((3,), jnp.nan)),  # a tracker that lost the tag
    sj.stateless(lambda key, d: jnp.zeros(3)),  # no motion seen
])
@pytest.mark.slow
def test_no_accepted_sample_never_converges(observe):
    res = jax.jit(lambda k: sj.self_identify(observe, k, 0.05, 0.5, n_act=3, task_dim=3, iters=8))(jax.random.key(0))
    assert int(res.converged_at) == -1 and int(res.state.rejected) == 8 and int(res.state.count) == 0
    assert np.all(np.isfinite(res.estimates))


@pytest.mark.slow
def test_traced_nan_or_zero_m_a_gives_rejected_samples_not_convergence():
    run = jax.jit(lambda a: sj.self_identify(OBSERVE, jax.random.key(0), a, 0.5, n_act=3, task_dim=3, iters=6))
    for m_a in (0.0, jnp.nan, jnp.inf):
        res = run(jnp.asarray(m_a))
        assert int(res.converged_at) == -1 and int(res.state.count) == 0, m_a
    with pytest.raises(ValueError, match="m_a: must be > 0"):
        sj.self_identify(OBSERVE, jax.random.key(0), 0.0, 0.5, n_act=3, task_dim=3, iters=6)
    with pytest.raises(ValueError, match=r"m_a: expected a scalar or shape \(3,\)"):
        sj.self_identify(OBSERVE, jax.random.key(0), jnp.ones(2), 0.5, n_act=3, task_dim=3, iters=6)
