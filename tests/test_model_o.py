"""Yale Model O: the MJCF, the kinematic equilibrium against native MuJoCo / MJX, guards, self-ID and control.

float64 throughout (conftest turns x64 on). The fast tier touches only native
MuJoCo; every test that compiles the kinematic solve or MJX is marked slow.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import selfid_jax as sj
from selfid_jax.systems.hands import model_o_hand as mo
from selfid_jax.systems.hands import settle

POSE_TOL = 1e-6  # m: kinematic vs settled poses
JAC_RTOL = 1e-3  # relative: kinematic vs finite-difference settled Jacobians
# a few commands (m) about the grasp, asymmetric (symmetric ones hide slow modes)
OFFSETS = np.array([[0.0, 0.0, 0.0], [1e-3, -2e-3, 0.5e-3], [-3e-3, 2.5e-3, 1e-3], [2e-3, 1e-3, -4e-3]])
ROLL_OVER = np.array([7e-3, -7e-3, 0.0])  # pulls f0, releases f1: past the fold, the object rolls over


def _native(q, tol=1e-12):
    """Native settled POM ``(p (B, 3), R (B, 3, 3), settled (B,))`` from the grasp keyframe, no guards."""
    return settle.native_settle(mo.model_o_mjmodel(), mo.MODEL_O_SITE, np.atleast_2d(q),
                                qpos0=mo.model_o_keyframe()[0], max_steps=3000, tol=tol)


def _native_jacobian(q, h):
    """``(3, 3)`` central-difference Jacobian of the native settled POM position at ``q`` (step ``h``, m)."""
    E = h * np.eye(3)
    p, _, ok = _native(np.concatenate([q + E, q - E]))
    assert ok.all()
    return (p[:3] - p[3:]).T / (2 * h)


@pytest.fixture(scope="module")
def hand():
    return mo.model_o()


# ------------------------------------------------------------------ fast: the MJCF and the settled map
def test_mjcf_is_the_documented_hand():
    mj = mo.model_o_mjmodel()
    assert (mj.nu, mj.neq, mj.ntendon, mj.njnt) == (3, 3, 3, 7)
    assert np.all(mj.geom_contype == 0) and np.all(mj.geom_conaffinity == 0)
    assert np.all(mj.opt.gravity == 0) and mj.opt.solver == mujoco.mjtSolver.mjSOL_NEWTON and mj.opt.timestep == 0.002
    assert np.allclose(mj.actuator_gainprm[:, 0], 500) and np.allclose(mj.eq_solref, [0.004, 1])
    assert np.allclose(mj.eq_solimp, [0.9999, 0.9999, 0.001, 0.5, 2])
    assert np.allclose(mj.wrap_prm[: mj.nwrap], np.tile([0.012, 0.008], 3))
    assert np.allclose(mj.jnt_stiffness[:6], 0.05) and np.allclose(mj.dof_damping[:6], 0.001)
    assert np.allclose(mj.site_pos[mj.site("pom").id], [0, 0, 0.03])  # POM 30 mm above the object's centre
    # the keyframe is the grasp: contacts closed, at rest up to the soft constraints' give, 0.064 N squeeze
    d = mujoco.MjData(mj)
    mujoco.mj_resetDataKeyframe(mj, d, mj.key("grasp").id)
    mujoco.mj_forward(mj, d)
    assert np.abs(d.efc_pos).max() < 1e-12 and np.abs(d.qacc).max() < 1e-2
    assert np.allclose(np.linalg.norm(d.efc_force.reshape(3, 3), axis=1), 0.064, atol=1e-3)


def test_settled_map_is_deterministic_and_smooth():
    q = mo.model_o_home() + OFFSETS[1]
    p1, _, ok1 = _native(q)
    p2, _, ok2 = _native(q)
    assert ok1.all() and ok2.all() and np.array_equal(p1, p2)
    J1, J2 = _native_jacobian(q, 2e-4), _native_jacobian(q, 1e-4)
    assert np.abs(J1 - J2).max() < JAC_RTOL * np.abs(J1).max()


def test_needs_x64_and_checks_arguments():
    with jax.enable_x64(False), pytest.raises(ValueError, match="float64"):
        mo.model_o()
    with pytest.raises(ValueError, match="backend"):
        mo.model_o(backend="cg")
    with pytest.raises(ValueError, match="low < 0 < high"):
        mo.model_o(safe_range=(0.001, 0.005))


# ------------------------------------------------------------------ slow: the kinematic equilibrium
@pytest.mark.slow
def test_kinematic_matches_native(hand, poses):
    home = mo.model_o_home()
    Q = home + OFFSETS
    (p, R), J = jax.jit(jax.vmap(hand.pose_and_jacobian))(jnp.asarray(Q))
    pn, Rn, ok = _native(Q)
    assert ok.all() and np.all(np.isfinite(p))
    assert np.abs(np.asarray(p) - pn).max() < POSE_TOL
    assert np.abs(np.asarray(R) - Rn).max() < POSE_TOL / 0.03  # rad, over the POM's 30 mm lever
    assert np.allclose(p[0], [0, 0, 0.12], atol=1e-12)  # the grasp: POM straight above the palm, 120 mm up
    for q, Jk in zip(Q, np.asarray(J)):
        Jn = _native_jacobian(q, 1e-4)
        assert np.abs(Jk - Jn).max() < JAC_RTOL * np.abs(Jn).max()
    pn_sys = poses(mo.model_o(backend="native"), jnp.asarray(Q))[0]  # the native System: pure_callback, guards
    assert np.abs(np.asarray(pn_sys) - pn).max() < 1e-9
    s = np.linalg.svd(J[0], compute_uv=False)
    assert 1.5 < s[0] / s[-1] < 3  # well conditioned at the grasp (2.17)


@pytest.mark.slow
def test_jacobians_forward_mode_through_solve_and_rotation(hand):
    q = jnp.asarray(mo.model_o_home() + OFFSETS[2])
    h6 = hand.with_task_dim(6)
    J6 = jax.jit(h6.jacobian)(q)
    J_fwd = jax.jit(jax.jacfwd(lambda q_: hand.pose(q_)[0]))(q)  # implicit_root's derivative
    assert np.allclose(J_fwd, J6[:3], rtol=1e-9, atol=1e-12)
    # the 6-D rows: world-frame angular velocity against differences of the rotation vector
    pose = jax.jit(hand.pose)
    R0 = pose(q)[1]
    rot = lambda q_: sj.math.geometry.so3_log(pose(q_)[1] @ R0.T)
    Jr = jnp.stack([(rot(q + 1e-6 * e) - rot(q - 1e-6 * e)) / 2e-6 for e in jnp.eye(3)], axis=1)
    assert np.abs(J6[3:] - Jr).max() < 1e-5 * np.abs(Jr).max()
    assert np.linalg.matrix_rank(np.asarray(J6), tol=1e-6) == 3  # the grasp has 3 DOF


@pytest.mark.slow
@pytest.mark.xdist_group("model_o_mjx")  # with test_cuda_lowering.py's lowering of the same MJX program: one trace
def test_mjx_matches_kinematic_and_its_settle_options_keep_the_pose(hand, poses, mjx_batch):
    """MJX settling matches the kinematic equilibrium to POSE_TOL about the grasp. And settle.mjx_model's settling
    options (one Newton iteration and 4 line-search steps a step, sparse mass matrix on CPU; the loop carrying the
    state only), which the hand's MJX backend uses, settle 16 random commands to the pose MJX gives with the MJCF's
    own options (up to 100 iterations, 50 line-search steps, dense) and to native MuJoCo's. One test: both parts run
    the same compiled MJX settle (16 commands, the poses fixture), traced once (test_stewart_hand.py checks the
    Stewart Hand's settling options the same way)."""
    import dataclasses

    hm = mo.model_o(backend="mjx")
    extra = np.random.default_rng(12).uniform(-0.001, 0.001, (mjx_batch - 2, 3))
    Q = jnp.asarray(mo.model_o_home() + np.concatenate([OFFSETS[1:3], extra]))
    pm, pk = poses(hm, Q)[0], poses(hand, Q)[0]
    assert np.all(np.isfinite(pm)) and np.abs(pm - pk).max() < POSE_TOL

    # the settling options, on 16 random commands within 1 mm of the grasp
    mj, steps, tol = mo.model_o_mjmodel(), mo.MODEL_O_SETTLE_STEPS, mo.MODEL_O_SETTLE_TOL
    qpos0, home = mo.model_o_keyframe()
    q = home + np.random.default_rng(11).uniform(-0.001, 0.001, (mjx_batch, 3))
    inner, max_tilt = hm.params
    mjcf = settle.mjx_model(mj, iterations=None, ls_iterations=None, sparse=False)
    assert (int(inner.model.opt.iterations), int(inner.model.opt.ls_iterations)) == (1, 4)
    assert (int(mjcf.opt.iterations), int(mjcf.opt.ls_iterations)) == (mj.opt.iterations, mj.opt.ls_iterations)
    assert (hm.pose_fn.inner.max_steps, hm.pose_fn.inner.tol) == (steps, tol)
    p_f, R_f = poses(hm, jnp.asarray(q))
    p_m, R_m = poses(hm.replace(params=(dataclasses.replace(inner, model=mjcf), max_tilt)), jnp.asarray(q))
    p_n, R_n, ok_n = settle.native_settle(mj, int(mj.site("pom").id), q, qpos0=qpos0, max_steps=steps, tol=tol)
    assert ok_n.all() and np.all(np.isfinite(p_f)) and np.all(np.isfinite(p_m))
    e_fm = np.abs(np.asarray(p_f) - np.asarray(p_m)).max(), np.abs(np.asarray(R_f) - np.asarray(R_m)).max()
    e_fn = np.abs(np.asarray(p_f) - p_n).max(), np.abs(np.asarray(R_f) - R_n).max()
    assert e_fm[0] < 1e-12 and e_fm[1] < 1e-10, e_fm
    assert e_fn[0] < 1e-8 and e_fn[1] < 1e-6, e_fn


@pytest.mark.slow
def test_grasp_held_over_random_selfid_actuations(hand):
    run = jax.jit(lambda k, q0: sj.identify.algorithm.run(hand, k, q0, iters=50, eps=0.0, eps_rel=0.05,
                                                          stop_at_convergence=False))
    for k, q0 in zip(jax.random.split(jax.random.key(1), 2), hand.sample_configs(jax.random.key(0), 4)[:2]):
        res = run(k, q0)  # m_a: the hand's default, 0.3 mm of tendon
        assert res.state.rejected == 0 and np.all(np.isfinite(res.V)) and np.abs(res.V).max() > 0


@pytest.mark.slow
def test_roll_over_is_flagged(hand, poses):
    home = mo.model_o_home()
    q = jnp.asarray(home + ROLL_OVER)
    assert np.all(np.isnan(poses(hand, q[None])[0]))
    # native MuJoCo rolls the object over there; with the box widened the branch guard still flags it
    _, Rn, ok = _native(home + ROLL_OVER, tol=1e-10)
    assert ok.all() and np.degrees(mo.tilt_angle(jnp.asarray(Rn[0]))) > 45
    wide = mo.model_o(safe_range=(-0.02, 0.02))
    assert np.all(np.isnan(poses(wide, q[None])[0]))
    assert np.all(np.isnan(poses(mo.model_o(backend="native", safe_range=(-0.02, 0.02)), q[None])[0]))  # tilt
    ctrl = sj.ControllerParams(max_step=0.0005, tol=0.00005)
    path = jnp.array([[0.0, -0.02, 0.0]])  # 20 mm sideways: the controller pulls the object over
    starts = jnp.stack([q, jnp.asarray(home)])
    out = jax.jit(jax.vmap(lambda q0: sj.follow(wide, sj.control.true_inverse(wide), path, q0, ctrl, steps=60)))(starts)
    assert np.all(out.failed) and np.all(out.completion == 0)
    for metric in (out.mean_error, out.max_error, out.waypoint_error, out.final_q):
        assert np.all(np.isfinite(metric))


@pytest.mark.slow
def test_selfid_converges_and_star_is_followed(hand):
    # eps_rel 0.05: ||J_t - J_{t-1}|| <= 5% of ||J_t|| twice (J^+ is ~3 m/m here, so ~0.15 absolute)
    path = sj.control.paths.star(size=0.0015, dim=3)
    ctrl = sj.ControllerParams(max_step=0.0002, tol=0.00005)

    @jax.jit
    def one(key, q0):
        res = sj.identify.algorithm.run(hand, key, q0, iters=12, eps=0.0, eps_rel=0.05)
        est = sj.follow(hand, sj.control.fixed(res.estimate), path, res.env, ctrl, steps=200)
        true = sj.follow(hand, sj.control.true_inverse(hand), path, q0, ctrl, steps=200)
        return res.converged_at, est.completion, est.failed, true.completion, true.failed

    q0s = hand.sample_configs(jax.random.key(2), 4)
    out = [one(k, q0) for k, q0 in zip(jax.random.split(jax.random.key(3), 4), q0s)]
    conv, est, est_failed, true, true_failed = (np.array(v) for v in zip(*out))
    assert np.all(conv >= 3) and conv.mean() <= 8  # paper: 5.7 +- 1.0
    assert np.all(true == 1.0) and not true_failed.any()
    assert est.mean() >= 0.9 and not est_failed.any()
