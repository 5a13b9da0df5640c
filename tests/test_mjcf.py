"""from_mjcf on a Menagerie-style model: implicit integrator, actuators (joint, servo, tendon), an equality,
held joints and a free-floating box; against MuJoCo C and an independent numpy actuator -> qpos map."""

import jax
import mujoco
import numpy as np
import pytest
from helpers_mjcf import TENDON_ARM_XML
from scipy.spatial.transform import Rotation

from selfid_jax import control
from selfid_jax.control import paths
from selfid_jax.identify import algorithm as selfid
from selfid_jax.systems import from_mjcf

# The arm (its joints, tendon and actuators): tests/helpers_mjcf.py.
ACTS = ["a1", "a_pair", "a2", "a3"]  # q order (not the model's)
FIXED = {"jh": 0.3}
MJ = mujoco.MjModel.from_xml_string(TENDON_ARM_XML)


def qpos_of(u):
    """Independent numpy map: actuator values (ACTS order) -> qpos (nq,), the documented convention."""
    a1, t, a2, a3 = u
    qpos = MJ.qpos0.copy()
    adr = {n: MJ.jnt_qposadr[MJ.joint(n).id] for n in ("j1", "j2", "j3", "jf", "ja", "jb", "jh")}
    qpos[adr["j1"]], qpos[adr["j2"]], qpos[adr["j3"]] = a1, a2, a3
    qpos[adr["jf"]] = 0.5 * a3  # equality: jf - 0 = 0.5 (j3 - 0)
    coef = np.array([1.0, 0.5])
    L0 = coef @ [0.2, 0.0]  # tendon length at qpos0
    qpos[[adr["ja"], adr["jb"]]] = np.array([0.2, 0.0]) + coef * (t - L0) / (coef @ coef)  # least-norm
    qpos[adr["jh"]] = FIXED["jh"]
    return qpos


def vel_map():
    """d qvel / d u (nv, 4) of :func:`qpos_of` (hinge/slide dofs only)."""
    M = np.zeros((MJ.nv, 4))
    dof = {n: MJ.jnt_dofadr[MJ.joint(n).id] for n in ("j1", "j2", "j3", "jf", "ja", "jb")}
    M[dof["j1"], 0], M[dof["ja"], 1], M[dof["jb"], 1] = 1.0, 1.0 / 1.25, 0.5 / 1.25
    M[dof["j2"], 2], M[dof["j3"], 3], M[dof["jf"], 3] = 1.0, 1.0, 0.5
    return M


def mj_site(qpos, site="tip"):
    """MuJoCo C: (p, R, jacp, jacr) of a site at qpos."""
    d = mujoco.MjData(MJ)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(MJ, d)
    mujoco.mj_comPos(MJ, d)
    sid = MJ.site(site).id
    jacp, jacr = np.zeros((3, MJ.nv)), np.zeros((3, MJ.nv))
    mujoco.mj_jacSite(MJ, d, jacp, jacr, sid)
    return d.site_xpos[sid].copy(), d.site_xmat[sid].reshape(3, 3).copy(), jacp, jacr


@pytest.fixture(scope="module")
def arm():
    return from_mjcf(TENDON_ARM_XML, "tip", actuators=ACTS, joints_fixed=FIXED, task_dim=6, m_a=0.02)


U = np.array([[0.3, 0.4, -0.5, 0.8], [-1.2, -0.7, 1.0, -1.5], [1.9, 0.9, 0.1, 0.2]])


@jax.jit
def _pose_jac(system, q):
    (p, R), J = system.pose_and_jacobian(q)
    return p, R, J, system.jacobian(q)


def test_loads_and_has_the_chosen_actuators(arm):
    assert MJ.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICIT  # MJX cannot simulate it; kinematics load
    assert (arm.n_act, arm.task_dim, arm.name) == (4, 6, "mjcf")
    assert arm.pose_fn.qmap.names == tuple(ACTS)
    assert arm.m_a.shape == (4,)
    # limits: a1 servo ctrlrange [-2, 2] inside the joint range; tendon: ja in [-1, 1] allows [-1.3, 1.2],
    # the servo [-1, 1]; a2 servo [-1.5, 1.5]; a3 motor (torque range unused): j3 [-2, 2] and jf = 0.5 j3 in
    # [-0.5, 0.5] -> [-1, 1]
    np.testing.assert_allclose(arm.q_low, [-2.0, -1.0, -1.5, -1.0], atol=1e-12)
    np.testing.assert_allclose(arm.q_high, [2.0, 1.0, 1.5, 1.0], atol=1e-12)
    # default box: home (qpos0 -> actuators: 0, tendon 0.2) +- 0.5 rad (hinge-only actuators), clipped
    np.testing.assert_allclose(arm.sample_low, [-0.5, -0.3, -0.5, -0.5], atol=1e-12)
    np.testing.assert_allclose(arm.sample_high, [0.5, 0.7, 0.5, 0.5], atol=1e-12)


