"""Magnitude variants (Eq. 11-12 and the ablation's median / weighted / Kalman) against numpy references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax.identify import estimator as E
from selfid_jax.identify import magnitude as M

V_TOL = 1e-9
# jitted once per state shape: eager dispatch of the sorts and scans is slower than compiling
median, weighted, kalman = jax.jit(M.median), jax.jit(M.weighted), jax.jit(M.kalman)


def samples(seed=0, K=9, n=3, m=4):
    """Random samples with degenerate entries: tiny V_j, zero dtheta_i, and one invalid (NaN) sample."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(-0.05, 0.05, (K, n))
    V = d @ rng.normal(size=(n, m)) + 1e-3 * rng.normal(size=(K, m))
    V[1, 0] = 1e-12  # below v_tol: column 0 loses a sample (even / odd counts differ per column)
    V[:, 3] = 0.0  # column 3 never usable
    V[4, 3] = 2e-3  # ... except once
    d[2, 1] = 0.0  # a zero actuation: ratio 0, weight 0
    return d, V


def fold(d, V, capacity, bad=True):
    state = E.init(d.shape[1], V.shape[1], capacity=capacity, v_tol=V_TOL)
    upd = jax.jit(E.update)
    for k, (a, b) in enumerate(zip(d, V)):
        if bad and k == 3:  # rejected samples must not reach the buffer
            state = upd(state, np.full_like(a, np.nan), b)
            state = upd(state, np.zeros_like(a), b)
        state = upd(state, a, b)
    return state


def valid_ratios(d, V, i, j):
    keep = np.abs(V[:, j]) > V_TOL
    r = np.abs(d[keep, i] / V[keep, j])
    wt = np.abs(d[keep, i]) / np.abs(d[keep]).sum(1)
    wv = np.abs(V[keep, j]) / np.abs(V[keep]).sum(1)
    return r, wt * wv


def np_median(d, V):
    out = np.zeros((d.shape[1], V.shape[1]))
    for i in range(d.shape[1]):
        for j in range(V.shape[1]):
            r, _ = valid_ratios(d, V, i, j)
            out[i, j] = np.median(r) if r.size else 0.0
    return out


def np_weighted(d, V):
    out = np.zeros((d.shape[1], V.shape[1]))
    for i in range(d.shape[1]):
        for j in range(V.shape[1]):
            r, w = valid_ratios(d, V, i, j)
            out[i, j] = np.average(r, weights=w) if w.sum() > 0 else 0.0
    return out


def np_kalman(d, V, q, r):
    """Scalar Kalman filter per element, written out as in the docstring of magnitude.kalman."""
    out = np.zeros((d.shape[1], V.shape[1]))
    for i in range(d.shape[1]):
        for j in range(V.shape[1]):
            x, P, started = 0.0, 0.0, False
            for z in valid_ratios(d, V, i, j)[0]:
                if not started:
                    x, P, started = z, r * z * z, True
                    continue
                P = P + q * x * x
                S = P + r * x * x
                K = P / S if S > 0 else 1.0
                x = x + K * (z - x)
                P = (1 - K) * P
            out[i, j] = x
    return out


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
@pytest.mark.parametrize("capacity", [16, 6])  # buffer larger than the stream, and a wrapped ring buffer
def test_variants_match_numpy(capacity):
    d, V = samples()
    state = fold(d, V, capacity)
    assert int(state.rejected) == 2 and int(state.count) == len(d)
    last = slice(-min(capacity, len(d)), None)  # the buffer holds the last `capacity` samples
    np.testing.assert_allclose(median(state), np_median(d[last], V[last]), rtol=1e-12)
    np.testing.assert_allclose(weighted(state), np_weighted(d[last], V[last]), rtol=1e-12)
    for q, r in [(1e-2, 1.0), (0.3, 0.05), (0.0, 2.0)]:
        np.testing.assert_allclose(kalman(state, q=q, r=r), np_kalman(d[last], V[last], q, r), rtol=1e-10)
    np.testing.assert_array_equal(M.mean(state), E.magnitude_inverse_jacobian(state))
    # every variant of a noise-free-ish system is positive where data exist, zero where none
    for out in (median(state), weighted(state), kalman(state), M.mean(state)):
        assert np.all(np.isfinite(out)) and np.all(np.asarray(out) >= 0)


@pytest.mark.slow
def test_median_even_and_odd_counts():
    # column 0: ratios [1, 2, 10] (odd), column 1: [1, 2, 3, 100] (even)
    d = np.ones((4, 3))  # the shape of the degenerate states below: one compiled median and update
    V = np.array([[1.0, 1.0], [0.5, 0.5], [0.1, 1 / 3], [1e-12, 0.01]])
    state = fold(d, V, capacity=5, bad=False)
    np.testing.assert_allclose(median(state), [[2.0, 2.5]] * 3, rtol=1e-12)


@pytest.mark.slow
def test_degenerate_states_are_finite_and_zero():
    variants = (M.mean, median, weighted, kalman)
    empty = E.init(3, 2, capacity=5)
    for fn in variants:
        np.testing.assert_array_equal(fn(empty), np.zeros((3, 2)))
    # only zero-V components in column 1 and a zero actuator 0: zeros there, no NaN
    d = np.array([[0.0, 0.1, -0.2], [0.0, 0.3, 0.1]])
    V = np.array([[0.01, 0.0], [-0.02, 0.0]])
    state = fold(d, V, capacity=5, bad=False)
    for fn in variants:
        out = np.asarray(fn(state))
        assert np.all(np.isfinite(out))
        np.testing.assert_array_equal(out[:, 1], 0.0)
        np.testing.assert_array_equal(out[0], 0.0)
    with pytest.raises(ValueError, match="median"):
        M.get("mode")
    assert M.get("kalman") is M.kalman


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_jit_and_vmap_equal_loop():
    states = [fold(*samples(seed), capacity=6) for seed in range(3)]
    batched = jax.tree.map(lambda *x: jnp.stack(x), *states)
    q = jnp.array([0.0, 0.1, 1.0])
    cases = {
        "median": lambda s, _: median(s),
        "weighted": lambda s, _: weighted(s),
        "kalman": lambda s, qq: kalman(s, q=qq, r=0.5),
    }
    for name, fn in cases.items():
        got = jax.jit(jax.vmap(fn))(batched, q)
        want = np.stack([fn(s, qq) for s, qq in zip(states, q)])
        np.testing.assert_allclose(got, want, rtol=1e-12, err_msg=name)


@jax.jit
def _sorts(x, batch):
    """``sort_axis0`` of ``x`` and, vmapped, of each row of ``batch``: one compiled program per ``K``."""
    return M.sort_axis0(x), jax.vmap(M.sort_axis0)(batch)


@pytest.mark.slow
@pytest.mark.parametrize("K", [1, 2, 3, 7, 8, 37, 100])
def test_sort_axis0_matches_numpy(K):
    rng = np.random.default_rng(K)
    x = rng.choice([0.0, 0.5, 1.0, 2.0, np.inf], size=(K, 3, 2)) if K % 2 else rng.normal(size=(K, 3, 2))
    batch = rng.normal(size=(4, K, 5))
    one, batched = _sorts(jnp.asarray(x), jnp.asarray(batch))
    np.testing.assert_array_equal(one, np.sort(x, axis=0))  # ties and inf too
    np.testing.assert_array_equal(batched, np.sort(batch, axis=1))
