"""Stewart Hand (selfid_jax.systems.hands): kinematic Newton solve, closed-form inverse Jacobian,
native MuJoCo and MJX settling, NaN outside the safe range, self-ID and path following (float64)."""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import selfid_jax as sj
from selfid_jax.systems.hands import settle
from selfid_jax.systems.hands.stewart import (
    STEWART_HALF_WIDTH,
    STEWART_SETTLE_STEPS,
    STEWART_XML,
    stewart_hand,
    stewart_home,
    stewart_inverse_jacobian,
    stewart_native_batch,
)

HOME = stewart_home()


@pytest.fixture(scope="module")
def hand():
    return stewart_hand()


def _box(seed, k, half_width=STEWART_HALF_WIDTH):
    """``(k, 6)`` random asymmetric leg lengths in the sampling box around home (m)."""
    return HOME + np.random.default_rng(seed).uniform(-half_width, half_width, (k, 6))


def _pose_err(p, R, p_ref, R_ref):
    return float(np.max(np.abs(np.asarray(p) - np.asarray(p_ref)))), float(np.max(np.abs(np.asarray(R) - R_ref)))


@pytest.mark.slow
def test_layout_read_from_mjcf(hand):
    """a_i are the ball-joint anchors, b_i agree with the connect anchors; home is consistent and well conditioned."""
    mj = mujoco.MjModel.from_xml_path(STEWART_XML)
    prm = hand.params
    np.testing.assert_allclose(np.linalg.norm(np.asarray(prm.a)[:, :2], axis=1), 0.05, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(prm.b)[:, :2], axis=1), 0.035, atol=1e-12)
    np.testing.assert_allclose(mj.eq_data[:, 3:6], np.asarray(prm.b), atol=1e-9)  # body2 anchor, compiled at home
    p, R = hand.pose(jnp.asarray(HOME))
    np.testing.assert_allclose(p, [0.0, 0.0, 0.05], atol=1e-9)  # the MJCF prints 10 digits
    np.testing.assert_allclose(R, np.eye(3), atol=1e-9)
    Jinv = np.asarray(stewart_inverse_jacobian(prm, p, R)) * np.r_[np.ones(3), np.full(3, 1 / 0.035)]
    assert np.linalg.cond(Jinv) == pytest.approx(2.21, abs=0.01)


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_closed_form_equals_ift_inverse_jacobian(hand):
    """pinv of the implicit-function-theorem Jacobian (jacfwd through Newton) = rows [u_i, (R b_i) x u_i]."""
    q = jnp.asarray(_box(0, 8))

    @jax.jit
    def both(q):
        p, R = hand.pose(q)
        return hand.true_inverse_jacobian(q), stewart_inverse_jacobian(hand.params, p, R)

    Ji, Jc = jax.vmap(both)(q)
    assert np.all(np.linalg.cond(np.asarray(Jc)) < 100)  # non-singular
    rel = np.max(np.abs(Ji - Jc), axis=(1, 2)) / np.max(np.abs(Jc), axis=(1, 2))
    assert rel.max() < 1e-6, rel


