"""Ablation estimators (Sec. V-A): one interface, exact recovery on linear systems, independent
references (numpy least squares, RLS = Kalman at q = 0), jit == vmap == loop, bad-sample handling."""

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax import estimator as E
from selfid_jax.refine import refine
from selfid_jax.baselines import METHOD_NAMES, get_method, particle, run_stream, scan

run = jax.jit(run_stream, static_argnames=("method", "capacity"))


def linear_stream(seed, n, T, noise=0.0, scale=0.05):
    """Random square system V = A dtheta (+ noise); returns dthetas (T, n), Vs (T, n), truth inv(A)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n)) + 2.0 * np.eye(n)
    d = rng.uniform(-scale, scale, (T, n))
    V = d @ A.T + noise * rng.normal(size=(T, n))
    return d, V, np.linalg.inv(A)


@jax.jit
def fold(state, d, V):
    """The paper's estimator after the samples ``d (T, n)``, ``V (T, m)``."""
    return jax.lax.scan(lambda s, x: (E.update(s, *x), None), state, (d, V))[0]


def rel_err(est, truth):
    return np.linalg.norm(np.asarray(est) - truth, axis=(-2, -1)) / np.linalg.norm(truth)


def test_get_method_validates_names_and_options():
    with pytest.raises(ValueError) as err:
        get_method("svd")
    for name in METHOD_NAMES:
        assert name in str(err.value)
    with pytest.raises(ValueError, match="lam"):  # the message lists the valid options
        get_method("rls", lamda=0.9)
    with pytest.raises(ValueError, match="magnitude"):
        get_method("ours", magnitude="mode")
    with pytest.raises(ValueError, match="refine_steps"):
        get_method("direct", refine_steps=0)
    with pytest.raises(ValueError, match="concrete"):
        get_method("rls", lam="fast")
    with pytest.raises(ValueError, match="unknown parameter"):
        get_method("rls").init(2, 2, capacity=4, q=1.0)
    # equal by value, hence one jit cache entry for repeated get_method calls
    assert get_method("rls", lam=0.9) == get_method("rls", lam=0.9)
    assert hash(get_method("particle", n_particles=8)) == hash(get_method("particle", n_particles=8))


@pytest.mark.parametrize(
    "name, options",
    [
        ("ours", {}),
        ("ours", {"magnitude": "median"}),
        ("ours", {"refine_method": "optax"}),
        ("direct", {}),
        ("direct", {"init": "random"}),
        ("rls", {}),
        ("kalman", {}),
    ],
)
def test_exact_recovery_of_linear_system(name, options):
    n, T = 3, 8
    d, V, truth = linear_stream(1, n, T)
    est = run(get_method(name, **options), jax.random.key(0), d, V, truth)
    # exact from the m-th independent sample on (noise-free data: least squares has one solution)
    err = rel_err(est[n - 1 :], truth)
    assert err.max() < 1e-6, err


def test_broyden_recovers_linear_system():
    n, m = 4, 3
    rng = np.random.default_rng(2)
    J = rng.normal(size=(n, m))
    # orthogonal excitation: exact after m moves
    Q, _ = np.linalg.qr(rng.normal(size=(m, m)))
    Vo = 0.01 * Q.T
    est = run(get_method("broyden"), None, Vo @ J.T, Vo, J)
    np.testing.assert_allclose(est[-1], J, rtol=1e-12, atol=1e-12)
    assert rel_err(est[-2], J) > 0.1  # not before
    # generic random excitation: linear convergence, < 1e-3 after 20 m samples
    for seed in range(3):
        d, V, truth = linear_stream(seed, 2, 40)
        est = run(get_method("broyden"), None, d, V, truth)
        assert rel_err(est[-1], truth) < 1e-3
        assert rel_err(est[-1], truth) < rel_err(est[9], truth)
    # identity start, damped step
    est = run(get_method("broyden", init="identity"), None, d, V, truth, step=0.5)
    assert rel_err(est[-1], truth) < 0.05  # half steps converge more slowly


def test_rls_with_forgetting_matches_weighted_least_squares():
    """RLS = argmin sum lam^(K-k) ||d_k - J V_k||^2 + lam^K delta_0 ||J||^2, delta_0 = delta |V_1|^2."""
    d, V, _ = linear_stream(3, 3, 12, noise=1e-3)
    lam, delta = 0.8, 1e-2
    est = np.asarray(run(get_method("rls"), None, d, V, np.zeros((3, 3)), lam=lam, delta=delta))
    delta0 = delta * V[0] @ V[0]
    for K in [1, 2, 5, 12]:
        w = lam ** (K - 1 - np.arange(K))
        G = (V[:K].T * w) @ V[:K] + lam**K * delta0 * np.eye(3)
        B = (d[:K].T * w) @ V[:K]
        np.testing.assert_allclose(est[K - 1], np.linalg.solve(G.T, B.T).T, rtol=1e-9)


def test_kalman_with_zero_process_noise_is_rls():
    d, V, truth = linear_stream(4, 3, 15, noise=1e-3)
    delta, r = 1e-3, 1e-4
    p0 = r / (delta * V[0] @ V[0])
    rls = run(get_method("rls"), None, d, V, truth, lam=1.0, delta=delta)
    kal = run(get_method("kalman"), None, d, V, truth, q=0.0, r=r, p0=p0)
    np.testing.assert_allclose(kal, rls, rtol=1e-8, atol=1e-8 * np.abs(rls).max())
    # process noise makes a difference (and stays finite)
    kq = run(get_method("kalman"), None, d, V, truth, q=1e-2, r=r, p0=p0)
    assert np.all(np.isfinite(kq)) and not np.allclose(kq, kal)


