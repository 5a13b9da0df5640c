"""Constant-memory estimator (issue 14): the closed form of Eq. 14 from the sufficient statistics
S_vv = sum V V^T, S_tv = sum dtheta V^T equals the buffered closed form and numpy least squares,
over a whole selfid.run too; the state size does not grow with the samples; forgetting is
weighted least squares; the rank-revealing pseudo-inverse matches numpy's."""

import functools
import sys

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import selfid_jax as sj
from selfid_jax import baselines as B
from selfid_jax.identify import estimator as E

# the module (selfid_jax.identify.refine is also the re-exported function)
RF = sys.modules["selfid_jax.identify.refine"]


def stream(seed, n, m, K, noise=1e-3, scale=0.05, rank=None):
    """K samples of V = A dtheta (+ noise); with ``rank`` < m the pose changes lie in a tilted subspace."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, n))
    if rank is not None:
        Q, _ = np.linalg.qr(rng.normal(size=(m, m)))
        A = Q[:, :rank] @ Q[:, :rank].T @ A  # pose changes confined to span(Q[:, :rank]), not axis-aligned
    d = rng.uniform(-scale, scale, (K, n))
    V = d @ A.T
    if rank is None:
        V = V + noise * rng.normal(size=(K, m))
    return d, V


def fold(d, V, capacity, forget=1.0):
    """An empty state updated with every sample; ``forget`` is always passed, so both call forms share a program."""
    return _fold(d, V, capacity, forget)


@functools.partial(jax.jit, static_argnums=2)
def _fold(d, V, capacity, forget):
    state = E.init(d.shape[1], V.shape[1], capacity=capacity, forget=forget, dtype=d.dtype)
    return jax.lax.scan(lambda s, x: (E.update(s, *x), None), state, (d, V))[0]


def buffered_reference(d, V, J0):
    """The buffered closed form, numpy only: J0 + (Theta - J0 V) pinv(V) with the samples as columns."""
    d, V, J0 = (np.asarray(x, np.float64) for x in (d, V, J0))
    return J0 + (d.T - J0 @ V.T) @ np.linalg.pinv(V.T)


def rel(a, b):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / max(np.max(np.abs(np.asarray(b))), 1e-300))


@pytest.mark.parametrize("K", [1, pytest.param(2, marks=pytest.mark.slow), 3,
                               pytest.param(4, marks=pytest.mark.slow), 40])
# fewer samples than task dims (m = 3), square, overdetermined
@pytest.mark.slow
def test_statistics_closed_form_equals_buffered_and_numpy_float64(K):
    n, m = 4, 3
    d, V = stream(K, n, m, K)
    state = fold(jnp.asarray(d), jnp.asarray(V), capacity=K)
    rng = np.random.default_rng(100 + K)
    for J0 in (E.initial_guess(state), jnp.asarray(1e3 * rng.standard_cauchy((n, m)))):  # Eq. 13, heavy-tailed
        got = sj.refine(state, J0, method="closed_form")
        np.testing.assert_allclose(got, buffered_reference(d, V, J0), rtol=0, atol=1e-9 * np.abs(got).max())
        theta, Vb, mask = E.samples(state)  # the library's own buffered closed form (SVD pinv)
        np.testing.assert_allclose(got, RF.closed_form(theta, Vb, J0), rtol=0, atol=1e-9 * np.abs(got).max())
        if K >= m:  # one solution: numpy least squares, whatever J0 is
            lstsq = np.linalg.lstsq(V, d, rcond=None)[0].T
            assert rel(got, lstsq) < 1e-9
        else:  # it interpolates the samples and corrects J0 only in their span
            np.testing.assert_allclose(V @ np.asarray(got).T, d, atol=1e-12)
    # the objective from the statistics is the buffered sum of squares
    J = sj.refine(state, E.initial_guess(state), method="closed_form")
    np.testing.assert_allclose(E.objective(state, J), E.buffer_objective(state, J), rtol=1e-7,
                               atol=1e-14 * float(state.s_tt))  # s_tt - 2 <J, S_tv> + ... cancels to ~eps s_tt


@pytest.mark.parametrize("rank", [pytest.param(1, marks=pytest.mark.slow), 2])
def test_rank_deficient_data_with_many_samples(rank):
    """Pose changes confined to a tilted plane or line (a planar task in 3-D): minimum-norm, as buffered."""
    n, m, K = 5, 3, 30
    d, V = stream(rank, n, m, K, rank=rank)
    state = fold(jnp.asarray(d), jnp.asarray(V), capacity=K)
    J0 = E.initial_guess(state)
    got = sj.refine(state, J0, method="closed_form")
    np.testing.assert_allclose(got, buffered_reference(d, V, J0), rtol=0, atol=1e-9 * np.abs(got).max())
    P, N = RF.psd_pinv(state.S_vv)
    assert round(float(jnp.trace(N))) == m - rank


@pytest.mark.parametrize("m", [1, 2, 3, pytest.param(4, marks=pytest.mark.slow), 6])
def test_psd_pinv_matches_numpy(m):
    rng = np.random.default_rng(m)
    for rank in range(m + 1):
        X = rng.normal(size=(m, rank)) * np.geomspace(1, 0.1, max(rank, 1))[:rank]
        S = X @ X.T
        P, N = RF.psd_pinv(jnp.asarray(S))
        np.testing.assert_allclose(P, np.linalg.pinv(S, rcond=1e-10, hermitian=True), rtol=1e-7,
                                   atol=1e-9 * max(np.abs(np.linalg.pinv(S, rcond=1e-10)).max(), 1.0))
        null = np.eye(m) - S @ np.linalg.pinv(S, rcond=1e-10, hermitian=True)
        np.testing.assert_allclose(N, null, atol=1e-9)
        if rank == m:
            assert np.all(np.asarray(N) == 0.0)  # exactly: J0 has no effect once S_vv has full rank


@pytest.mark.slow
class PsdPinvJitVmapTest(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    def test_jit_vmap_and_grad(self):
        rng = np.random.default_rng(0)
        X = rng.normal(size=(4, 3, 2))  # rank 2 in 3-D
        S = jnp.asarray(np.einsum("bik,bjk->bij", X, X))
        out = self.variant(jax.vmap(RF.psd_pinv))(S)
        for b in range(4):
            chex.assert_trees_all_close(jax.tree.map(lambda x, b=b: x[b], out), RF.psd_pinv(S[b]),
                                        rtol=1e-12, atol=1e-14)
        g = jax.grad(lambda s: jnp.sum(RF.statistics_closed_form(s, jnp.ones((2, 3)) @ s, jnp.ones((2, 3)))))(S[0])
        assert np.all(np.isfinite(g))


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_float32_agreement_with_float64_least_squares():
    """Well-conditioned data (cond(A) = 3): float32 statistics within 1e-4 of float64 least squares
    (the issue's goal), as is the buffered float32 closed form (the same Gram form since it stopped taking an SVD)."""
    n, m, K = 6, 3, 50
    rng = np.random.default_rng(0)
    errs_stats, errs_buf = [], []
    for _ in range(8):
        U, _ = np.linalg.qr(rng.normal(size=(m, m)))
        W, _ = np.linalg.qr(rng.normal(size=(n, n)))
        A = (U * np.geomspace(1, 3, m)) @ W[:m]
        d = rng.uniform(-0.03, 0.03, (K, n))
        V = d @ A.T + 1e-4 * rng.normal(size=(K, m))
        ref = np.linalg.lstsq(V, d, rcond=None)[0].T
        state = fold(jnp.asarray(d, jnp.float32), jnp.asarray(V, jnp.float32), capacity=K)
        J0 = E.initial_guess(state)
        errs_stats.append(rel(sj.refine(state, J0, method="closed_form"), ref))
        errs_buf.append(rel(RF.closed_form(*E.samples(state)[:2], J0), ref))
    assert max(errs_stats) < 1e-4
    # the buffered closed form is now the same Gram-form computation (refine.closed_form -> statistics_closed_form
    # on V^T V and theta^T V): equal to float32 round-off, where it was an SVD of the buffer in which J0 cancelled
    assert max(errs_buf) < 1e-4 and abs(max(errs_stats) - max(errs_buf)) < 1e-5


def _arm4():
    """A 4-joint spatial arm (base yaw, three pitch links), position task: n = 4, m = 3."""

    def pose(params, q):
        r = params[0] * jnp.cos(q[1]) + params[1] * jnp.cos(q[1] + q[2]) + params[2] * jnp.cos(q[1] + q[2] + q[3])
        z = params[0] * jnp.sin(q[1]) + params[1] * jnp.sin(q[1] + q[2]) + params[2] * jnp.sin(q[1] + q[2] + q[3])
        return jnp.stack([r * jnp.cos(q[0]), r * jnp.sin(q[0]), z])

    return sj.from_pose_fn(pose, 4, task_dim=3, q_low=-3.0, q_high=3.0, dq_max=0.2, m_a=0.05,
                           params=jnp.array([0.4, 0.3, 0.2]), name="arm4")


EPS = 0.5  # rad/m (|J| ~ 13 rad/m): reached at iteration 8 of 10


@pytest.mark.slow
@pytest.mark.parametrize("stop", [False, True])
def test_selfid_run_identical_to_buffered_closed_form(stop):
    """Every estimate of a whole selfid.run (no buffer: capacity 0 by default) equals the buffered closed
    form replayed on its samples with numpy, and the convergence iteration is the same."""
    system = _arm4()
    q0 = jnp.array([0.3, 0.4, 0.6, -0.5])
    run = jax.jit(lambda k: sj.identify.algorithm.run(system, k, q0, iters=10, eps=EPS, pose_noise=1e-5,
                                          stop_at_convergence=stop))
    res = run(jax.random.key(0))
    assert res.state.dtheta_buf.shape == (0, 4)
    state = E.init(4, 3, capacity=10)
    ref = []
    for t in range(10):
        state = E.update(state, res.dtheta[t], res.V[t])
        ref.append(buffered_reference(res.dtheta[: t + 1], res.V[: t + 1], E.initial_guess(state)))
        if stop and int(res.converged_at) == t + 1:
            ref += [ref[-1]] * (9 - t)
            break
    ref = np.stack(ref)
    np.testing.assert_allclose(res.estimates, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
    conv = int(E.convergence_iteration(jnp.asarray(ref), EPS))
    assert int(res.converged_at) == conv and conv > 0


@pytest.mark.slow
def test_state_size_is_independent_of_the_number_of_samples():
    def leaves(state):
        return [(x.shape, x.dtype) for x in jax.tree.leaves(state)]

    d, V = stream(0, 3, 3, 60)  # the sizes of the other tests' folds (5 and 60 samples): their programs
    few = fold(jnp.asarray(d[:5]), jnp.asarray(V[:5]), capacity=0)
    many = fold(jnp.asarray(d), jnp.asarray(V), capacity=0)
    assert leaves(few) == leaves(many) == leaves(E.init(3, 3, capacity=0))
    # a whole self-ID run: the same state whatever the number of iterations
    system = _arm4()
    shapes = [leaves(jax.eval_shape(
        lambda k, it=it: sj.identify.algorithm.run(system, k, jnp.zeros(4), iters=it, eps=1e-3).state,
        jax.random.key(0))) for it in (10, 1000)]
    assert shapes[0] == shapes[1]
    # the paper's estimator in the ablation protocol keeps no buffer unless its magnitude variant needs one
    assert B.ours().init(4, 3, capacity=64).dtheta_buf.shape == (0, 4)
    assert B.direct().init(4, 3, capacity=64).est.dtheta_buf.shape == (0, 4)
    assert B.ours(magnitude="median").init(4, 3, capacity=64).dtheta_buf.shape == (64, 4)


@pytest.mark.slow
def test_forgetting_is_weighted_least_squares_and_follows_a_jump():
    """forget < 1: the closed form is numpy's weighted least squares (weights forget^(K-k)); after the
    Jacobian jumps (a grasp that slips) it converges to the new one, forget = 1 stays between the two."""
    n, m, K = 3, 3, 60
    rng = np.random.default_rng(3)
    A1, A2 = rng.normal(size=(m, n)) + 2 * np.eye(3), rng.normal(size=(m, n)) + 2 * np.eye(3)
    d = rng.uniform(-0.05, 0.05, (K, n))
    V = np.concatenate([d[:30] @ A1.T, d[30:] @ A2.T]) + 1e-5 * rng.normal(size=(K, m))
    lam = 0.8
    state = fold(jnp.asarray(d), jnp.asarray(V), capacity=0, forget=lam)
    J = np.asarray(sj.refine(state, E.initial_guess(state), method="closed_form"))
    w = np.sqrt(lam ** np.arange(K - 1, -1, -1))[:, None]
    np.testing.assert_allclose(J, np.linalg.lstsq(w * V, w * d, rcond=None)[0].T, rtol=1e-9, atol=1e-12)
    never = fold(jnp.asarray(d), jnp.asarray(V), capacity=0)
    J_never = np.asarray(sj.refine(never, E.initial_guess(never), method="closed_form"))
    truth = np.linalg.inv(A2)
    assert rel(J, truth) < 1e-2 < 0.1 < rel(J_never, truth)


@pytest.mark.slow
def test_rejected_and_overflowing_samples_leave_the_state_unchanged():
    f32 = jnp.float32
    update = jax.jit(E.update)
    state = fold(*(jnp.asarray(x, f32) for x in stream(1, 3, 2, 4)), capacity=2, forget=0.5)
    for d, v in ((jnp.array([jnp.nan, 0.0, 1.0]), jnp.ones(2)), (jnp.zeros(3), jnp.ones(2)),
                 (jnp.ones(3), jnp.array([-1.5e19, 1.5e19]))):  # |V|^2 = 4.5e38 overflows float32
        new = update(state, jnp.asarray(d, f32), jnp.asarray(v, f32))
        chex.assert_trees_all_equal(new, state._replace(rejected=state.rejected + 1))
        state = new
    # one large sample fits, a second one would overflow the float32 sums: rejected, all stays finite
    v = jnp.array([1.5e19, 0.0], f32)  # |V|^2 = 2.25e38 < 3.4e38
    big = update(E.init(3, 2, capacity=2, dtype=f32), jnp.ones(3, f32), v)  # forget = 1 (traced: same program)
    twice = update(big, jnp.ones(3, f32), v)
    assert int(big.count) == 1 and int(twice.count) == 1 and int(twice.rejected) == 1
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(twice._replace(last_deltas=jnp.zeros(2))))


@pytest.mark.slow
def test_buffer_free_state_refuses_sample_based_refinements():
    state = fold(*(jnp.asarray(x) for x in stream(2, 3, 3, 5)), capacity=0)
    J0 = E.initial_guess(state)
    for kwargs in ({"method": "slsqp"}, {"method": "optax", "loss": "huber"}):
        with pytest.raises(ValueError, match="capacity=0"):
            sj.refine(state, J0, **kwargs)
    for name in ("median", "weighted", "kalman"):
        with pytest.raises(ValueError, match="capacity=0"):
            sj.identify.magnitude.get(name)(state)
    # the L2 gradient refinement reads the statistics: it reaches the closed form without samples
    np.testing.assert_allclose(sj.refine(state, J0, method="optax"), sj.refine(state, J0, method="closed_form"),
                               rtol=1e-7, atol=1e-9)