@pytest.mark.slow
def test_jacrev_matches_jacfwd(hand):
    """Reverse mode through the Newton solve (implicit adjoint) equals forward mode."""
    q = jnp.asarray(_box(1, 1)[0])
    f = lambda q_: jnp.concatenate([hand.pose(q_)[0], hand.pose(q_)[1].ravel()])
    rev, fwd = jax.jit(lambda q_: (jax.jacrev(f)(q_), jax.jacfwd(f)(q_)))(q)
    np.testing.assert_allclose(rev, fwd, rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_unsafe_commands_give_nan(hand, poses):
    """A leg outside [0.05, 0.07] m, or a pose off the home branch, gives NaN (never a wrong pose)."""
    bad = np.tile(HOME, (3, 1))
    bad[0, 0] = 0.0499
    bad[1, 3] = 0.0701
    bad[2] = [0.05, 0.07, 0.05, 0.07, 0.05, 0.07]  # in range, far off home: must be finite or NaN, never garbage
    p, R = poses(hand, jnp.asarray(bad))
    assert np.all(np.isnan(p[:2])) and np.all(np.isnan(R[:2]))
    if np.all(np.isfinite(p[2])):  # if Newton converged there, the legs must have the commanded lengths
        leg = p[2][None, :] + np.asarray(R[2] @ hand.params.b.T).T - np.asarray(hand.params.a)
        np.testing.assert_allclose(np.linalg.norm(leg, axis=1), bad[2], atol=1e-9)
    flipped = hand.replace(params=hand.params.replace(det_sign=-hand.params.det_sign))  # the other branch
    assert np.all(np.isnan(flipped.pose(jnp.asarray(HOME))[0]))
    p, _, ok = stewart_native_batch(bad[:2])
    assert not ok.any() and np.all(np.isnan(p))
    with jax.enable_x64(False), pytest.raises(ValueError, match="float64"):
        stewart_hand()


@pytest.mark.slow
def test_native_matches_kinematic_and_settles_within_half_budget(hand, poses):
    """64 asymmetric commands over the sampling box settle natively within half the budget, to <= 1e-6 m."""
    q = _box(2, 64)
    p_n, R_n, ok = stewart_native_batch(q, max_steps=STEWART_SETTLE_STEPS // 2)
    assert ok.all()
    p_k, R_k = poses(hand, jnp.asarray(q))
    ep, eR = _pose_err(p_n, R_n, p_k, R_k)
    assert ep < 1e-6 and eR < 1e-5, (ep, eR)


@pytest.mark.slow
def test_native_system_by_callback(hand, poses):
    """backend="native": the pose map through jax.pure_callback, under jit and vmap."""
    native = stewart_hand(backend="native")
    q = jnp.asarray(_box(3, 2))
    p, R = jax.jit(jax.vmap(native.pose))(q)
    p_k, R_k = poses(hand, q)
    assert _pose_err(p, R, p_k, R_k)[0] < 1e-6
    p1, _ = jax.jit(native.pose)(q[0])
    np.testing.assert_allclose(p1, p[0], atol=1e-12)
    p2, _ = jax.vmap(jax.vmap(native.pose))(q[:, None, :])  # nested vmap: one (2, 1, 6) callback
    np.testing.assert_allclose(p2[:, 0], p, atol=1e-12)


@pytest.mark.slow
def test_mjx_matches_kinematic_pose_and_jacobian_and_its_settle_options_keep_the_pose(hand, poses, mjx_batch):
    """MJX settling (float64): poses within 1e-6 m of Newton's; central-difference Jacobian within 1e-3; NaN out of
    range. And settle.mjx_model's settling options (one Newton iteration and 4 line-search steps a step, sparse mass
    matrix on CPU; the loop carrying the state only), which the hand's MJX backend uses, settle 16 random commands
    to the pose MJX gives with the MJCF's own options (up to 100 iterations, 50 line-search steps, dense) and to
    native MuJoCo's. One test: both parts run the same compiled MJX settle (16 commands, the poses fixture), traced
    once (the Model O's settling options are checked in test_model_o.py, beside its MJX pose)."""
    from selfid_jax.systems.hands.stewart import STEWART_SETTLE_TOL

    mjx_hand = stewart_hand(backend="mjx")
    q = _box(4, 3)
    h = 1e-4  # settled to ~1e-9 m: a larger step keeps the settle error small against h
    q_fd = np.concatenate([q[0] + h * np.eye(6), q[0] - h * np.eye(6)])
    bad = HOME.copy()
    bad[2] = 0.0705
    batch = jnp.asarray(np.concatenate([q, q_fd, bad[None]]))
    assert batch.shape[0] == mjx_batch
    p, R = poses(mjx_hand, batch)
    p_k, R_k = poses(hand, batch[:3])  # the program test_unsafe_commands_give_nan runs
    ep, eR = _pose_err(p[:3], R[:3], p_k, R_k)
    assert ep < 1e-6 and eR < 1e-5, (ep, eR)
    ref = (p[0], R[0])
    V = jax.vmap(lambda pp, RR: mjx_hand.task_difference((pp, RR), ref))(p[3:15], R[3:15])
    J_fd = np.asarray((V[:6] - V[6:]) / (2 * h)).T
    J_k = np.asarray(jax.jit(lambda s, q_: s.jacobian(q_))(hand, jnp.asarray(q[0])))
    assert np.max(np.abs(J_fd - J_k)) / np.max(np.abs(J_k)) < 1e-3
    assert np.all(np.isnan(p[-1])) and np.all(np.isnan(R[-1]))

    # the settling options, on 16 random commands over the sampling box
    mj, steps, tol = mujoco.MjModel.from_xml_path(STEWART_XML), STEWART_SETTLE_STEPS, STEWART_SETTLE_TOL
    q = _box(11, mjx_batch)
    inner = mjx_hand.params
    mjcf = settle.mjx_model(mj, iterations=None, ls_iterations=None, sparse=False)
    assert (int(inner.model.opt.iterations), int(inner.model.opt.ls_iterations)) == (1, 4)
    assert (int(mjcf.opt.iterations), int(mjcf.opt.ls_iterations)) == (mj.opt.iterations, mj.opt.ls_iterations)
    assert (mjx_hand.pose_fn.max_steps, mjx_hand.pose_fn.tol) == (steps, tol)
    p_f, R_f = poses(mjx_hand, jnp.asarray(q))
    p_m, R_m = poses(mjx_hand.replace(params=dataclasses.replace(inner, model=mjcf)), jnp.asarray(q))
    p_n, R_n, ok_n = settle.native_settle(mj, int(mj.site("pom").id), q, max_steps=steps, tol=tol)
    assert ok_n.all() and np.all(np.isfinite(p_f)) and np.all(np.isfinite(p_m))
    e_fm, eR_fm = _pose_err(p_f, R_f, p_m, R_m)
    e_fn, eR_fn = _pose_err(p_f, R_f, p_n, R_n)
    assert e_fm < 1e-12 and eR_fm < 1e-10, (e_fm, eR_fm)
    assert e_fn < 1e-8 and eR_fn < 1e-6, (e_fn, eR_fn)


@pytest.mark.slow
def test_mjx_settle_loops_on_a_toy_model():
    """mjx_settle: "while" and "scan" agree with native_settle on a one-slide servo; forward/reverse derivatives."""
    xml = """<mujoco><option timestep="0.005"/><worldbody><body><joint name="s" type="slide" axis="1 0 0" damping="2"/>
      <geom size=".01" mass="0.05" contype="0" conaffinity="0"/><site name="pom"/></body></worldbody>
      <actuator><position joint="s" kp="100"/></actuator></mujoco>"""
    mj = mujoco.MjModel.from_xml_string(xml)
    model = settle.mjx_model(mj)
    d0 = settle._mjx().make_data(model)
    target = jnp.asarray([0.01])

    def pos(c, loop):
        d, ok = settle.mjx_settle(model, d0, c, max_steps=300, tol=1e-10, loop=loop)
        return d.site_xpos[0, 0], ok

    @jax.jit
    def everything(c):
        (x_s, ok_s), g_s = jax.value_and_grad(lambda c_: pos(c_, "scan"), has_aux=True)(c)  # reverse mode
        x_w, dx_w, ok_w = jax.jvp(lambda c_: pos(c_, "while"), (c,), (jnp.ones_like(c),), has_aux=True)  # forward
        ok_short = settle.mjx_settle(model, d0, c, max_steps=3, tol=1e-10)[1]
        return x_s, ok_s, g_s, x_w, dx_w, ok_w, ok_short

    x_s, ok_s, g_s, x_w, dx_w, ok_w, ok_short = everything(target)
    p_n, _, ok_n = settle.native_settle(mj, "pom", np.asarray([[0.01]]), max_steps=300, tol=1e-10)
    assert ok_w and ok_s and ok_n[0] and not ok_short
    np.testing.assert_allclose([x_w, x_s, p_n[0, 0]], 0.01, atol=1e-8)  # underdamped: patience skips turning points
    np.testing.assert_allclose([g_s[0], dx_w], 1.0, atol=1e-5)  # d x / d ctrl = 1


@pytest.mark.slow
def test_selfid_and_follow_rotation(hand):
    """Self-ID (eps_rel = 0.02) converges near the truth; true inverse and estimate complete a 6-D rotation path."""
    q0 = hand.sample_configs(jax.random.key(0), 1)[0]
    ctrl = sj.ControllerParams(max_step=0.0005, tol=0.0002, max_rot_step=0.01, rot_tol=0.005)
    path = sj.control.paths.rotation(axis=(1.0, 1.0, 0.0), angle=0.1, steps=5)

    @jax.jit
    def one(key, q0):
        res = sj.identify.algorithm.run(hand, key, q0, iters=20, eps=0.0, eps_rel=0.02)
        J_true = hand.true_inverse_jacobian(res.env)
        est = sj.follow(hand, sj.control.fixed(res.estimate), path, res.env, ctrl, steps=100)
        tru = sj.follow(hand, sj.control.true_inverse(hand), path, res.env, ctrl, steps=100)
        return res.converged_at, jnp.linalg.norm(res.estimate - J_true) / jnp.linalg.norm(J_true), est, tru

    conv, rel, est, tru = one(jax.random.key(1), q0)
    assert 0 < conv <= 20 and rel < 0.05
    assert tru.completion == 1.0 and not tru.failed and tru.mean_error < 1e-5
    assert est.completion >= 0.9 and not est.failed


@pytest.mark.slow
def test_three_backends_agree_on_a_short_rollout(hand):
    """The same controller rollout (a fixed inverse Jacobian from the kinematic hand) on all three backends."""
    q0 = jnp.asarray(HOME)
    J = jax.jit(lambda s, q_: s.true_inverse_jacobian(q_))(hand, q0)
    path = sj.control.paths.star(size=0.002, dim=6)[:2]
    ctrl = sj.ControllerParams(max_step=0.0005, tol=0.0002, max_rot_step=0.01, rot_tol=0.005)
    runs = {}
    for backend in ("kinematic", "mjx", "native"):
        system = hand if backend == "kinematic" else stewart_hand(backend=backend)
        res = jax.jit(lambda q, system=system: sj.follow(system, sj.control.fixed(J), path, q, ctrl, steps=6,
                                                         return_trajectory=True))(q0)
        assert not bool(res.failed), backend
        runs[backend] = np.asarray(res.positions)
    for backend in ("mjx", "native"):
        np.testing.assert_allclose(runs[backend], runs["kinematic"], atol=1e-6, err_msg=backend)
    assert np.ptp(runs["kinematic"][:, 0]) > 5e-4  # the hand really moved
