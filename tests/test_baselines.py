"""Ablation estimators (Sec. V-A): one protocol, exact recovery on linear systems, independent
references (numpy least squares, RLS = Kalman at q = 0), jit == vmap == loop, bad-sample handling,
option checks and traced numeric options."""

import functools
import inspect

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax import baselines as B
from selfid_jax.baselines import (
    METHOD_NAMES,
    METHODS,
    make,
    particle_filter,
    run_stream,
    scan,
)
from selfid_jax.identify import estimator as E
from selfid_jax.identify.refine import refine

run = jax.jit(run_stream, static_argnames=("estimator", "capacity"))


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


def test_make_validates_names_and_options():
    with pytest.raises(ValueError) as err:
        make("svd")
    for name in METHOD_NAMES:
        assert name in str(err.value)
    with pytest.raises(ValueError) as err:  # the message lists the factory's keyword options
        make("rls", lamda=0.9)
    assert "lamda" in str(err.value) and "lam" in str(err.value) and "delta" in str(err.value)
    variants = r"\('mean', 'median', 'weighted', 'kalman'\)"
    with pytest.raises(ValueError, match=rf"ours: magnitude: expected one of {variants}, got 'mode'"):
        make("ours", magnitude="mode")
    with pytest.raises(ValueError, match=r"refine_steps: expected None or a positive integer, got 0"):
        make("direct", refine_steps=0)
    with pytest.raises(ValueError, match=r"lam: expected a real number, got 'fast'"):
        make("rls", lam="fast")
    with pytest.raises(ValueError, match=r"refine: expected one of \(True, False\), got 'yes'"):
        B.ours(refine="yes")
    with pytest.raises(ValueError, match="sign_project"):
        B.ours(sign_project=True)  # needs a gradient refinement
    with pytest.raises(ValueError, match=r"n_particles: expected a positive integer, got 2.5"):
        B.particle(n_particles=2.5)
    with pytest.raises(ValueError, match=r"resampling: expected one of \('systematic', 'stratified'\), got 'multi"):
        B.particle(resampling="multinomial")
    with pytest.raises(ValueError, match=r"init: expected one of \('zero', 'identity'\), got 'random'"):
        B.broyden(init="random")
    with pytest.raises(ValueError, match=r"q: expected a scalar"):
        B.kalman(q=np.ones(2))
    with pytest.raises(TypeError):  # keyword-only, as optax's factories
        B.rls(0.9)
    with pytest.raises(ValueError, match="PRNG key"):
        B.particle(n_particles=4).init(2, 2)
    with pytest.raises(ValueError, match="median.*capacity must be > 0"):
        B.ours(magnitude="median").init(2, 2, capacity=0)
    with pytest.raises(ValueError, match="capacity"):
        B.ours().init(2, 2, capacity=-1)
    assert B.ours().init(2, 2, capacity=0).dtheta_buf.shape == (0, 2)  # the mean magnitude needs no buffer
    # every factory is keyword-only and make() forwards to it
    for name, factory in METHODS.items():
        params = inspect.signature(factory).parameters.values()
        assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for p in params), name
        est = make(name)
        assert isinstance(est, B.Estimator) and est.name == name
    assert B.options("rls") == ("lam", "delta")


@pytest.mark.slow
def test_states_are_namedtuples_of_arrays_and_shapes_are_checked():
    for name in METHOD_NAMES:
        est = make(name, **_options(name))
        state = est.init(3, 3, jax.random.key(0), capacity=4)
        assert hasattr(state, "_fields"), name
        for field in state._fields:  # no dicts: every field is an array or a NamedTuple of arrays
            assert all(isinstance(leaf, jax.Array) for leaf in jax.tree.leaves(getattr(state, field))), (name, field)
        with pytest.raises(ValueError, match=r"dtheta: expected shape \(3,\), got \(2,\)"):
            est.update(state, jnp.zeros(2), jnp.ones(3))
        with pytest.raises(ValueError, match=r"V: expected shape \(3,\), got \(3, 1\)"):
            est.update(state, jnp.ones(3), jnp.ones((3, 1)))
        with pytest.raises(ValueError, match=r"truth: expected shape \(3, 3\), got \(3, 2\)"):
            est.estimate(state, jnp.zeros((3, 2)))
    # the paper's estimator keeps its counters once: "ours" is the EstimatorState itself
    assert isinstance(B.ours().init(3, 3), E.EstimatorState)
    assert B.direct().init(3, 3)._fields == ("est", "J_init")


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
@pytest.mark.slow
def test_exact_recovery_of_linear_system(name, options):
    n, T = 3, 8
    d, V, truth = linear_stream(1, n, T)
    est = run(make(name, **options), jax.random.key(0), d, V, truth)
    # exact from the m-th independent sample on (noise-free data: least squares has one solution)
    err = rel_err(est[n - 1 :], truth)
    assert err.max() < 1e-6, err