def test_particle_filter_roughly_recovers_2x2():
    d, V, truth = linear_stream(0, 2, 40)
    est = run(get_method("particle", n_particles=2000), jax.random.key(0), d, V, truth)
    assert rel_err(est[-1], truth) < 0.2
    assert rel_err(est[-1], truth) < rel_err(est[0], truth)


@pytest.mark.parametrize("scheme", particle.RESAMPLING)
def test_resampling_counts(scheme):
    """Systematic and stratified resampling keep floor(N w_p) copies of each particle at least."""
    w = np.array([0.5, 0.25, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0])
    draw = jax.jit(jax.vmap(functools.partial(particle.resample_indices, scheme=scheme), in_axes=(0, None)))
    for idx in np.asarray(draw(jax.random.split(jax.random.key(0), 5), jnp.log(jnp.asarray(w)))):
        np.testing.assert_array_equal(np.bincount(idx, minlength=8), [4, 2, 2, 0, 0, 0, 0, 0])
    assert float(particle.effective_sample_size(jnp.log(jnp.asarray(w)))) == pytest.approx(1 / 0.375)


def test_oracles_and_ours_without_refinement():
    d, V, truth = linear_stream(5, 3, 6)
    state = fold(E.init(3, 3, capacity=6), d, V)
    signed = E.signed_inverse_jacobian(state)
    np.testing.assert_array_equal(run(get_method("sign_true_mag"), None, d, V, truth)[-1], signed * np.abs(truth))
    np.testing.assert_array_equal(run(get_method("true"), None, d, V, truth)[-1], truth)
    raw = run(get_method("ours", refine=False), None, d, V, truth)[-1]
    np.testing.assert_allclose(raw, E.initial_guess(state), rtol=1e-14)


def test_ours_versus_direct_initial_guess_effect():
    """Closed form: identical once K >= m, different below. Early-stopped refinement: different, worse than LS."""
    n, T = 3, 8
    d, V, truth = linear_stream(6, n, T, noise=1e-4)
    ours = run(get_method("ours"), None, d, V, truth)
    direct = run(get_method("direct"), None, d, V, truth)
    np.testing.assert_allclose(ours[n - 1 :], direct[n - 1 :], rtol=1e-9, atol=1e-9)
    assert not np.allclose(ours[: n - 1], direct[: n - 1])
    budget = 3
    ours_k = run(get_method("ours", refine_steps=budget), None, d, V, truth)
    direct_k = run(get_method("direct", refine_steps=budget), None, d, V, truth)
    assert np.all(np.isfinite(ours_k)) and np.all(np.isfinite(direct_k))
    assert not np.allclose(ours_k[-1], direct_k[-1])
    state = fold(E.init(n, n, capacity=T), d, V)
    f_ls = float(E.objective(state, direct[-1]))
    for J in (ours_k[-1], direct_k[-1]):
        assert float(E.objective(state, J)) >= f_ls * (1 - 1e-9)
    # the budgeted refinement is Nesterov GD from the respective initial guess
    ref = refine(state, E.initial_guess(state), method="optax", steps=budget, precondition=False)
    np.testing.assert_allclose(ours_k[-1], ref, rtol=1e-10)


def _options(name):
    return {"n_particles": 64} if name == "particle" else {}


def _bad_stream(seed, n=3, T=12):
    """Noisy stream with a NaN sample (t=3), a zero actuation (t=6) and a zero pose change (t=9)."""
    d, V, truth = linear_stream(seed, n, T, noise=1e-3)
    d[3, 1] = np.nan
    d[6] = 0.0
    V[9] = 0.0
    return d, V, truth


@pytest.mark.parametrize("name", METHOD_NAMES)
def test_jit_vmap_loop_and_bad_samples(name):
    method = get_method(name, **_options(name))
    streams = [_bad_stream(seed) for seed in range(2)]
    keys = jax.random.split(jax.random.key(1), 2)

    def final_and_estimates(key, d, V, truth):
        state = method.init(3, 3, key, capacity=12)
        return scan(method, state, d, V, truth)

    singles = [jax.jit(final_and_estimates)(k, *s) for k, s in zip(keys, streams)]
    stacked = [np.stack(x) for x in zip(*streams)]
    b_state, b_est = jax.jit(jax.vmap(final_and_estimates))(keys, *stacked)
    for i, (state, est) in enumerate(singles):
        np.testing.assert_allclose(b_est[i], est, rtol=1e-10, atol=1e-12)
        assert int(state.rejected) == 3 and int(state.count) == 9
        assert int(b_state.rejected[i]) == 3
        for leaf in jax.tree.leaves(state):  # (EstimatorState.last_deltas is inf by design)
            if jnp.issubdtype(leaf.dtype, jnp.floating):
                assert not np.any(np.isnan(leaf)), name
        assert np.all(np.isfinite(est))
        for t in (3, 6, 9):  # a rejected sample leaves the estimate unchanged
            np.testing.assert_array_equal(est[t], est[t - 1])


def test_traced_parameter_sweep_compiles_once():
    d, V, truth = linear_stream(7, 3, 10, noise=1e-3)
    method = get_method("rls", delta=1e-4)  # well-conditioned: vmapped and looped rounding agree to 1e-10

    @jax.jit
    @chex.assert_max_traces(n=1)
    def final(lam):
        return run_stream(method, None, d, V, truth, lam=lam)[-1]

    lams = [1.0, 0.95, 0.8]
    loop = np.stack([final(lam) for lam in lams])
    swept = jax.vmap(functools.partial(run_stream, method, None, d, V, truth))
    np.testing.assert_allclose(jax.jit(lambda lam: swept(lam=lam)[:, -1])(jnp.asarray(lams)), loop, rtol=1e-10)
    assert not np.allclose(loop[0], loop[2])