@pytest.mark.slow
def test_pose_and_jacobian_match_mujoco(arm):
    M = vel_map()
    for u in U:
        p, R, J, J2 = (np.asarray(x) for x in _pose_jac(arm, u))
        p_ref, R_ref, jacp, jacr = mj_site(qpos_of(u))
        np.testing.assert_allclose(p, p_ref, atol=1e-12)
        np.testing.assert_allclose(R, R_ref, atol=1e-12)
        np.testing.assert_allclose(J, J2, atol=0)
        np.testing.assert_allclose(J[:3], jacp @ M, atol=1e-10)
        np.testing.assert_allclose(J[3:], jacr @ M, atol=1e-10)
        # central finite differences of MuJoCo's pose through the numpy map: [dp, rotvec(R R0^T)]
        h, fd = 1e-6, np.zeros((6, 4))
        for i in range(4):
            e = np.eye(4)[i] * h
            (pp, Rp, _, _), (pm, Rm, _, _) = mj_site(qpos_of(u + e)), mj_site(qpos_of(u - e))
            fd[:3, i] = (pp - pm) / (2 * h)
            fd[3:, i] = Rotation.from_matrix(Rp @ Rm.T).as_rotvec() / (2 * h)
        np.testing.assert_allclose(J, fd, atol=1e-8)
    again = from_mjcf(TENDON_ARM_XML, "tip", actuators=ACTS, joints_fixed=FIXED, task_dim=6, m_a=0.02)
    assert again.pose_fn == arm.pose_fn and hash(again.pose_fn) == hash(arm.pose_fn)  # no recompilation


@pytest.mark.slow
def test_mjx_path_loads_the_implicit_model_and_agrees(arm):
    s = from_mjcf(TENDON_ARM_XML, "tip", actuators=ACTS, joints_fixed=FIXED, task_dim=6, m_a=0.02, fk="mjx")
    assert s.params.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER  # the kinematic copy
    assert MJ.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICIT
    p, R = jax.jit(lambda system, q: system.pose(q))(s, U[0])
    p_ref, R_ref, _, _ = mj_site(qpos_of(U[0]))
    np.testing.assert_allclose(p, p_ref, atol=1e-12)
    np.testing.assert_allclose(R, R_ref, atol=1e-12)


@jax.jit
def _selfid_then_follow(system, key, q0):
    res = selfid.run(system, key, q0, iters=30, eps=0.5)
    out = control.follow(system, control.fixed(res.estimate), paths.star(size=0.02, dim=3), res.env,
                         control.ControllerParams(max_step=0.002, tol=0.0005), steps=150)
    return res.converged_at, res.dtheta, out.completion, out.failed


@pytest.mark.slow
def test_selfid_converges_and_star_completes(arm):
    # qpos0 is the outstretched (singular) arm: sample around a bent home instead
    arm3 = from_mjcf(TENDON_ARM_XML, "tip", actuators=ACTS, joints_fixed=FIXED, task_dim=3,
                     m_a=[0.02, 0.02, 0.02, 0.03], home=[0.0, 0.2, 0.5, 0.8], min_sigma=0.05)
    np.testing.assert_allclose(arm3.m_a, [0.02, 0.02, 0.02, 0.03])
    np.testing.assert_allclose(arm3.sample_low, [-0.5, -0.3, 0.0, 0.3], atol=1e-12)
    np.testing.assert_allclose(arm3.sample_high, [0.5, 0.7, 1.0, 1.0], atol=1e-12)
    q0 = arm3.sample_configs(jax.random.key(0), 1)[0]
    conv, dtheta, completion, failed = _selfid_then_follow(arm3, jax.random.key(1), q0)
    assert int(conv) > 0
    assert float(completion) == 1.0 and not bool(failed)
    # a user m_a vector sets the actuation scale per actuator: |dtheta_i| <= m_a_i, and reaches near it
    scale = np.abs(np.asarray(dtheta))[: int(conv)].max(axis=0)
    assert np.all(scale <= np.asarray(arm3.m_a)) and np.all(scale > 0.6 * np.asarray(arm3.m_a))
    big = arm3.replace(m_a=np.array([0.02, 0.02, 0.02, 0.06]))  # same compiled program
    dtheta_big = np.asarray(_selfid_then_follow(big, jax.random.key(1), q0)[1])
    np.testing.assert_allclose(dtheta_big[0], np.asarray(dtheta)[0] * [1, 1, 1, 2], rtol=1e-12)


