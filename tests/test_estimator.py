"""Estimator (Eq. 6-13), convergence test (Sec. IV-D) and bad-input handling."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import selfid_jax as sj
from selfid_jax.identify import estimator as E
from selfid_jax.math import native


def numpy_reference(dthetas, Vs, v_tol):
    """Straight numpy reading of Eq. 6-13 over a list of valid samples."""
    n, m = dthetas.shape[1], Vs.shape[1]
    pos, neg = np.zeros((n, m)), np.zeros((n, m))
    msum, mcnt = np.zeros((n, m)), np.zeros((n, m))
    for d, v in zip(dthetas, Vs):
        for i in range(n):
            for j in range(m):
                s = np.sign(d[i]) * np.sign(v[j])  # Eq. 6
                w = abs(d[i]) / np.abs(d).sum() * abs(v[j]) / np.abs(v).sum()  # Eq. 7-8
                if s > 0:
                    pos[i, j] += w  # Eq. 9
                elif s < 0:
                    neg[i, j] += w
                if abs(v[j]) > v_tol:
                    msum[i, j] += abs(d[i] / v[j])  # Eq. 11
                    mcnt[i, j] += 1
    signed = np.where(pos >= neg, 1.0, -1.0)  # Eq. 10
    mag = np.where(mcnt > 0, msum / np.maximum(mcnt, 1), 0.0)  # Eq. 12
    return signed, mag, signed * mag  # Eq. 13


def fold(state, dthetas, Vs, update=E.update):
    for d, v in zip(dthetas, Vs):
        state = update(state, d, v)
    return state


jit_update = jax.jit(E.update)


@pytest.mark.slow
def test_matches_numpy_reference():
    rng = np.random.default_rng(0)
    n, m, K = 4, 3, 25
    d = rng.uniform(-0.05, 0.05, (K, n))
    V = d @ rng.normal(size=(n, m)) + 1e-3 * rng.normal(size=(K, m))
    V[3, 1] = 1e-12  # below v_tol: skipped by the magnitude mean only
    d[5, 2] = 0.0  # a zero actuation adds no sign weight
    state = fold(E.init(n, m, capacity=8, v_tol=1e-9), d, V, jit_update)
    signed, mag, guess = numpy_reference(d, V, 1e-9)
    np.testing.assert_array_equal(sj.signed_inverse_jacobian(state), signed)
    np.testing.assert_allclose(sj.magnitude_inverse_jacobian(state), mag, rtol=1e-12)
    np.testing.assert_allclose(sj.initial_guess(state), guess, rtol=1e-12)
    assert int(state.count) == K and int(state.rejected) == 0
    # ring buffer keeps the last `capacity` samples
    buf_rows = {tuple(np.round(r, 12)) for r in np.asarray(state.dtheta_buf)}
    assert buf_rows == {tuple(np.round(r, 12)) for r in d[-8:]}


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_ties_and_empty_state():
    state = E.init(2, 3)
    np.testing.assert_array_equal(sj.signed_inverse_jacobian(state), np.ones((2, 3)))
    np.testing.assert_array_equal(sj.magnitude_inverse_jacobian(state), np.zeros((2, 3)))
    J0 = jnp.arange(6.0).reshape(2, 3)
    for method in ("closed_form", "optax", "slsqp"):
        np.testing.assert_array_equal(sj.refine(state, J0, method=method), J0)


def random_orthogonal(rng, n, min_abs=0.15):
    while True:
        q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        if np.abs(q).min() > min_abs:
            return q


@pytest.mark.parametrize("n", [2, 3])
@pytest.mark.slow
def test_sign_recovery_on_sign_unambiguous_system(n):
    # For an orthogonal J, sign(J^-1) = sign(J^T): every element has a clear sign.
    rng = np.random.default_rng(n)
    Q = random_orthogonal(rng, n)
    d = rng.uniform(-0.05, 0.05, (400, n))
    state = fold(E.init(n, n, capacity=4), d, d @ Q.T, jit_update)
    np.testing.assert_array_equal(sj.signed_inverse_jacobian(state), np.sign(np.linalg.inv(Q)))


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_rejects_bad_samples_without_nan():
    state = E.init(3, 2, capacity=4)
    good_d, good_v = jnp.array([0.01, -0.02, 0.03]), jnp.array([0.1, -0.2])
    state = E.update(state, good_d, good_v)
    bad = [
        (jnp.array([jnp.nan, 0.0, 0.1]), good_v),
        (good_d, jnp.array([jnp.inf, 0.1])),
        (jnp.zeros(3), good_v),
        (good_d, jnp.zeros(2)),
        (good_d, jnp.array([-jnp.inf, jnp.nan])),
    ]
    for d, v in bad:
        before = state
        state = jit_update(state, d, v)
        chex.assert_trees_all_equal(before._replace(rejected=state.rejected), state)
    assert int(state.rejected) == len(bad) and int(state.count) == 1
    # last_deltas is +inf until the first `record`; everything else must be finite
    for leaf in jax.tree.leaves(state._replace(last_deltas=jnp.zeros(2))):
        assert np.all(np.isfinite(leaf))
    for x in (sj.initial_guess(state), sj.refine(state, sj.initial_guess(state), method="optax")):
        assert np.all(np.isfinite(x))


def test_wrong_shapes_raise_value_error():
    state = E.init(3, 2)
    with pytest.raises(ValueError, match=r"dtheta: expected shape \(3,\), got \(2,\)"):
        E.update(state, jnp.zeros(2), jnp.zeros(2))
    with pytest.raises(ValueError, match=r"V: expected shape \(2,\), got \(2, 1\)"):
        E.update(state, jnp.zeros(3), jnp.zeros((2, 1)))
    with pytest.raises(ValueError, match=r"J0: expected shape \(3, 2\), got \(2, 3\)"):
        sj.refine(state, jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match="dtype"):
        E.update(state, jnp.zeros(3, bool), jnp.zeros(2))
    with pytest.raises(ValueError, match="capacity: expected a non-negative integer"):
        E.init(3, 2, capacity=-1)
    for forget in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="forget"):
            E.init(3, 2, forget=forget)
    with pytest.raises(ValueError, match="method"):
        sj.refine(state, jnp.zeros((3, 2)), method="adam")


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_convergence_test_needs_two_consecutive_small_changes():
    eps = 0.1
    state = E.init(1, 1)
    sequence = [1.0, 1.05, 2.0, 2.05, 2.1, 2.12]  # deltas: 1, .05, .95, .05, .05, .02
    expect = [False, False, False, False, True, True]
    for t, (j, want) in enumerate(zip(sequence, expect), start=1):
        state = E.update(state, jnp.array([0.01]), jnp.array([0.02]))  # new data before each record
        state = E.record(state, jnp.array([[j]]), eps)
        assert bool(sj.converged(state, eps)) == want, t
    assert int(state.converged_at) == 5 and int(state.iteration) == 6
    np.testing.assert_allclose(state.last_deltas, [0.05, 0.02], atol=1e-12)


@pytest.mark.slow
def test_min_count_holds_the_test_back_until_that_many_samples_jit_and_vmap():
    """record(min_count=k): converged at the first record with both last changes small and >= k samples accepted;
    the deltas [1, .05, .95, .05, .05, .02, .01]: 5 for k <= 5, 6 for k = 6, 7 for k = 7, never for k = 8."""
    sequence = jnp.array([1.0, 1.05, 2.0, 2.05, 2.1, 2.12, 2.13])

    def run(min_count):
        def body(state, j):
            state = E.update(state, jnp.array([0.01]), jnp.array([0.02]))
            return E.record(state, j.reshape(1, 1), 0.1, min_count=min_count), None
        return jax.lax.scan(body, E.init(1, 1), sequence)[0].converged_at

    ks = jnp.array([0, 5, 6, 7, 8])
    np.testing.assert_array_equal(jax.jit(jax.vmap(run))(ks), [5, 5, 6, 7, -1])
    assert int(run(0)) == 5


def _numpy_convergence_iteration(est, eps):
    """Sec. IV-D over a sequence, straight numpy: first t with delta_{t-1}, delta_t <= eps (J_0 = 0), else -1."""
    deltas = np.linalg.norm(np.diff(np.concatenate([np.zeros((1,) + est.shape[1:]), est]), axis=0), axis=(1, 2))
    for t in range(1, len(est)):
        if deltas[t] <= eps and deltas[t - 1] <= eps:
            return t + 1
    return -1


@pytest.mark.slow
def test_convergence_iteration_matches_numpy_and_record():
    """One convergence test: convergence_iteration over a sequence == a numpy loop == record's converged_at."""
    rng = np.random.default_rng(0)
    T, n, m = 30, 3, 2
    est = np.cumsum(rng.normal(size=(T, n, m)) * np.geomspace(1, 1e-4, T)[:, None, None], axis=0)
    est[12] = est[11]  # an exact repeat (delta 0) in the middle
    conv = jax.jit(E.convergence_iteration)
    seen = set()
    for eps in (1e-9, 1e-3, 1e-2, 0.1, 1.0, 10.0):
        want = _numpy_convergence_iteration(est, eps)
        got = conv(jnp.asarray(est), eps)
        assert got.dtype == jnp.int32 and int(got) == want, eps
        state = E.init(n, m)
        for J in est:
            state = E.update(state, jnp.ones(n), jnp.ones(m))
            state = E.record(state, jnp.asarray(J), eps)
        assert int(state.converged_at) == want, eps
        seen.add(want)
    assert -1 in seen and len(seen) >= 3  # the sweep covers never, early and late convergence
    # the sequence in test_convergence_test_needs_two_consecutive_small_changes
    seq = jnp.asarray([1.0, 1.05, 2.0, 2.05, 2.1, 2.12])[:, None, None]
    assert int(E.convergence_iteration(seq, 0.1)) == 5
    assert int(E.convergence_iteration(seq[:4], 0.1)) == -1
    assert int(E.convergence_iteration(jnp.zeros((0, 1, 1)), 0.1)) == -1
    with pytest.raises(ValueError, match=r"estimates: expected shape .*, got \(3, 2\)"):
        E.convergence_iteration(jnp.zeros((3, 2)), 0.1)


