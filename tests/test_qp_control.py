"""The Eq. 10-11 QP (qp_control.solve) against scipy on random small problems: SLSQP where the task step
is reachable inside the box, bounded least squares (lsq_linear) where it is not; vmap == loop; shape
errors; and the constrained controller completes a 2-link star with the true Jacobian."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import lsq_linear, minimize

from selfid_jax import control
from selfid_jax.control import paths
from selfid_jax.control import qp as qp_control
from selfid_jax.systems.two_link import two_link

solve = jax.jit(jax.vmap(qp_control.solve))


def problems(seed, count, n, m, reachable):
    """Random (J, v, lo, hi, w): reachable -> v = J da* for a da* strictly inside the box; else v far outside."""
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(count, m, n))
    lo = -rng.uniform(0.05, 1.0, (count, n))
    hi = rng.uniform(0.05, 1.0, (count, n))
    w = rng.uniform(0.2, 5.0, (count, n))
    if reachable:
        v = np.einsum("bmn,bn->bm", J, lo + rng.uniform(0.1, 0.9, (count, n)) * (hi - lo))
    else:
        v = 20.0 * rng.normal(size=(count, m))
    return J, v, lo, hi, w


def slsqp(J, v, lo, hi, w):
    res = minimize(lambda x: np.sum(w * x * x), np.clip(np.zeros_like(lo), lo, hi), jac=lambda x: 2 * w * x,
                   method="SLSQP", bounds=list(zip(lo, hi)),
                   constraints=[{"type": "eq", "fun": lambda x: J @ x - v, "jac": lambda x: J}],
                   options={"ftol": 1e-15, "maxiter": 500})
    assert res.success, res.message
    return res.x


@pytest.mark.parametrize("n,m", [(6, 3), pytest.param(2, 2, marks=pytest.mark.slow),
                                 pytest.param(4, 2, marks=pytest.mark.slow)])
def test_reachable_steps_match_slsqp(n, m):
    J, v, lo, hi, w = problems(n + m, 30, n, m, reachable=True)
    out = solve(J, v, lo, hi, w)
    ref = np.stack([slsqp(*args) for args in zip(J, v, lo, hi, w)])
    assert np.all(np.asarray(out.da) >= lo - 1e-12) and np.all(np.asarray(out.da) <= hi + 1e-12)
    np.testing.assert_array_less(np.asarray(out.residual) / np.linalg.norm(v, axis=1), 1e-7)
    np.testing.assert_allclose(out.da, ref, atol=1e-6)
    # the weighted effort is SLSQP's or lower
    effort = np.sum(w * np.asarray(out.da) ** 2, axis=1)
    assert np.all(effort <= np.sum(w * ref**2, axis=1) + 1e-9)


@pytest.mark.parametrize("n,m", [(3, 3), pytest.param(2, 2, marks=pytest.mark.slow),
                                 pytest.param(5, 3, marks=pytest.mark.slow),
                                 pytest.param(6, 2, marks=pytest.mark.slow)])
def test_unreachable_steps_give_the_box_least_squares_step(n, m):
    J, v, lo, hi, w = problems(10 * n + m, 20, n, m, reachable=False)
    out = solve(J, v, lo, hi, w)
    best = np.array([lsq_linear(*a, bounds=(lb, ub), tol=1e-14).cost for *a, lb, ub in zip(J, v, lo, hi)])
    np.testing.assert_allclose(0.5 * np.asarray(out.residual) ** 2, best, rtol=1e-6, atol=1e-9)
    if n <= m:  # the least-squares step is unique
        ref = np.stack([lsq_linear(a, b, bounds=(lb, ub), tol=1e-14).x for a, b, lb, ub in zip(J, v, lo, hi)])
        # Round-off of the dual form: a free actuator's da = J^T lam / w cancels terms J_ij lam_i / w_j of up
        # to 5e11 on the worst problem (|lam| ~ residual / ridge ~ 1e12), an error of up to 5.5e-5 at float64's
        # 1.1e-16; measured 1.0e-6 at XLA's shipped level and 5.5e-6 at LLVM level 0 (tests/conftest.py).
        np.testing.assert_allclose(out.da, ref, atol=2e-5)


@pytest.mark.slow
def test_vmap_equals_one_by_one_and_checks():
    J, v, lo, hi, w = problems(7, 3, 3, 2, reachable=True)
    out = solve(J, v, lo, hi, w)
    one = jax.jit(qp_control.solve)
    for i in range(3):
        np.testing.assert_allclose(out.da[i], one(J[i], v[i], lo[i], hi[i], w[i]).da, atol=1e-12)
    with pytest.raises(ValueError, match=r"v: expected shape \(2,\), got \(3,\)"):
        qp_control.solve(J[0], np.zeros(3), lo[0], hi[0])
    with pytest.raises(ValueError, match="weights: must be > 0"):
        qp_control.solve(J[0], v[0], lo[0], hi[0], -1.0)
    bad = one(J[0] * np.nan, v[0], lo[0], hi[0], w[0])
    np.testing.assert_array_equal(bad.da, np.zeros(3))


@pytest.mark.slow
def test_constrained_controller_with_the_true_jacobian_completes_a_star():
    arm = two_link()
    path = paths.star(size=0.2, dim=2)
    ctrl = control.ControllerParams(max_step=0.01, tol=0.002)
    q0 = jnp.array([0.3, 1.4])

    def true_model(_, q):
        return arm.jacobian(q), jnp.zeros(2)

    res, _ = jax.jit(lambda q: qp_control.follow(arm, true_model, (), path, q, ctrl, steps=435))(q0)
    ref = control.follow(arm, control.true_inverse(arm), path, q0, ctrl, steps=435)
    assert float(res.completion) == 1.0 and not bool(res.failed)
    assert abs(float(res.mean_error) - float(ref.mean_error)) < 1e-6  # same steps: the box never binds here