@pytest.mark.slow
def test_default_actuators_skip_unsupported_ones_with_a_warning():
    with pytest.warns(UserWarning, match="'a_site' has a site transmission"):
        s = from_mjcf(TENDON_ARM_XML, "tip", task_dim=3, m_a=0.02)
    assert s.pose_fn.qmap.names == ("a1", "a2", "a3", "a_pair", "a_finger")
    # the finger slide (off the chain) has range [0, 0.04]: default box = home 0 + 1/4 of the range
    np.testing.assert_allclose([s.sample_low[4], s.sample_high[4]], [0.0, 0.01], atol=1e-15)
    # the unactuated jh is held at qpos0 = 0: the pose equals MuJoCo's with jh = 0
    u = np.array([0.3, -0.5, 0.8, 0.4, 0.02])
    qpos = qpos_of(u[[0, 3, 1, 2]])
    qpos[MJ.jnt_qposadr[MJ.joint("jh").id]] = 0.0
    qpos[MJ.jnt_qposadr[MJ.joint("finger").id]] = 0.02
    np.testing.assert_allclose(jax.jit(lambda system, q: system.pose(q)[0])(s, u), mj_site(qpos)[0], atol=1e-12)


NO_ACT = "<mujoco><worldbody><body><joint name='h'/><geom size='.1'/><site name='s'/></body></worldbody></mujoco>"


@pytest.mark.parametrize(
    "args, kw, match",
    [
        (("box_site",), dict(actuators=ACTS), "'box_free' is a free joint on the kinematic chain of site 'box_site'"),
        (("tip",), dict(actuators=["a1", "a9"]),
         r"unknown actuator 'a9'.*\['a1', 'a2', 'a3', 'a_pair', 'a_finger', 'a_site'\]"),
        (("tip",), dict(actuators=ACTS, m_a=[0.1, 0.1]),
         r"m_a must have shape \(4,\) \(one value per actuator.*'a_pair'"),
        (("tip",), dict(actuators=ACTS, dq_max=[0.1] * 5), r"dq_max must have shape \(4,\)"),
        (("tip",), dict(actuators=["a_site"]), "'a_site' has a site transmission"),
        (("tip",), dict(actuators=ACTS, joints_fixed={"j1": 0.1}),
         r"actuator 'a1' .* not independent of joints_fixed\['j1'\]"),
        (("tip",), dict(actuators=ACTS, joints_fixed={"nope": 0.1}), "'nope' is not a joint"),
        (("tip",), dict(actuators=ACTS, joints_fixed={"box_free": 0.1}), "'box_free' is a free joint"),
        (("tip",), dict(actuators=ACTS, home=[0.0, 0.0, 0.0, 3.0]), "home .* inside the limits"),
    ],
)
def test_clear_errors(args, kw, match):
    kw = dict(dict(task_dim=3, m_a=0.02), **kw)
    with pytest.raises(ValueError, match=match):
        from_mjcf(TENDON_ARM_XML, *args, **kw)


def test_clear_errors_on_other_models():
    with pytest.raises(ValueError, match="has no actuators .*actuators='joints'"):
        from_mjcf(NO_ACT, "s", task_dim=3, m_a=0.02)
    empty = "<mujoco><worldbody><site name='s'/></worldbody></mujoco>"
    with pytest.raises(ValueError, match="has no actuators and no hinge or slide joints: nothing to actuate"):
        from_mjcf(empty, "s", task_dim=3, m_a=0.02)
    with pytest.raises(ValueError, match="has no hinge or slide joints"):
        from_mjcf(empty, "s", actuators="joints", task_dim=3, m_a=0.02)
    two = NO_ACT.replace(
        "</mujoco>", "<actuator><position name='p' joint='h'/><velocity name='v' joint='h'/></actuator></mujoco>"
    )
    with pytest.raises(ValueError, match="actuator 'v' .* not independent of actuator 'p'"):
        from_mjcf(two, "s", task_dim=3, m_a=0.02)
    slide = (
        "<mujoco><worldbody><body><joint name='x' type='slide'/><geom size='.1'/><site name='s'/></body></worldbody>"
        "<actuator><motor name='m' joint='x'/></actuator></mujoco>"
    )
    with pytest.raises(ValueError, match="'m' .*no finite range: pass sample_half_width"):
        from_mjcf(slide, "s", task_dim=3, m_a=0.02)
    s = from_mjcf(slide, "s", task_dim=3, m_a=0.02, sample_half_width=0.1)
    np.testing.assert_allclose([s.sample_low[0], s.sample_high[0]], [-0.1, 0.1])