@pytest.mark.slow
def test_guarded_update_is_the_one_sample_screen():
    """update == guarded_update(accumulate): valid samples are folded and counted, invalid ones only counted."""
    state = E.init(3, 2, capacity=4)
    d, V = jnp.array([0.01, -0.02, 0.03]), jnp.array([0.1, -0.2])
    folded = E.accumulate(state, d, V)
    chex.assert_trees_all_equal(E.update(state, d, V), folded._replace(count=jnp.int32(1)))
    seen = []

    def fold(s, a, b):  # sees a zeroed sample when invalid, never the NaN
        seen.append((a, b))
        return E.accumulate(s, a, b)

    out = E.guarded_update(fold, state, jnp.array([jnp.nan, 0.0, 0.1]), V, shape=(3, 2), dtype=state.sign_net.dtype)
    chex.assert_trees_all_equal(out, state._replace(rejected=jnp.int32(1)))
    np.testing.assert_array_equal(seen[0][0], np.zeros(3))


class JitVmapTest(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_update_and_estimates_jit_equals_eager(self):
        rng = np.random.default_rng(3)
        d, V = rng.normal(size=(6, 3)), rng.normal(size=(6, 2))
        ref = fold(E.init(3, 2, capacity=4), d, V)
        upd = self.variant(E.update)
        state = E.init(3, 2, capacity=4)
        for a, b in zip(d, V):
            state = upd(state, a, b)
        chex.assert_trees_all_close(state, ref, rtol=1e-12)
        chex.assert_trees_all_close(self.variant(sj.initial_guess)(state), sj.initial_guess(ref), rtol=1e-12)

    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_record_with_a_given_delta_equals_record(self):
        """``delta=`` (the caller's ``||J - estimate||_F``, e.g. a rank-one update's ``||e|| ||k||``) records what
        ``record`` computes itself, convergence included; a wrong shape names the argument."""
        rng = np.random.default_rng(7)
        state = E.update(E.init(3, 2, capacity=0), rng.normal(size=3), rng.normal(size=2))
        rec = self.variant(lambda s, J, d: E.record(s, J, 0.5, delta=d))
        for _ in range(3):
            e, k = 0.1 * rng.normal(size=3), 0.1 * rng.normal(size=2)
            J = np.asarray(state.estimate) + np.outer(e, k)
            got = rec(state, J, np.linalg.norm(e) * np.linalg.norm(k))
            ref = E.record(state, J, 0.5)
            chex.assert_trees_all_close(got, ref, rtol=1e-12, atol=1e-15)
            state = E.update(got, rng.normal(size=3), rng.normal(size=2))
        assert int(got.converged_at) == int(ref.converged_at) > 0
        with pytest.raises(ValueError, match="delta"):
            E.record(state, J, 0.5, delta=np.ones(2))

    @pytest.mark.slow
    def test_vmap_equals_loop(self):
        rng = np.random.default_rng(4)
        B, K, n, m = 3, 5, 3, 2
        d, V = rng.normal(size=(B, K, n)), rng.normal(size=(B, K, m))
        states = jax.vmap(lambda _: E.init(n, m, capacity=4))(jnp.arange(B))
        vupd = jax.jit(jax.vmap(E.update))
        for k in range(K):
            states = vupd(states, d[:, k], V[:, k])
        guesses = jax.vmap(sj.initial_guess)(states)
        for b in range(B):
            np.testing.assert_allclose(guesses[b], sj.initial_guess(fold(E.init(n, m, capacity=4), d[b], V[b])))

    def test_v_tol_is_traced_no_retrace(self):
        @jax.jit
        @chex.assert_max_traces(n=1)
        def magnitude(v_tol, d, V):
            return sj.magnitude_inverse_jacobian(E.update(E.init(2, 2, v_tol=v_tol), d, V))

        d, V = jnp.array([0.1, 0.2]), jnp.array([1e-4, 1.0])
        out = [magnitude(tol, d, V) for tol in (1e-6, 1e-3, 1e-2)]
        np.testing.assert_allclose(out[0][:, 0], [1000.0, 2000.0])
        np.testing.assert_allclose(out[1][:, 0], [0.0, 0.0])


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_update_once_and_record_norm_change_no_value():
    """update(once=f) screens and folds as update() does, f seeing the acceptance and the sample's terms; record(norm=)
    stores the given ||J||_F, which record otherwise computes itself; a wrong-shaped norm names the argument."""
    seen = []

    def f(x):
        seen.append(x.shape)
        return x

    state = E.init(3, 2, capacity=2)
    old = native.set_enabled(False)  # update() without once runs the native kernel where built: equal to round-off
    try:
        for d, V in (([0.1, -0.2, 0.3], [0.5, -0.1]), ([jnp.nan, 0.0, 0.1], [1.0, 0.0])):  # accepted, rejected
            chex.assert_trees_all_equal(E.update(state, d, V, once=f), E.update(state, d, V))
    finally:
        native.set_enabled(old)
    assert seen == [(), (3,), (2,), (2,)] * 2  # acceptance, u_t, u_v, 1 / |V_j|
    J = jnp.arange(6.0).reshape(3, 2)
    chex.assert_trees_all_close(E.record(state, J, 0.1, norm=jnp.linalg.norm(J)), E.record(state, J, 0.1),
                                rtol=1e-15)
    with pytest.raises(ValueError, match="norm"):
        E.record(state, J, 0.1, norm=np.ones(2))


@pytest.mark.slow
def test_no_new_data_never_converges_and_eps_inf_needs_two_records():
    """Records that follow no accepted sample never count; iteration 1 never converges, even at eps = inf."""
    state = E.init(2, 2)
    for _ in range(5):  # every sample rejected: the estimate stays 0, deltas are 0
        state = E.update(state, jnp.array([jnp.nan, 0.1]), jnp.array([0.1, 0.2]))
        state = E.record(state, E.initial_guess(state), 0.5)
    assert int(state.converged_at) == -1 and int(state.rejected) == 5 and not bool(sj.converged(state, 0.5))
    est = jnp.zeros((5, 2, 2))
    assert int(E.convergence_iteration(est, 0.5, accepted=jnp.zeros(5, bool))) == -1
    assert int(E.convergence_iteration(est, 0.5, accepted=jnp.array([0, 1, 0, 1, 1], bool))) == 5
    fresh = E.init(1, 1)
    fresh = E.record(E.update(fresh, jnp.ones(1), jnp.ones(1)), jnp.ones((1, 1)), jnp.inf)
    assert int(fresh.converged_at) == -1  # one record is not "twice in a row"
    fresh = E.record(E.update(fresh, jnp.ones(1), jnp.ones(1)), jnp.ones((1, 1)), jnp.inf)
    assert int(fresh.converged_at) == 2
    assert int(E.convergence_iteration(jnp.ones((3, 1, 1)), jnp.inf)) == 2


@pytest.mark.slow
def test_relative_threshold_scales_with_the_estimate():
    """eps_rel: ||J_t - J_{t-1}||_F <= eps + eps_rel ||J_t||_F; a 40x larger system converges at the same step."""
    seq = jnp.asarray([1.0, 1.5, 1.52, 1.53, 1.531])[:, None, None]  # deltas 1, .5, .02, .01, .001
    for scale in (1.0, 40.0):
        got = E.convergence_iteration(scale * seq, 0.0, 0.02)  # 2% of the estimate's norm
        assert int(got) == 4, scale
        state = E.init(1, 1)
        for J in scale * seq:
            state = E.record(E.update(state, jnp.ones(1), jnp.ones(1)), J, 0.0, 0.02)
        assert int(state.converged_at) == 4
    assert int(E.convergence_iteration(40.0 * seq, 0.05)) == -1  # the absolute eps does not scale


@pytest.mark.parametrize("eps, eps_rel, match", [(-0.1, 0.0, "eps: must be >= 0"),
                                                 (float("nan"), 0.0, "eps: must not be NaN"),
                                                 (0.0, 0.0, "both 0"), (0.1, -1.0, "eps_rel")])
def test_bad_thresholds_raise(eps, eps_rel, match):
    state = E.init(1, 1)
    with pytest.raises(ValueError, match=match):
        E.record(state, jnp.ones((1, 1)), eps, eps_rel)
    with pytest.raises(ValueError, match=match):
        E.convergence_iteration(jnp.ones((2, 1, 1)), eps, eps_rel)
    with pytest.raises(ValueError, match=match):
        sj.self_identify(sj.stateless(lambda k, d: d), jax.random.key(0), 0.1, eps, n_act=1, task_dim=1, iters=2,
                         eps_rel=eps_rel)


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_overflowing_samples_are_rejected_and_bad_dtypes_refused():
    state = E.init(2, 2, dtype=jnp.float32)
    state = E.update(state, jnp.array([3e38, 0.1], jnp.float32), jnp.array([0.1, 0.2], jnp.float32))
    assert int(state.rejected) == 1 and int(state.count) == 0
    assert np.all(np.isfinite(E.initial_guess(state))) and np.all(np.isfinite(sj.refine(state, E.initial_guess(state))))
    for dtype in (jnp.int32, jnp.float16, "bfloat16"):
        with pytest.raises(ValueError, match="dtype: expected float32 or float64"):
            E.init(2, 2, dtype=dtype)
    lists = E.update(E.init(2, 2), [0.1, 0.2], [0.3, 0.4])  # Python lists are arrays too
    assert int(lists.count) == 1
