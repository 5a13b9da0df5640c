"""Refinement (Eq. 14): exact recovery, agreement of the three methods, options, grad, jit/vmap."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import selfid_jax as sj
from selfid_jax.identify import estimator as E


def make_state(rng, J, K, noise=0.0, capacity=32, scale=0.05):
    """State holding K samples of the linear system V = J dtheta (+ noise)."""
    m, n = J.shape
    d = rng.uniform(-scale, scale, (K, n))
    V = d @ J.T + noise * rng.normal(size=(K, m))
    state = E.init(n, m, capacity=capacity)
    update = jax.jit(E.update)
    for a, b in zip(d, V):
        state = update(state, a, b)
    return state, d, V


def rel_objective_gap(state, J, J_ref):
    """|f(J) - f(J_ref)| / f(J_ref), with f(J_ref) floored at 1e-12 sum ||dtheta||^2."""
    theta, _, _ = E.samples(state)
    floor = 1e-12 * float(jnp.sum(theta**2))
    f, f_ref = float(E.objective(state, J)), float(E.objective(state, J_ref))
    return abs(f - f_ref) / max(f_ref, floor)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["closed_form", "optax"])
@pytest.mark.parametrize("n", [2, 6])
def test_exact_recovery_of_linear_system(method, n):
    rng = np.random.default_rng(n)
    J = rng.normal(size=(n, n)) + 2 * np.eye(n)  # invertible
    state, _, _ = make_state(rng, J, K=n + 2)
    Jinv = sj.refine(state, sj.initial_guess(state), method=method)
    np.testing.assert_allclose(Jinv, np.linalg.pinv(J), rtol=1e-5, atol=1e-5 * np.abs(np.linalg.pinv(J)).max())


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
@pytest.mark.parametrize("K", [3, 20])  # fewer samples than task dims, and overdetermined
def test_optax_and_slsqp_agree_with_closed_form(K):
    rng = np.random.default_rng(K)
    n = m = 6
    for _ in range(3):
        J = rng.normal(size=(m, n))
        state, _, _ = make_state(rng, J, K=K, noise=1e-3)
        J0 = sj.initial_guess(state)
        Jc = sj.refine(state, J0, method="closed_form")
        Jo = sj.refine(state, J0, method="optax")
        Js = sj.refine(state, J0, method="slsqp")
        if K >= m:
            assert rel_objective_gap(state, Jo, Jc) <= 1e-6
            assert rel_objective_gap(state, Js, Jc) <= 1e-6
        else:
            # f* = 0 with fewer samples than task dims, so compare the solutions: both must land
            # on the minimum-norm correction of J0 (SLSQP, started at J0, does too, to its ftol)
            np.testing.assert_allclose(Jo, Jc, atol=1e-6 * float(jnp.abs(Jc).max()))
            np.testing.assert_allclose(Js, Jc, atol=1e-6 * float(jnp.abs(Jc).max()))
        # also the unpreconditioned Nesterov path, given enough steps
        Jn = sj.refine(state, J0, method="optax", precondition=False, steps=3000)
        assert rel_objective_gap(state, Jn, Jc) <= 1e-3


@pytest.mark.slow
def test_closed_form_is_minimum_norm_correction():
    rng = np.random.default_rng(7)
    state, d, V = make_state(rng, rng.normal(size=(4, 4)), K=2)
    J0 = rng.normal(size=(4, 4))
    J = np.asarray(sj.refine(state, J0, method="closed_form"))
    np.testing.assert_allclose(V @ J.T, d, atol=1e-12)  # interpolates the samples
    # the correction lies in the row space of the samples: J - J0 = A V
    A = (J - J0) @ np.linalg.pinv(V)
    np.testing.assert_allclose(A @ V, J - J0, atol=1e-10)


@pytest.mark.slow
def test_ridge_closed_form_matches_optax_and_normal_equations():
    rng = np.random.default_rng(8)
    state, d, V = make_state(rng, rng.normal(size=(3, 3)), K=10, noise=1e-2)
    J0 = jnp.asarray(rng.normal(size=(3, 3)))
    ridge = 1e-3
    expected = (d.T @ V + ridge * np.asarray(J0)) @ np.linalg.inv(V.T @ V + ridge * np.eye(3))
    np.testing.assert_allclose(sj.refine(state, J0, method="closed_form", ridge=ridge), expected, rtol=1e-8)
    np.testing.assert_allclose(sj.refine(state, J0, method="optax", ridge=ridge), expected, rtol=1e-6)


@pytest.mark.slow
def test_huber_resists_outliers():
    rng = np.random.default_rng(9)
    J = rng.normal(size=(3, 3)) + 2 * np.eye(3)
    state, d, V = make_state(rng, J, K=30, noise=1e-4)
    for _ in range(3):  # tracker outliers: motion reported with the wrong sign
        bad = rng.uniform(-0.05, 0.05, 3)
        state = E.update(state, jnp.asarray(bad), jnp.asarray(-J @ bad))
    truth = np.linalg.inv(J)
    J0 = sj.initial_guess(state)
    err_l2 = np.abs(sj.refine(state, J0, method="closed_form") - truth).max()
    err_hub = np.abs(sj.refine(state, J0, method="optax", loss="huber", huber_delta=1e-3, steps=300) - truth).max()
    assert err_hub < 0.1 * err_l2


@pytest.mark.slow
def test_sign_projection_respects_signed_inverse_jacobian():
    rng = np.random.default_rng(10)
    state, _, _ = make_state(rng, rng.normal(size=(4, 4)), K=3, noise=1e-2)
    S = np.asarray(sj.signed_inverse_jacobian(state))
    J = np.asarray(sj.refine(state, sj.initial_guess(state), method="optax", sign_project=True, steps=200))
    assert np.all(S * J >= 0)
    assert E.objective(state, J) <= E.objective(state, sj.initial_guess(state))


def test_slsqp_is_eager_only():
    state = E.init(2, 2)
    with pytest.raises(ValueError, match="slsqp"):
        jax.jit(lambda s: sj.refine(s, jnp.zeros((2, 2)), method="slsqp"))(state)


@pytest.mark.slow
def test_grad_through_refinement_wrt_samples_is_finite():
    rng = np.random.default_rng(11)
    d = jnp.asarray(rng.uniform(-0.05, 0.05, (4, 3)))
    V = d @ jnp.asarray(rng.normal(size=(3, 3))).T
    target = jnp.asarray(rng.normal(size=(3, 3)))

    def loss(d, V, method):
        state = E.init(3, 3, capacity=4)
        for k in range(4):
            state = E.update(state, d[k], V[k])
        return jnp.sum((sj.refine(state, sj.initial_guess(state), method=method, steps=20) - target) ** 2)

    for method in ("closed_form", "optax"):
        gd, gV = jax.jit(jax.grad(loss, argnums=(0, 1)), static_argnums=2)(d, V, method)
        assert np.all(np.isfinite(gd)) and np.all(np.isfinite(gV))
        assert np.abs(gV).max() > 0


class RefineJitVmapTest(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_jit_equals_eager(self):
        rng = np.random.default_rng(12)
        state, _, _ = make_state(rng, rng.normal(size=(3, 3)), K=6, noise=1e-3)
        J0 = sj.initial_guess(state)
        for method in ("closed_form", "optax"):
            got = self.variant(lambda s, j, method=method: sj.refine(s, j, method=method))(state, J0)
            np.testing.assert_allclose(got, sj.refine(state, J0, method=method), rtol=1e-9, atol=1e-12)

    @pytest.mark.slow
    def test_vmap_equals_loop_and_no_retrace_over_ridge(self):
        rng = np.random.default_rng(13)
        states = [make_state(rng, rng.normal(size=(3, 2)), K=5, noise=1e-3)[0] for _ in range(3)]
        batched = jax.tree.map(lambda *x: jnp.stack(x), *states)

        @jax.jit
        @chex.assert_max_traces(n=1)
        def run(states, ridge):
            return jax.vmap(lambda s: sj.refine(s, sj.initial_guess(s), method="optax", ridge=ridge))(states)

        one = jax.jit(lambda s, ridge: sj.refine(s, sj.initial_guess(s), method="optax", ridge=ridge),
                      static_argnames="ridge")  # the loop's ridge stays a Python number, as in an eager call
        for ridge in (0.0, 1e-4, 1e-2):
            out = run(batched, ridge)
            for b, s in enumerate(states):
                np.testing.assert_allclose(out[b], one(s, ridge=ridge), rtol=1e-9)


@pytest.mark.slow
def test_negative_huber_delta_and_ridge_raise():
    state = E.update(E.init(2, 2), jnp.array([0.1, 0.2]), jnp.array([0.3, -0.1]))
    J0 = E.initial_guess(state)
    with pytest.raises(ValueError, match="huber_delta: must be > 0"):
        sj.refine(state, J0, loss="huber", huber_delta=-1.0)
    with pytest.raises(ValueError, match="ridge: must be >= 0"):
        sj.refine(state, J0, method="closed_form", ridge=-0.5)
