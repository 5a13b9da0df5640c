"""Property tests (hypothesis) of laws the estimator must satisfy for any input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

import selfid_jax as sj
from selfid_jax.identify import estimator as E

update = jax.jit(E.update)
closed_form = jax.jit(lambda s: sj.refine(s, sj.initial_guess(s), method="closed_form"))

finite = st.floats(-1e3, 1e3, allow_nan=False, width=64)
anything = st.one_of(finite, st.just(0.0), st.just(np.nan), st.just(np.inf), st.just(-np.inf))


@pytest.mark.slow
@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.lists(anything, min_size=3, max_size=3), st.lists(anything, min_size=2, max_size=2)),
                min_size=1, max_size=6))
@example([([1.0, 0.0, 0.0], [0.0, 1.1125369292536007e-308])])  # a subnormal pose change counts as zero
def test_state_never_holds_nan_and_counts_add_up(samples):
    state = E.init(3, 2, capacity=4)
    for d, v in samples:
        state = update(state, jnp.asarray(d), jnp.asarray(v))
    assert int(state.count) + int(state.rejected) == len(samples)
    for leaf in jax.tree.leaves(state._replace(last_deltas=jnp.zeros(2))):
        assert np.all(np.isfinite(leaf))
    for x in (sj.initial_guess(state), closed_form(state)):
        assert np.all(np.isfinite(x))
    tiny = np.finfo(np.float64).tiny  # subnormal entries count as zero
    expected_ok = sum(np.all(np.isfinite(d)) and np.all(np.isfinite(v)) and np.any(np.abs(d) >= tiny)
                      and np.any(np.abs(v) >= tiny) for d, v in samples)
    assert int(state.count) == expected_ok


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 4))
def test_exact_recovery_and_sample_order_invariance(seed, n):
    """Noise-free samples of an invertible linear system: the refined estimate is its inverse,
    whatever the order of the samples."""
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(n, n)) + 3.0 * np.eye(n)
    d = rng.uniform(-0.05, 0.05, (n + 3, n))
    V = d @ J.T
    states = []
    for order in (np.arange(len(d)), rng.permutation(len(d))):
        s = E.init(n, n, capacity=8)
        for k in order:
            s = update(s, jnp.asarray(d[k]), jnp.asarray(V[k]))
        states.append(s)
    est = [np.asarray(closed_form(s)) for s in states]
    inv = np.linalg.inv(J)
    np.testing.assert_allclose(est[0], inv, rtol=1e-6, atol=1e-6 * np.abs(inv).max())
    np.testing.assert_allclose(est[0], est[1], rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(sj.initial_guess(states[0]), sj.initial_guess(states[1]), rtol=1e-10)
