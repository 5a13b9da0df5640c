"""DLS IK, the feasibility-projected DLS and the base-yaw workaround against scipy, numpy and closed forms."""

import jax

jax.config.update("jax_enable_x64", True)

import chex  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.optimize import lsq_linear, minimize_scalar  # noqa: E402

from selfid_jax.control import dls  # noqa: E402
from selfid_jax.identify import algorithm as selfid  # noqa: E402
from selfid_jax.systems.ets import ARM5_HOME, arm5, from_ets  # noqa: E402

# Seed 004's failure case: tool horizontal (q2 + q3 + q4 = pi/2) at radius 0.33 m, then 100 mm sideways at fixed
# orientation.
Q_SIDE = np.array([0.0, 0.6, 0.717, np.pi / 2 - 1.317, 0.0])
SIDEWAYS = 0.1  # m


@pytest.fixture(scope="module")
def arm():
    return arm5(task_dim=6)


# ------------------------------------------------------------------ the box-constrained step
@pytest.mark.slow
def test_box_qp_matches_scipy_bvls():
    """Random DLS-shaped problems (``H = A^T A``, ``A = [Wx J; lambda I]``) with held variables, against BVLS."""
    rng = np.random.default_rng(0)
    n, m, k = 5, 6, 24
    A = np.concatenate([rng.normal(size=(k, m, n)), 10 ** rng.uniform(-2, 0, (k, 1, 1)) * np.eye(n)], axis=1)
    b = np.concatenate([rng.normal(size=(k, m)), np.zeros((k, n))], axis=1)
    lo, hi = -rng.uniform(0, 0.5, (k, n)), rng.uniform(0, 0.5, (k, n))
    fixed = rng.random((k, n)) < 0.2  # a held joint: lower = upper = 0
    lo[fixed] = hi[fixed] = 0.0
    lo[0], hi[0], fixed[0] = -np.inf, np.inf, False  # no bounds at all: the unconstrained minimiser
    H, g = np.einsum("kri,krj->kij", A, A), np.einsum("kri,kr->ki", A, b)
    x = np.asarray(jax.jit(jax.vmap(dls.box_qp))(H, g, lo, hi))
    np.testing.assert_allclose(x[0], np.linalg.solve(H[0], g[0]), rtol=1e-10)
    n_active = 0
    for i in range(1, k):
        free = ~fixed[i]
        ref = np.zeros(n)
        ref[free] = lsq_linear(A[i][:, free], b[i], bounds=(lo[i, free], hi[i, free]), method="bvls", tol=1e-14).x
        np.testing.assert_allclose(x[i], ref, atol=1e-9)
        assert np.all(x[i] >= lo[i]) and np.all(x[i] <= hi[i])
        n_active += int(np.sum(np.isclose(ref, lo[i]) | np.isclose(ref, hi[i])))
    assert n_active > 2 * k  # the bounds were really active


# ------------------------------------------------------------------ one step
@pytest.mark.slow
def test_dls_step_matches_normal_equations_and_projection(arm):
    J = np.asarray(arm.jacobian(jnp.asarray(ARM5_HOME)))  # 6x5, rank 5
    e = np.random.default_rng(1).normal(size=6) * 0.01
    step = jax.jit(dls.dls_step, static_argnames="method")
    for L in (1.0, 0.1):
        W = np.diag([1, 1, 1, L**2, L**2, L**2])
        lam = 0.01
        prm = dls.DLSParams(damping=lam, rot_weight=L)
        want = np.linalg.solve(J.T @ W @ J + lam**2 * np.eye(5), J.T @ W @ e)
        np.testing.assert_allclose(step(J, e, prm, method="dls"), want, rtol=1e-10)
        P = J @ np.linalg.pinv(J)  # J J^+
        want_p = np.linalg.solve(J.T @ W @ J + lam**2 * np.eye(5), J.T @ W @ P @ e)
        np.testing.assert_allclose(step(J, e, prm, method="projected"), want_p, rtol=1e-9)
    same = dls.DLSParams(rot_weight=1.0)  # W = I: J^T J J^+ = J^T, the projection is a no-op
    np.testing.assert_allclose(step(J, e, same, method="projected"), step(J, e, same, method="dls"),
                               rtol=1e-9)
    weighted = dls.DLSParams(rot_weight=0.1)  # W != I: it is not
    diff = step(J, e, weighted, method="projected") - step(J, e, weighted, method="dls")
    assert np.linalg.norm(diff) > 1e-3 * np.linalg.norm(step(J, e, weighted, method="dls"))
    tiny = dls.DLSParams(damping=1e-9, rot_weight=0.1)  # lambda -> 0: the projected step is J^+ e, whatever W
    np.testing.assert_allclose(step(J, e, tiny, method="projected"), np.linalg.pinv(J) @ e, rtol=1e-6)


