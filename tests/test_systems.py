"""Systems against independent references: numpy DH chains, closed forms, MuJoCo C."""

import jax

jax.config.update("jax_enable_x64", True)

import dataclasses  # noqa: E402
import os  # noqa: E402

import chex  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from selfid_jax.systems import System, from_mjcf, from_pose_fn, two_link, ur5e  # noqa: E402
from selfid_jax.systems.ur5e import UR5E_XML  # noqa: E402

POS_TOL = 1e-6  # m
ROT_TOL = 1e-6  # rad
JAC_TOL = 1e-9  # exact derivatives vs MuJoCo's analytic jacobians (float64)

# ---------------------------------------------------------------- references
DH_D = [0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996]
DH_A = [0.0, -0.425, -0.3922, 0.0, 0.0, 0.0]
DH_ALPHA = [np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0]


def dh_fk(q):
    """Standard DH product prod_i Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i) -> (p, R)."""
    T = np.eye(4)
    for i in range(6):
        ct, st, ca, sa = np.cos(q[i]), np.sin(q[i]), np.cos(DH_ALPHA[i]), np.sin(DH_ALPHA[i])
        T = T @ np.array(
            [
                [ct, -st * ca, st * sa, DH_A[i] * ct],
                [st, ct * ca, -ct * sa, DH_A[i] * st],
                [0.0, sa, ca, DH_D[i]],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
    return T[:3, 3], T[:3, :3]


def mj_site_jacobian(model_path_or_mj, qs, site="ee"):
    """MuJoCo C: (p, R, jacp, jacr) of a site for each row of qs."""
    mj = model_path_or_mj
    if isinstance(mj, str):
        mj = mujoco.MjModel.from_xml_path(mj)
    d = mujoco.MjData(mj)
    sid = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, site)
    out = []
    for q in np.asarray(qs):
        d.qpos[:] = q
        mujoco.mj_kinematics(mj, d)
        mujoco.mj_comPos(mj, d)
        jacp, jacr = np.zeros((3, mj.nv)), np.zeros((3, mj.nv))
        mujoco.mj_jacSite(mj, d, jacp, jacr, sid)
        out.append((d.site_xpos[sid].copy(), d.site_xmat[sid].reshape(3, 3).copy(), jacp, jacr))
    return [np.stack(x) for x in zip(*out)]


def rot_angle(Ra, Rb):
    """Angle (rad) of the rotation between two orientations (scipy, well conditioned near 0)."""
    from scipy.spatial.transform import Rotation

    return float(Rotation.from_matrix(Ra.T @ Rb).magnitude())


def random_q(n, k, seed, low=-2 * np.pi, high=2 * np.pi):
    return np.random.default_rng(seed).uniform(low, high, size=(k, n))


# ------------------------------------------------------------------ fixtures
# Every UR5e call uses batch UR_B and the compiled functions below (one
# compilation per task_dim), so the whole module compiles only a handful of
# programs on a 2-core CPU.
UR_B = 12
TL_B = 64  # the same for every two-link call


def _evaluate(system, qs):
    """Batched (p, R, J, Jinv, sigma_min) of a system at ``qs (B, n)``."""

    def one(q):
        p, R = system.pose(q)
        return p, R, system.jacobian(q), system.true_inverse_jacobian(q), system.sigma_min(q)

    return jax.vmap(one)(qs)


evaluate = jax.jit(_evaluate)
sample = jax.jit(System.sample_configs, static_argnames=("k", "oversample", "return_valid"))
pose_one = jax.jit(System.pose)  # the System (e.g. with its mjx.Model) as a jit argument


@pytest.fixture(scope="module")
def ur6():
    """UR5e, 6-D task, plain-JAX chain FK (the default)."""
    return ur5e(task_dim=6)


@pytest.fixture(scope="module")
def ur_mjx():
    """UR5e through mjx.kinematics."""
    return ur5e(task_dim=6, fk="mjx")


@pytest.fixture(scope="module")
def ur_samples(ur6):
    """UR_B sampled UR5e configurations and their validity mask."""
    return sample(ur6, jax.random.key(0), k=UR_B, oversample=2, return_valid=True)


@pytest.fixture(scope="module")
def arm2():
    return two_link()


def three_link_xy(params, q):
    c = jnp.cumsum(q)
    return jnp.stack([jnp.sum(params * jnp.cos(c)), jnp.sum(params * jnp.sin(c))])


@pytest.fixture(scope="module")
def arm3():
    return from_pose_fn(
        three_link_xy,
        3,
        task_dim=2,
        q_low=-np.pi,
        q_high=np.pi,
        dq_max=0.1,
        m_a=0.05,
        params=jnp.array([1.0, 0.8, 0.5]),
        sample_low=[-1.0, 0.3, 0.3],
        sample_high=[1.0, 2.5, 2.5],
        min_sigma=0.05,
    )


# --------------------------------------------------------------------- UR5e
@pytest.mark.slow
def test_ur5e_fk_matches_dh(ur6, ur_mjx):
    qs = random_q(6, UR_B, seed=0)
    refs = [dh_fk(q) for q in qs]
    p_c, R_c = evaluate(ur6, qs)[:2]
    # unbatched MJX pose (compiles much faster than a vmapped one), System as argument
    p_m, R_m = (np.stack(x) for x in zip(*(pose_one(ur_mjx, q) for q in qs)))
    for p, R in ((p_c, R_c), (p_m, R_m)):
        assert p.dtype == jnp.float64 and p.shape == (UR_B, 3) and R.shape == (UR_B, 3, 3)
        for i, (p_ref, R_ref) in enumerate(refs):
            np.testing.assert_allclose(p[i], p_ref, atol=POS_TOL)
            assert rot_angle(np.asarray(R[i]), R_ref) <= ROT_TOL
    # the two FK paths agree to rounding
    np.testing.assert_allclose(p_c, p_m, atol=1e-12)
    np.testing.assert_allclose(R_c, R_m, atol=1e-12)


@pytest.mark.slow
def test_ur5e_jacobian_matches_mj_jacsite(ur6):
    qs = random_q(6, UR_B, seed=1)
    _, _, jacp, jacr = mj_site_jacobian(UR5E_XML, qs)
    for td in (6, 3):
        J = np.asarray(evaluate(ur6.with_task_dim(td), qs)[2])
        assert J.shape == (UR_B, td, 6)
        np.testing.assert_allclose(J[:, :3], jacp, atol=JAC_TOL)
        if td == 6:
            np.testing.assert_allclose(J[:, 3:], jacr, atol=JAC_TOL)  # world-frame angular part


@pytest.mark.slow
def test_ur5e_jacobian_matches_finite_differences(ur6):
    # Independent of MuJoCo and of selfid_jax.math.geometry: central differences of
    # [p - p0, rotvec(R R0^T)] with scipy's rotation vector.
    from scipy.spatial.transform import Rotation

    q0 = random_q(6, 1, seed=4)[0]
    h = 1e-6
    steps = np.concatenate([np.eye(6), -np.eye(6)]) * h  # (12, 6) = UR_B perturbations
    assert steps.shape[0] == UR_B
    p, R, J = evaluate(ur6, q0 + steps)[:3]
    p0, R0 = dh_fk(q0)
    V = np.concatenate(
        [np.asarray(p) - p0, Rotation.from_matrix(np.asarray(R) @ R0.T).as_rotvec()], axis=1
    )  # (12, 6)
    fd = ((V[:6] - V[6:]) / (2 * h)).T
    J_q0 = (np.asarray(J[0]) + np.asarray(J[6])) / 2  # J(q0 +- h e_0): mean is J(q0) + O(h^2)
    np.testing.assert_allclose(J_q0, fd, atol=1e-8)


@pytest.mark.slow
def test_ur5e_inverse_jacobian_and_sampling(ur6, ur_samples):
    q, valid = ur_samples
    assert q.shape == (UR_B, 6) and valid.shape == (UR_B,) and bool(valid.all())
    q = np.asarray(q)
    assert np.all(q >= np.asarray(ur6.sample_low)) and np.all(q <= np.asarray(ur6.sample_high))
    for td in (6, 3):
        sd = ur6.with_task_dim(td)
        p, _, J, Jinv, sig = evaluate(sd, q)
        assert Jinv.shape == (UR_B, 6, td)
        np.testing.assert_allclose(J @ Jinv, np.broadcast_to(np.eye(td), (UR_B, td, td)), atol=1e-9)
        np.testing.assert_allclose(Jinv, np.linalg.pinv(np.asarray(J)), atol=1e-9)
        np.testing.assert_allclose(sig, np.linalg.svd(np.asarray(J), compute_uv=False)[:, -1], atol=1e-12)
        assert np.all(sig > sd.min_sigma)
    # sampled configurations are reasonable: flange in front of the base and above it
    p = np.asarray(p)
    assert np.all(p[:, 0] < -0.1) and np.all(p[:, 2] > 0.0)


# ----------------------------------------------------------------- two-link
@pytest.mark.slow
def test_two_link_closed_form(arm2):
    qs = random_q(2, TL_B, seed=5, low=-np.pi, high=np.pi)
    p, R, J, _, _ = evaluate(arm2, qs)
    q1, q12 = qs[:, 0], qs[:, 0] + qs[:, 1]
    np.testing.assert_allclose(p[:, 0], np.cos(q1) + np.cos(q12), atol=1e-12)
    np.testing.assert_allclose(p[:, 1], np.sin(q1) + np.sin(q12), atol=1e-12)
    np.testing.assert_allclose(p[:, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(R[:, 0, 0], np.cos(q12), atol=1e-12)
    np.testing.assert_allclose(R[:, 1, 0], np.sin(q12), atol=1e-12)
    J_ref = np.stack(
        [
            np.stack([-np.sin(q1) - np.sin(q12), -np.sin(q12)], -1),
            np.stack([np.cos(q1) + np.cos(q12), np.cos(q12)], -1),
        ],
        axis=1,
    )
    np.testing.assert_allclose(J, J_ref, atol=1e-12)
    q = np.asarray(sample(arm2, jax.random.key(2), k=TL_B))
    _, _, Jq, Jinv, _ = evaluate(arm2, q)
    np.testing.assert_allclose(Jinv @ Jq, np.broadcast_to(np.eye(2), (TL_B, 2, 2)), atol=1e-10)
    np.testing.assert_allclose(Jq @ Jinv, np.broadcast_to(np.eye(2), (TL_B, 2, 2)), atol=1e-10)


@pytest.mark.slow
def test_two_link_sample_configs_and_mask(arm2):
    q = sample(arm2, jax.random.key(3), k=TL_B)
    assert q.shape == (TL_B, 2)
    sig = np.asarray(evaluate(arm2, q)[4])
    assert np.all(sig > arm2.min_sigma)
    # A box straddling the straight elbow (det J = l1 l2 sin q2 = 0 at q2 = 0) with
    # a strict threshold: some candidates are invalid, and valid ones come first.
    bad = arm2.replace(sample_low=jnp.array([-1.0, -0.5]), sample_high=jnp.array([1.0, 1.5]))
    bad = dataclasses.replace(bad, min_sigma=0.3)
    q, valid = sample(bad, jax.random.key(4), k=16, oversample=2, return_valid=True)
    valid = np.asarray(valid)
    n_valid = int(valid.sum())
    assert 0 < n_valid < 16
    assert np.all(valid[:n_valid]) and not np.any(valid[n_valid:])
    sig = np.asarray(evaluate(bad, q)[4])
    np.testing.assert_array_equal(sig > 0.3, valid)


def test_apply_clips_steps_and_limits():
    s = two_link(dq_max=0.1, q_low=(-1.0, -1.0), q_high=(1.0, 1.0), sample_low=(-1.0, 0.3), sample_high=(1.0, 0.9))
    apply = jax.jit(lambda system, q, dq: system.apply(q, dq))
    q = jnp.array([0.95, 0.0])
    np.testing.assert_allclose(apply(s, q, jnp.array([0.5, -0.05])), [1.0, -0.05])
    np.testing.assert_allclose(apply(s, q, jnp.array([-0.5, 0.3])), [0.85, 0.1])


# ---------------------------------------------------------------- from_pose_fn
@pytest.mark.slow
def test_three_link_from_pose_fn_closed_form(arm3):
    s = arm3
    assert (s.n_act, s.task_dim, s.has_rotation) == (3, 2, False)
    lengths = np.array([1.0, 0.8, 0.5])
    qs = random_q(3, UR_B, seed=6, low=-np.pi, high=np.pi)
    _, _, J, Jinv, _ = evaluate(s, qs)
    J, Jinv = np.asarray(J), np.asarray(Jinv)
    c = np.cumsum(qs, axis=1)
    # dx/dq_j = -sum_{i>=j} l_i sin(c_i), dy/dq_j = sum_{i>=j} l_i cos(c_i)
    tail_s = np.cumsum((lengths * np.sin(c))[:, ::-1], axis=1)[:, ::-1]
    tail_c = np.cumsum((lengths * np.cos(c))[:, ::-1], axis=1)[:, ::-1]
    np.testing.assert_allclose(J, np.stack([-tail_s, tail_c], axis=1), atol=1e-12)
    assert Jinv.shape == (UR_B, 3, 2)
    np.testing.assert_allclose(Jinv, np.linalg.pinv(J), atol=1e-10)


@pytest.mark.slow
def test_position_only_3d_and_full_pose_fns():
    def p3(params, q):
        return jnp.stack([q[0], q[1], q[0] * q[1]])

    s = from_pose_fn(p3, 2, task_dim=3, q_low=-1, q_high=1, dq_max=0.1, m_a=0.01)
    np.testing.assert_allclose(s.m_a, [0.01, 0.01])  # scalar broadcast; a vector is kept per actuator
    np.testing.assert_allclose(from_pose_fn(p3, 2, task_dim=3, q_low=-1, q_high=1, dq_max=0.1, m_a=[0.01, 0.03]).m_a,
                               [0.01, 0.03])
    p, R, J, _, _ = evaluate(s, np.array([[0.2, 0.5]]))
    np.testing.assert_allclose(p[0], [0.2, 0.5, 0.1])
    np.testing.assert_allclose(R[0], np.eye(3))
    np.testing.assert_allclose(J[0], [[1, 0], [0, 1], [0.5, 0.2]], atol=1e-12)
    with pytest.raises(ValueError, match="task_dim=6"):
        s.with_task_dim(6)

    def full(params, q):  # rotation about z by q[0], translation along x by q[1]
        c, sn = jnp.cos(q[0]), jnp.sin(q[0])
        R = jnp.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        return jnp.stack([q[1], 0.0, 0.0]), R

    s6 = from_pose_fn(full, 2, task_dim=6, q_low=-1, q_high=1, dq_max=0.1, m_a=0.01)
    J = evaluate(s6, np.array([[0.3, 0.2]]))[2][0]
    np.testing.assert_allclose(J, [[0, 1], [0, 0], [0, 0], [0, 0], [0, 0], [1, 0]], atol=1e-12)


def _good_kwargs(**over):
    kw = dict(task_dim=2, q_low=-np.pi, q_high=np.pi, dq_max=0.1, m_a=0.05, params=jnp.array([1.0, 0.8, 0.5]))
    kw.update(over)
    return kw


@pytest.mark.parametrize(
    "fn_n_over, match",
    [
        ((None, 3, {}), "fn must be callable"),
        ((three_link_xy, 0, {}), "n_act"),
        ((three_link_xy, 3, dict(task_dim=4)), "task_dim"),
        ((three_link_xy, 3, dict(task_dim=3)), "task_dim=2"),
        ((three_link_xy, 3, dict(q_low=[0.0, 0.0])), r"q_low must have shape \(3,\)"),
        ((three_link_xy, 3, dict(q_low=1.0, q_high=0.0)), "q_low must be < q_high"),
        ((three_link_xy, 3, dict(dq_max=-0.1)), "dq_max must be positive"),
        ((three_link_xy, 3, dict(m_a=[0.1, 0.1])), r"m_a must have shape \(3,\) \(one value per actuator"),
        ((three_link_xy, 3, dict(m_a=[0.1, -0.1, 0.1])), "m_a: must be > 0"),
        ((three_link_xy, 3, dict(m_a=0.0)), "m_a: must be > 0"),
        ((three_link_xy, 3, dict(q_low=-np.inf, q_high=np.inf)), "sampling box must be finite"),
        ((three_link_xy, 3, dict(sample_low=-4.0)), "inside the joint limits"),
        ((three_link_xy, 3, dict(min_sigma=-1.0)), "min_sigma"),
        ((lambda params, q: jnp.zeros(4), 3, {}), "fn must return"),
        ((lambda params, q: (jnp.zeros(3), jnp.eye(2)), 3, {}), "fn must return"),
        ((lambda params, q: q @ jnp.ones(5), 3, {}), "fn.*failed"),
        ((lambda params, q: jnp.zeros(3), 3, dict(task_dim=6)), "task_dim=6"),
    ],
)
def test_from_pose_fn_bad_inputs(fn_n_over, match):
    fn, n, over = fn_n_over
    with pytest.raises(ValueError, match=match):
        from_pose_fn(fn, n, **_good_kwargs(**over))


# ------------------------------------------------------------------ from_mjcf
SMALL_XML = """
<mujoco>
  <compiler angle="radian"/>
  <worldbody>
    <body name="a" pos="0.1 0.2 0.3" quat="0.9 0.1 -0.3 0.2">
      <joint name="h1" type="hinge" axis="0.3 0.5 0.8" pos="0.05 0 0.02" range="-2 2"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03"/>
      <body name="b" pos="0.4 0 0" euler="0.3 0.2 0.1">
        <joint name="s1" type="slide" axis="1 0 0.5" range="-0.2 0.2"/>
        <joint name="h2" type="hinge" axis="0 1 0" pos="0 0.03 0"/>
        <geom type="sphere" size="0.05"/>
        <site name="tip" pos="0.1 0.05 0" euler="0.5 -0.4 0.2"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.slow
def test_from_mjcf_chain_and_mjx_match_mujoco_on_a_general_tree():
    # Offset hinge anchors, a slide, tilted axes, rotated bodies and site.
    mj = mujoco.MjModel.from_xml_string(SMALL_XML)
    qs = np.random.default_rng(7).uniform([-2, -0.2, -3], [2, 0.2, 3], size=(5, 3))
    p_ref, R_ref, jacp, jacr = mj_site_jacobian(mj, qs, site="tip")
    box = dict(sample_low=[-1.0, -0.1, -1.0], sample_high=[1.0, 0.1, 1.0])
    chain = from_mjcf(SMALL_XML, "tip", actuators="joints", task_dim=6, m_a=0.02, fk="chain", **box)
    assert chain.n_act == 3
    np.testing.assert_allclose(chain.q_low, [-2, -0.2, -np.inf])
    p, R, J, _, _ = evaluate(chain, qs)
    np.testing.assert_allclose(p, p_ref, atol=1e-12)
    np.testing.assert_allclose(R, R_ref, atol=1e-12)
    np.testing.assert_allclose(J[:, :3], jacp, atol=JAC_TOL)
    np.testing.assert_allclose(J[:, 3:], jacr, atol=JAC_TOL)
    # The MJX path: pose and one Jacobian-vector product (cheaper to compile
    # than jacfwd through mjx.kinematics).
    mjx_sys = from_mjcf(SMALL_XML, "tip", actuators="joints", task_dim=6, m_a=0.02, fk="mjx", **box)
    v = np.array([0.3, -0.7, 0.5])

    @jax.jit
    def pose_and_jvp(system, q):
        ref = jax.lax.stop_gradient(system.pose(q))
        V, dV = jax.jvp(lambda q_: system.task_difference(system.pose(q_), ref), (q,), (v,))
        return system.pose(q), dV

    (p_m, R_m), dV = pose_and_jvp(mjx_sys, qs[0])
    np.testing.assert_allclose(p_m, p_ref[0], atol=1e-12)
    np.testing.assert_allclose(R_m, R_ref[0], atol=1e-12)
    np.testing.assert_allclose(dV, np.concatenate([jacp[0] @ v, jacr[0] @ v]), atol=JAC_TOL)


def test_from_mjcf_errors(tmp_path):
    with pytest.raises(ValueError, match="site 'nope' not found.*ur5e.xml"):
        from_mjcf(UR5E_XML, "nope", task_dim=3, m_a=0.02)
    missing = tmp_path / "missing.xml"
    with pytest.raises(ValueError, match="missing.xml"):
        from_mjcf(missing, "ee", task_dim=3, m_a=0.02)
    ball = (
        "<mujoco><worldbody><body><joint name='b' type='ball'/><geom size='.1'/><body><joint name='h'/>"
        "<geom size='.1'/><site name='s'/></body></body></worldbody></mujoco>"
    )
    with pytest.raises(ValueError, match="'b' is a ball joint on the kinematic chain of site 's'"):
        from_mjcf(ball, "s", actuators="joints", task_dim=3, m_a=0.02)
    with pytest.raises(ValueError, match="no actuators .*actuators='joints'"):
        from_mjcf(ball, "s", task_dim=3, m_a=0.02)
    with pytest.raises(ValueError, match="fk must be"):
        from_mjcf(UR5E_XML, "ee", task_dim=3, m_a=0.02, fk="dh")
    with pytest.raises(ValueError, match="task_dim"):
        from_mjcf(UR5E_XML, "ee", task_dim=5, m_a=0.02)
    with pytest.raises(ValueError, match="site must be"):
        from_mjcf(UR5E_XML, 0, task_dim=3, m_a=0.02)


def test_ur5e_asset_and_metadata(ur6):
    assert os.path.isfile(UR5E_XML)
    mj = mujoco.MjModel.from_xml_path(UR5E_XML)
    np.testing.assert_allclose(mj.body_mass[1:], [3.761, 8.058, 2.846, 1.37, 1.3, 0.365])
    assert (ur6.n_act, ur6.task_dim, ur6.name) == (6, 6, "ur5e")
    np.testing.assert_allclose(ur6.q_high, 2 * np.pi)
    assert ur5e().task_dim == 3
    with pytest.raises(ValueError, match="task_dim"):
        ur6.with_task_dim(4)


def test_builtin_registry_is_the_one_list_configs_and_the_cli_read():
    from selfid_jax.experiments.common import specs

    from selfid_jax import systems

    assert specs.BUILTIN_FACTORIES == tuple(systems.REGISTRY) == tuple(systems.BUILTIN)
    assert specs.X64_BUILTINS == {"stewart_hand", "model_o"}
    assert all(systems.BUILTIN[n].endswith("[float64]") for n in specs.X64_BUILTINS)
    for name, task_dim in (("two_link", 2), ("ur5e", 3), ("ur5e_6d", 6), ("arm5", 3)):
        assert specs.build_system(name).task_dim == task_dim
    with pytest.raises(ValueError, match="built-in: two_link, ur5e, ur5e_6d, stewart_hand, model_o, arm5"):
        specs.build_system("panda")


# ------------------------------------------------------------- jit and vmap
@pytest.mark.slow
@pytest.mark.parametrize("which", ["ur5e", "two_link", "three_link"])
def test_vmap_inverse_jacobian_equals_loop(which, ur6, ur_samples, arm2, arm3):
    if which == "ur5e":
        s, qs = ur6, ur_samples[0]
    else:
        s = {"two_link": arm2, "three_link": arm3}[which]
        qs = sample(s, jax.random.key(5), k=TL_B if which == "two_link" else UR_B)
    batched = evaluate(s, qs)[3]  # jit(vmap(...)) of true_inverse_jacobian (among others)
    single = jax.jit(System.true_inverse_jacobian)
    for i in range(4):
        np.testing.assert_allclose(batched[i], single(s, qs[i]), atol=1e-12)


def test_system_is_a_pytree_through_jit_without_retracing(arm2):
    s = arm2
    leaves, treedef = jax.tree_util.tree_flatten(s)
    assert len(leaves) == 7  # params (link lengths) + 6 limit arrays

    @jax.jit
    @chex.assert_max_traces(n=1)
    def step(system, q, dtheta):
        return system.apply(q, dtheta), system.true_inverse_jacobian(q), system.m_a

    q = jnp.array([0.3, 1.0])
    assert s.m_a.shape == (2,)  # a scalar m_a is broadcast to one value per actuator
    for m_a, dq in [(0.01, 0.1), (0.02, 0.2), (0.05, 0.05)]:  # data fields: no retrace
        sys_i = s.replace(m_a=jnp.full(2, m_a, s.m_a.dtype), dq_max=jnp.full(2, dq, s.dq_max.dtype))
        q_new, Jinv, m = step(sys_i, q, jnp.array([1.0, -1.0]))
        np.testing.assert_allclose(q_new, q + np.array([dq, -dq]))
        np.testing.assert_allclose(m, m_a)
    np.testing.assert_allclose(Jinv, jax.jit(s.true_inverse_jacobian)(q), atol=1e-12)
    # a system built separately hashes equal (module-level pose fn): no retrace either
    step(two_link(l1=0.9), q, jnp.zeros(2))


def test_vmap_over_system_fields(arm2):
    lengths = jnp.array([[1.0, 1.0], [0.5, 2.0], [2.0, 0.3]])
    axes = jax.tree_util.tree_map(lambda _: None, arm2)
    axes = dataclasses.replace(axes, params=0)
    tips = jax.jit(jax.vmap(lambda system: system.pose(jnp.zeros(2))[0], in_axes=(axes,)))(arm2.replace(params=lengths))
    np.testing.assert_allclose(tips[:, 0], lengths.sum(axis=1))


@pytest.mark.slow
def test_mjx_model_is_a_traced_pytree(ur_mjx):
    leaves = jax.tree_util.tree_leaves(ur_mjx)
    assert all(isinstance(x, jax.Array) for x in leaves)
    assert len(leaves) > 7  # the mjx.Model's arrays are leaves
    q = random_q(6, 1, seed=8)[0]
    np.testing.assert_allclose(pose_one(ur_mjx, q)[0], dh_fk(q)[0], atol=POS_TOL)  # same compiled fn


@pytest.mark.slow
def test_vmap_over_chain_model_field(ur6):
    # A sweep over the flange offset: vmap over one field of the ChainModel in
    # params (the chain FK reads site_pos with the MjModel's indexing).
    q = random_q(6, 1, seed=9)[0]
    site_pos = jnp.stack([ur6.params.site_pos, ur6.params.site_pos + jnp.array([[0.0, 0.0, 0.1]])])
    axes = jax.tree_util.tree_map(lambda _: None, ur6)
    axes = dataclasses.replace(axes, params=axes.params.replace(site_pos=0))
    batched = ur6.replace(params=ur6.params.replace(site_pos=site_pos))
    p = jax.jit(jax.vmap(lambda system: system.pose(jnp.asarray(q))[0], in_axes=(axes,)))(batched)
    R = dh_fk(q)[1]
    np.testing.assert_allclose(p[1] - p[0], 0.1 * R[:, 2], atol=1e-12)


def test_small_inverse_matches_numpy_and_flags_singular_matrices():
    from selfid_jax.math import linalg

    small_inverse = jax.jit(linalg.small_inverse)
    rng = np.random.default_rng(3)
    for k in (1, 2, 3):
        A = rng.normal(size=(k, k))
        np.testing.assert_allclose(small_inverse(jnp.asarray(A)), np.linalg.inv(A), rtol=1e-10)
        S = A.copy()
        S[-1] = 2.0 * S[0] if k > 1 else 0.0  # rank-deficient
        assert np.all(np.isnan(small_inverse(jnp.asarray(S))))