@pytest.mark.slow
def test_broyden_recovers_linear_system():
    n, m = 4, 3
    rng = np.random.default_rng(2)
    J = rng.normal(size=(n, m))
    # orthogonal excitation: exact after m moves
    Q, _ = np.linalg.qr(rng.normal(size=(m, m)))
    Vo = 0.01 * Q.T
    est = run(B.broyden(), None, Vo @ J.T, Vo, J)
    np.testing.assert_allclose(est[-1], J, rtol=1e-12, atol=1e-12)
    assert rel_err(est[-2], J) > 0.1  # not before
    # generic random excitation: linear convergence, < 1e-3 after 20 m samples
    for seed in range(3):
        d, V, truth = linear_stream(seed, 2, 40)
        est = run(B.broyden(), None, d, V, truth)
        assert rel_err(est[-1], truth) < 1e-3
        assert rel_err(est[-1], truth) < rel_err(est[9], truth)
    # identity start, damped step
    est = run(B.broyden(init="identity", step=0.5), None, d, V, truth)
    assert rel_err(est[-1], truth) < 0.05  # half steps converge more slowly


def test_rls_with_forgetting_matches_weighted_least_squares():
    """RLS = argmin sum lam^(K-k) ||d_k - J V_k||^2 + lam^K delta_0 ||J||^2, delta_0 = delta |V_1|^2."""
    d, V, _ = linear_stream(3, 3, 12, noise=1e-3)
    lam, delta = 0.8, 1e-2
    est = np.asarray(run(B.rls(lam=lam, delta=delta), None, d, V, np.zeros((3, 3))))
    delta0 = delta * V[0] @ V[0]
    for K in [1, 2, 5, 12]:
        w = lam ** (K - 1 - np.arange(K))
        G = (V[:K].T * w) @ V[:K] + lam**K * delta0 * np.eye(3)
        rhs = (d[:K].T * w) @ V[:K]
        np.testing.assert_allclose(est[K - 1], np.linalg.solve(G.T, rhs.T).T, rtol=1e-9)


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_kalman_with_zero_process_noise_is_rls():
    d, V, truth = linear_stream(4, 3, 15, noise=1e-3)
    delta, r = 1e-3, 1e-4
    p0 = r / (delta * V[0] @ V[0])
    rls = run(B.rls(lam=1.0, delta=delta), None, d, V, truth)
    kal = run(B.kalman(q=0.0, r=r, p0=p0), None, d, V, truth)
    np.testing.assert_allclose(kal, rls, rtol=1e-8, atol=1e-8 * np.abs(rls).max())
    # process noise makes a difference (and stays finite)
    kq = run(B.kalman(q=1e-2, r=r, p0=p0), None, d, V, truth)
    assert np.all(np.isfinite(kq)) and not np.allclose(kq, kal)


@pytest.mark.slow
def test_particle_filter_roughly_recovers_2x2():
    d, V, truth = linear_stream(0, 2, 40)
    est = run(B.particle(n_particles=2000), jax.random.key(0), d, V, truth)
    assert rel_err(est[-1], truth) < 0.2
    assert rel_err(est[-1], truth) < rel_err(est[0], truth)


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
@pytest.mark.parametrize("scheme", particle_filter.RESAMPLING)
def test_resampling_counts(scheme):
    """Systematic and stratified resampling keep floor(N w_p) copies of each particle at least."""
    w = np.array([0.5, 0.25, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0])
    draw = jax.jit(jax.vmap(functools.partial(particle_filter.resample_indices, scheme=scheme), in_axes=(0, None)))
    for idx in np.asarray(draw(jax.random.split(jax.random.key(0), 5), jnp.log(jnp.asarray(w)))):
        np.testing.assert_array_equal(np.bincount(idx, minlength=8), [4, 2, 2, 0, 0, 0, 0, 0])
    assert float(particle_filter.effective_sample_size(jnp.log(jnp.asarray(w)))) == pytest.approx(1 / 0.375)


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_oracles_and_ours_without_refinement():
    d, V, truth = linear_stream(5, 3, 6)
    state = fold(E.init(3, 3, capacity=6), d, V)
    signed = E.signed_inverse_jacobian(state)
    np.testing.assert_array_equal(run(B.sign_true_mag(), None, d, V, truth)[-1], signed * np.abs(truth))
    np.testing.assert_array_equal(run(B.true(), None, d, V, truth)[-1], truth)
    raw = run(B.ours(refine=False), None, d, V, truth)[-1]
    np.testing.assert_allclose(raw, E.initial_guess(state), rtol=1e-14)