# ------------------------------------------------------------------ seed 004's failure case and its workaround
@pytest.mark.slow
def test_sideways_at_fixed_orientation_achieves_about_ten_percent(arm):
    """Projected DLS settles at the unweighted least-squares compromise: 9.97 mm of 100 mm at r = 0.33 m.

    Reference: the arm can reach any radius and height at its tool pitch, so a base turn ``psi`` costs
    ``psi`` of orientation and leaves ``|r sin psi - d cos psi|`` of position error; the compromise
    minimises their sum of squares (W = I, which the projection imposes whatever the weights).
    """
    p0, R0 = arm.pose(jnp.asarray(Q_SIDE))
    r = float(p0[0])
    psi = minimize_scalar(lambda a: (r * np.sin(a) - SIDEWAYS * np.cos(a)) ** 2 + a**2, bounds=(0, 1),
                          method="bounded", options=dict(xatol=1e-12)).x
    y_ref = (r * np.cos(psi) + SIDEWAYS * np.sin(psi)) * np.sin(psi)
    target = p0 + jnp.array([0.0, SIDEWAYS, 0.0])
    solve = jax.jit(lambda prm: dls.ik(arm, jnp.asarray(Q_SIDE), target, R0, prm, max_iters=300))
    for L in (0.1, 1.0):  # the projection makes the weights irrelevant
        res = solve(dls.DLSParams(rot_weight=L))
        y = float(arm.pose(res.q)[0][1] - p0[1])
        assert abs(y - y_ref) < 1e-6, (L, y, y_ref)
        assert not bool(res.success)
    assert 0.09 < y_ref / SIDEWAYS < 0.11  # "about 10% of the command"
    np.testing.assert_allclose(float(res.rotation_error), psi, atol=1e-6)
    # plain weighted DLS (no projection) with rotation weighted as 0.1 m trades more orientation for position
    res_w = jax.jit(lambda: dls.ik(arm, jnp.asarray(Q_SIDE), target, R0, dls.DLSParams(rot_weight=0.1),
                                   method="dls", max_iters=300))()
    y_w = float(arm.pose(res_w.q)[0][1] - p0[1])
    assert 0.85 * SIDEWAYS < y_w < SIDEWAYS and np.degrees(float(res_w.rotation_error)) > 10.0


@pytest.mark.slow
def test_base_yaw_workaround_moves_sideways_and_gives_up_yaw(arm):
    """Base to atan2(y*, x*), DLS on the rest: 99.9 of 100 mm, orientation off by the base turn atan(0.1/0.33)."""
    p0, R0 = arm.pose(jnp.asarray(Q_SIDE))
    target = p0 + jnp.array([0.0, SIDEWAYS, 0.0])
    res = jax.jit(lambda: dls.base_yaw_ik(arm, jnp.asarray(Q_SIDE), target, R0))()
    p, _ = arm.pose(res.q)
    assert bool(res.success) and float(res.position_error) < dls.DLSParams().tol
    assert float(p[1] - p0[1]) > 0.0995
    np.testing.assert_allclose(float(res.rotation_error), np.arctan2(SIDEWAYS, float(p0[0])), atol=1e-4)
    np.testing.assert_allclose(float(res.q[0]), np.arctan2(SIDEWAYS, float(p0[0])), atol=1e-12)
    assert np.all(res.q >= arm.q_low) and np.all(res.q <= arm.q_high)


