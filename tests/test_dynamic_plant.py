"""The dynamic plant (selfid_jax.control.realism.dynamic_plant) in the follow loop, the self-ID sampler and configs.

A plant whose actuators reach every target reproduces the kinematic loop bit
for bit through the hook (fast); the UR5e's MJX servos in the follow loop
agree with a closed loop written here on native ``mj_step`` (slow: one
program, jitted and vmapped over two starts; its plant is the one a
``realism: {plant: dynamic}`` section builds); such a section is checked
before any compute and builds the file's servos with its gains. x64 is on
(conftest).
"""

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pydantic
import pytest
from selfid_jax.experiments.common import realism as realistic
from selfid_jax.experiments.tracking import TrackingConfig

from selfid_jax import control
from selfid_jax.control import loop
from selfid_jax.control import realism as realism_lib
from selfid_jax.identify import algorithm as selfid
from selfid_jax.systems.two_link import two_link
from selfid_jax.systems.ur5e import UR5E_HOME, UR5E_XML, ur5e

KP, KV = 5000.0, 300.0  # stiffer servos than the file's, so the short path completes
SUBSTEPS = 4  # 0.008 s control period at dt 0.002 s
STEPS = 150
PATH = np.array([[0.005, 0.0, 0.0], [0.005, 0.005, 0.0], [0.0, 0.005, 0.002]])  # m, offsets from the start


class ExactArm:
    """A plant model whose actuators reach every target within the control step (state = ``q``)."""

    n_act = 2
    name = "exact"

    def init(self, q0):
        return jnp.asarray(q0)

    def control_step(self, state, target, *, substeps):
        return jnp.asarray(target, state.dtype)

    def q(self, state):
        return state


@pytest.mark.slow
def test_exact_plant_reproduces_the_ideal_loop():
    system = two_link()
    q0 = jnp.asarray([0.3, 1.2])
    path = jnp.asarray([[0.05, 0.0], [0.05, 0.05], [0.0, 0.05]])
    plant = realism_lib.dynamic_plant(ExactArm(), 1)
    ideal = loop.follow(system, control.true_inverse(system), path, q0, steps=80, return_trajectory=True)
    hooked = loop.follow(system, control.true_inverse(system), path, q0, steps=80, return_trajectory=True, plant=plant)
    assert float(ideal.completion) == 1.0
    for name in ("completion", "mean_error", "max_error", "waypoint_error", "steps_used", "final_q", "positions"):
        np.testing.assert_array_equal(np.asarray(getattr(hooked, name)), np.asarray(getattr(ideal, name)), err_msg=name)


@pytest.mark.slow
def test_exact_plant_reproduces_ideal_self_id_samples():
    system = two_link()
    q0 = jnp.asarray([0.3, 1.2])
    key = jax.random.key(3)
    kw = dict(n_act=2, task_dim=2, iters=12)
    results = []
    for plant in (None, realism_lib.dynamic_plant(ExactArm(), 1)):
        observe, env0 = realism_lib.self_id_sampler(system, realism_lib.IDEAL, q0, plant=plant)
        results.append(selfid.self_identify(observe, key, 0.03, 0.5, env=env0, **kw))
    np.testing.assert_array_equal(np.asarray(results[1].estimate), np.asarray(results[0].estimate))
    np.testing.assert_array_equal(np.asarray(results[1].env.q), np.asarray(results[0].env.q))
    assert results[1].env.plant is not None and results[0].env.plant is None


def test_plant_arguments_are_checked():
    with pytest.raises(ValueError, match="substeps must be a positive integer"):
        realism_lib.dynamic_plant(ExactArm(), 0)
    with pytest.raises(TypeError, match="has no init"):
        realism_lib.dynamic_plant(object(), 1)
    with pytest.raises(TypeError, match="plant must be a realism.Plant"):
        loop.follow(two_link(), control.true_inverse(two_link()), jnp.zeros((1, 2)), jnp.zeros(2), plant=ExactArm())


def native_follow(J, q0, path, steps, tol=0.0005, max_step=0.0025, gain=1.0):
    """The follow loop's rule on native MuJoCo: each control step the flange error to the current waypoint,
    gained and clipped to ``max_step``, times the fixed ``J (6, 3)``, clipped to ``dq_max = 0.1`` rad, commanded
    as servo targets from the measured ``qpos``, then ``SUBSTEPS`` ``mj_step`` calls. Returns the flange
    positions at the start of each step until the last waypoint is reached ``(k, 3)`` and the waypoints reached."""
    m = mujoco.MjModel.from_xml_path(UR5E_XML)
    m.actuator_gainprm[:, 0] = KP
    m.actuator_biasprm[:, 1] = -KP
    m.actuator_biasprm[:, 2] = -KV
    m.body_gravcomp[1:] = 1.0
    m.flg_gravcomp = 1
    d = mujoco.MjData(m)
    d.qpos[:6] = q0
    d.ctrl[:] = q0
    site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "ee")
    mujoco.mj_kinematics(m, d)
    targets = d.site_xpos[site].copy() + path
    w, seen = 0, []
    for _ in range(steps):
        mujoco.mj_kinematics(m, d)
        p = d.site_xpos[site].copy()
        seen.append(p)
        if np.linalg.norm(targets[w] - p) <= tol:
            w += 1
            if w == len(targets):
                break
        e = gain * (targets[w] - p)
        V = e * min(1.0, max_step / np.linalg.norm(e))
        q = d.qpos[:6].copy()
        d.ctrl[:] = np.clip(q + np.clip(J @ V, -0.1, 0.1), -2 * np.pi, 2 * np.pi)
        for _ in range(SUBSTEPS):
            mujoco.mj_step(m, d)
    return np.array(seen), w