@pytest.mark.slow
def test_ours_versus_direct_initial_guess_effect():
    """Closed form: identical once K >= m, different below. Early-stopped refinement: different, worse than LS."""
    n, T = 3, 8
    d, V, truth = linear_stream(6, n, T, noise=1e-4)
    ours = run(B.ours(), None, d, V, truth)
    direct = run(B.direct(), None, d, V, truth)
    np.testing.assert_allclose(ours[n - 1 :], direct[n - 1 :], rtol=1e-9, atol=1e-9)
    assert not np.allclose(ours[: n - 1], direct[: n - 1])
    budget = 3
    ours_k = run(B.ours(refine_steps=budget), None, d, V, truth)
    direct_k = run(B.direct(refine_steps=budget), None, d, V, truth)
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


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n == "particle" else n for n in METHOD_NAMES]
)
@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_jit_vmap_loop_and_bad_samples(name):
    est = make(name, **_options(name))
    streams = [_bad_stream(seed) for seed in range(2)]
    keys = jax.random.split(jax.random.key(1), 2)

    def final_and_estimates(key, d, V, truth):
        state = est.init(3, 3, key, capacity=12)
        return scan(est, state, d, V, truth)

    singles = [jax.jit(final_and_estimates)(k, *s) for k, s in zip(keys, streams)]
    stacked = [np.stack(x) for x in zip(*streams)]
    b_state, b_est = jax.jit(jax.vmap(final_and_estimates))(keys, *stacked)
    for i, (state, est) in enumerate(singles):
        np.testing.assert_allclose(b_est[i], est, rtol=1e-10, atol=1e-12)
        counters = state.est if name == "direct" else state  # direct keeps them in its EstimatorState
        assert int(counters.rejected) == 3 and int(counters.count) == 9
        assert int((b_state.est if name == "direct" else b_state).rejected[i]) == 3
        for leaf in jax.tree.leaves(state):  # (EstimatorState.last_deltas is inf by design)
            if jnp.issubdtype(leaf.dtype, jnp.floating):
                assert not np.any(np.isnan(leaf)), name
        assert np.all(np.isfinite(est))
        for t in (3, 6, 9):  # a rejected sample leaves the estimate unchanged
            np.testing.assert_array_equal(est[t], est[t - 1])


@pytest.mark.slow
def test_traced_options_compile_once():
    """Numeric options are captured by the factory's closures: one trace serves every value, jit and vmap."""
    d, V, truth = linear_stream(7, 3, 10, noise=1e-3)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def final(lam, delta):  # well-conditioned delta: vmapped and looped rounding agree to 1e-10
        return run_stream(B.rls(lam=lam, delta=delta), None, d, V, truth)[-1]

    lams = [1.0, 0.95, 0.8]
    loop = np.stack([final(lam, 1e-4) for lam in lams])
    swept = jax.jit(jax.vmap(lambda lam: run_stream(B.rls(lam=lam, delta=1e-4), None, d, V, truth)[-1]))
    np.testing.assert_allclose(swept(jnp.asarray(lams)), loop, rtol=1e-10)
    assert not np.allclose(loop[0], loop[2])
    # the traced option gives the same numbers as the Python float
    np.testing.assert_allclose(loop[1], run(B.rls(lam=0.95, delta=1e-4), None, d, V, truth)[-1], rtol=1e-12)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def three_methods(q, v_tol, scale):  # several methods, several traced options
        a = run_stream(B.kalman(q=q), None, d, V, truth)[-1]
        b = run_stream(B.ours(refine=False, magnitude="kalman", magnitude_q=q, v_tol=v_tol), None, d, V, truth)[-1]
        c = run_stream(B.direct(init="random", init_scale=scale), jax.random.key(0), d, V, truth)[0]
        return a, b, c

    outs = []
    for q, scale in ((0.0, 1.0), (1e-2, 2.0)):
        a, b, c = three_methods(q, 1e-9, scale)
        np.testing.assert_allclose(a, run(B.kalman(q=q), None, d, V, truth)[-1], rtol=1e-12)
        ours_q = B.ours(refine=False, magnitude="kalman", magnitude_q=q)
        np.testing.assert_allclose(b, run(ours_q, None, d, V, truth)[-1], rtol=1e-12)
        direct_s = B.direct(init="random", init_scale=scale)
        np.testing.assert_allclose(c, run(direct_s, jax.random.key(0), d, V, truth)[0], rtol=1e-12)
        outs.append((a, b, c))
    for x, y in zip(*outs):  # every traced option took effect
        assert not np.allclose(x, y)