# ------------------------------------------------------------------ joint limits
@pytest.mark.slow
def test_joint_limits_hold_and_bind():
    """A planar 3R arm with a tight elbow limit: the box step stops the elbow at its bound and still gets closer."""
    s = from_ets(["Rz", "tx(0.3)", "Rz", "tx(0.3)", "Rz", "tx(0.1)"], task_dim=3, q_low=[-3.0, -0.2, -3.0],
                 q_high=[3.0, 0.2, 3.0])
    q0 = jnp.array([0.3, 0.0, 0.2])
    target = jnp.array([0.2, 0.3, 0.0])  # needs the elbow folded far beyond 0.2 rad
    res = jax.jit(lambda: dls.ik(s, q0, target, None, dls.DLSParams(), method="dls", max_iters=300))()
    assert np.all(np.asarray(res.q) >= np.asarray(s.q_low) - 1e-15)
    assert np.all(np.asarray(res.q) <= np.asarray(s.q_high) + 1e-15)
    assert abs(abs(float(res.q[1])) - 0.2) < 1e-12  # the elbow rests on a limit
    assert float(res.position_error) < float(jnp.linalg.norm(target - s.pose(q0)[0]))


# ------------------------------------------------------------------ success rates
@pytest.mark.slow
def test_success_rate_on_random_reachable_targets_with_and_without_restarts(arm):
    """Pose targets of 100 random configurations: 69% from home, 97% with 8 restarts (probe: 78.6% / 96.9%).

    100 targets, not 200 (whose rates were 73.5% / 98.5%): a failing lane runs the batched solve to ``max_iters``,
    so the test's time is mostly this runtime. The keys are fixed, so the rates are the measured ones."""
    n = 100
    qs = jax.random.uniform(jax.random.key(1), (n, 5), minval=arm.q_low, maxval=arm.q_high)
    P, R = jax.vmap(arm.pose)(qs)
    home = jnp.asarray(ARM5_HOME)
    prm = dls.DLSParams()
    one = jax.jit(jax.vmap(lambda p, R: dls.ik(arm, home, p, R, prm, max_iters=200)))(P, R)
    keys = jax.random.split(jax.random.key(2), n)
    many = jax.jit(jax.vmap(lambda k, p, R: dls.ik_restarts(arm, k, home, p, R, prm, restarts=8, max_iters=200)))(
        keys, P, R)
    rate_one, rate_many = float(one.success.mean()), float(many.success.mean())
    assert 0.6 < rate_one < 0.9, rate_one
    assert rate_many > 0.95 and rate_many > rate_one + 0.1, rate_many
    ok = np.asarray(many.success)
    assert np.all(np.asarray(many.position_error)[ok] <= prm.tol)
    assert np.all(np.asarray(many.rotation_error)[ok] <= prm.rot_tol)
    assert np.all(np.asarray(many.q) >= np.asarray(arm.q_low)) and np.all(np.asarray(many.q) <= np.asarray(arm.q_high))


@pytest.mark.slow
def test_both_controllers_with_a_self_identified_inverse_jacobian():
    """Self-ID of the position task (Algorithm 1), then DLS / base-yaw IK with J = Jinv_hat^+ held fixed."""
    s = arm5(task_dim=3)
    # one compiled program for self-ID and the pose after it (op by op it was dozens of small compilations)
    sid, (p1, _) = jax.jit(lambda k, q: (r := selfid.run(s, k, q, iters=30, eps=0.5), s.pose(r.env)))(
        jax.random.key(0), jnp.asarray(ARM5_HOME))
    q1 = sid.env
    n = 64
    d = jax.random.normal(jax.random.key(3), (n, 3))
    d = d / jnp.linalg.norm(d, axis=1, keepdims=True) * jax.random.uniform(jax.random.key(4), (n, 1), minval=0.01,
                                                                            maxval=0.05)
    targets = p1[None, :] + d
    positions = jax.jit(jax.vmap(lambda q: s.pose(q)[0]))
    for solver in (dls.ik, dls.base_yaw_ik):
        for method in dls.METHODS:
            res = jax.jit(jax.vmap(lambda t, solver=solver, method=method: solver(
                s, q1, t, None, dls.DLSParams(), method=method, jinv=sid.estimate)))(targets)
            assert float(res.success.mean()) >= 0.95, (solver.__name__, method, float(res.success.mean()))
            # the reported error is measured on the arm, not on the estimate
            p = positions(res.q)
            np.testing.assert_allclose(res.position_error, np.linalg.norm(np.asarray(targets) - np.asarray(p), axis=1),
                                       atol=1e-12)