def native_jacobian_pinv(q0):
    m = mujoco.MjModel.from_xml_path(UR5E_XML)
    d = mujoco.MjData(m)
    d.qpos[:6] = q0
    mujoco.mj_forward(m, d)
    jac = np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jac, None, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "ee"))
    return np.linalg.pinv(jac[:, :6])


BASE = dict(experiment="tracking", system="ur5e", path={"kind": "star", "size": 0.02}, n_configs=1)


@pytest.mark.slow
def test_dynamic_follow_agrees_with_native_mujoco():
    """The plant a ``realism: {plant: dynamic}`` section builds (gains, gravity compensation, ``period / timestep``
    physics steps per control step) in the follow loop: the positions of a loop on native ``mj_step`` with those
    servos and SUBSTEPS physics steps, to 1e-9 m. (The section's builder is checked here, on the one MJX program
    of this module, rather than by compiling an MJX step of its own.)"""
    system = ur5e()
    cfg = TrackingConfig(**BASE, realism={"plant": "dynamic", "period": SUBSTEPS * 0.002, "kp": KP, "kv": KV,
                                          "gravcomp": 1.0})
    plant = realistic.plant(cfg.realism, cfg.system, system)
    arm = plant.q.__self__
    assert arm.timestep == 0.002 and arm.n_act == 6
    np.testing.assert_allclose(np.asarray(arm.model.actuator_gainprm[:, 0]), KP)
    np.testing.assert_allclose(np.asarray(arm.model.actuator_biasprm[:, 2]), -KV)
    np.testing.assert_allclose(np.asarray(arm.model.body_gravcomp[1:]), 1.0)
    starts = np.stack([np.asarray(UR5E_HOME), np.asarray(UR5E_HOME) + np.array([0.1, -0.1, 0.1, 0.0, 0.1, 0.0])])
    Js = np.stack([native_jacobian_pinv(q) for q in starts])

    @chex.assert_max_traces(n=1)
    def one(J, q0):
        return loop.follow(system, control.fixed(J), jnp.asarray(PATH), q0, steps=STEPS, return_trajectory=True,
                           plant=plant)

    res = jax.jit(jax.vmap(one))(jnp.asarray(Js), jnp.asarray(starts))
    # the kinematic loop from the same starts with the same J: one jitted call, not an eager loop per start
    kinematic = jax.jit(jax.vmap(lambda J, q0: loop.follow(system, control.fixed(J), jnp.asarray(PATH), q0,
                                                           steps=STEPS)))(jnp.asarray(Js), jnp.asarray(starts))
    for i in range(len(starts)):
        seen, reached = native_follow(Js[i], starts[i], PATH, STEPS)
        assert reached == len(PATH), "the reference itself must complete the path"
        assert float(res.completion[i]) == 1.0 and not bool(res.failed[i])
        k = len(seen)
        np.testing.assert_allclose(np.asarray(res.positions[i, :k]), seen, atol=1e-9, rtol=0)
        # the servos lag: the dynamic arm needs more control steps than the kinematic one
        assert int(kinematic.steps_used[i]) < int(res.steps_used[i])


# ------------------------------------------------------------------ configs


@pytest.mark.slow
def test_dynamic_section_validated_before_compute():
    ok = TrackingConfig(**BASE, realism={"plant": "dynamic", "period": 0.008, "kp": 2000.0})
    assert ok.realism.plant == "dynamic" and ok.realism.kp == 2000.0
    with pytest.raises(pydantic.ValidationError, match="needs one control period > 0"):
        TrackingConfig(**BASE, realism={"plant": "dynamic", "period": [0.004, 0.008]})
    with pytest.raises(pydantic.ValidationError, match="servo_tau belongs to plant 'servo'"):
        TrackingConfig(**BASE, realism={"plant": "dynamic", "period": 0.008, "servo_tau": 0.02})
    with pytest.raises(pydantic.ValidationError, match="kp applies to plant 'dynamic' only"):
        TrackingConfig(**BASE, realism={"period": 0.008, "kp": 100.0})
    hand = TrackingConfig(**{**BASE, "system": "two_link"}, realism={"plant": "dynamic", "period": 0.008})
    with pytest.raises(ValueError, match="needs an arm whose actuators are position servos"):
        realistic.plant(hand.realism, hand.system, two_link())
    odd = TrackingConfig(**BASE, realism={"plant": "dynamic", "period": 0.003})
    with pytest.raises(ValueError, match="not a whole number of the model's physics steps"):
        realistic.plant(odd.realism, odd.system, ur5e())


@pytest.mark.slow
def test_dynamic_section_builds_the_files_servos():
    """The section's gains and gravity compensation reach the file's servos. That a control step is ``period /
    timestep`` physics steps of them is checked by test_dynamic_follow_agrees_with_native_mujoco, whose plant this
    builder makes (one MJX program for both)."""
    cfg = TrackingConfig(**BASE, realism={"plant": "dynamic", "period": 0.01, "kp": 2000.0, "kv": 100.0,
                                          "gravcomp": 0.5})
    plant = realistic.plant(cfg.realism, cfg.system, ur5e())
    arm = plant.q.__self__
    assert arm.n_act == 6
    np.testing.assert_allclose(np.asarray(arm.model.actuator_gainprm[:, 0]), 2000.0)
    np.testing.assert_allclose(np.asarray(arm.model.actuator_biasprm[:, 2]), -100.0)
    np.testing.assert_allclose(np.asarray(arm.model.body_gravcomp[1:]), 0.5)