# ------------------------------------------------------------------ input checks and tracing
@pytest.mark.parametrize(
    "call, match",
    [
        (lambda s: dls.ik(s, jnp.zeros(4), jnp.zeros(3)), r"q0: expected shape \(5,\)"),
        (lambda s: dls.ik(s, jnp.zeros(5), jnp.zeros(2)), r"target_p: expected shape \(3,\)"),
        (lambda s: dls.ik(s, jnp.zeros(5), jnp.zeros(3), method="newton"), "method must be one of"),
        (lambda s: dls.ik(s, jnp.zeros(5), jnp.zeros(3), None, dls.DLSParams(damping=-1.0)), "params.damping"),
        (lambda s: dls.ik(s, jnp.zeros(5), jnp.zeros(3), jnp.eye(3), jinv=jnp.zeros((5, 3))), "position targets only"),
        (lambda s: dls.ik(s, jnp.zeros(5), jnp.zeros(3), jinv=jnp.zeros((3, 5))), r"jinv: expected shape \(5, 3\)"),
        (lambda s: dls.ik(s, jnp.zeros(5), jnp.zeros(3), max_iters=0), "max_iters"),
        (lambda s: dls.ik_restarts(s, jax.random.key(0), jnp.zeros(5), jnp.zeros(3), restarts=0), "restarts"),
        (lambda s: dls.dls_step(jnp.zeros((4, 5)), jnp.zeros(4)), r"J: expected shape \(3, n\) or \(6, n\)"),
        (lambda s: dls.box_qp(jnp.eye(3), jnp.zeros(3), jnp.zeros(2), jnp.zeros(3)), r"lower: expected shape \(3,\)"),
    ],
)
def test_bad_input_is_named(arm, call, match):
    with pytest.raises(ValueError, match=match):
        call(arm)


@pytest.mark.slow
class TestTracing(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    def test_jit_and_eager_agree(self):
        s = arm5(task_dim=6)
        q0 = jnp.asarray(ARM5_HOME)
        p, R = s.pose(jnp.array([0.2, 0.5, 0.8, 0.5, 0.1]))
        got = self.variant(lambda q, p, R: dls.ik(s, q, p, R, max_iters=50))(q0, p, R)
        want = jax.jit(lambda q, p, R: dls.ik(s, q, p, R, max_iters=50))(q0, p, R)
        chex.assert_trees_all_close(got, want, atol=1e-12)
        assert bool(got.success)

    def test_swept_params_do_not_retrace(self):
        s = arm5(task_dim=3)
        q0 = jnp.asarray(ARM5_HOME)
        target = s.pose(jnp.array([0.3, 0.5, 0.7, 0.4, 0.0]))[0]

        @jax.jit
        @chex.assert_max_traces(n=1)
        def solve(prm):
            return dls.ik(s, q0, target, None, prm, max_iters=100)

        for lam in (0.005, 0.01, 0.05):
            assert bool(solve(dls.DLSParams(damping=lam, tol=1e-4)).success)
        batch = dls.DLSParams(*(jnp.full((3,), v) for v in dls.DLSParams(tol=1e-4)))
        res = jax.jit(jax.vmap(lambda prm: dls.ik(s, q0, target, None, prm, max_iters=100)))(batch)
        assert res.q.shape == (3, 5) and bool(res.success.all())
