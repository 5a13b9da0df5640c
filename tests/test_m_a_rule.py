"""One m_a rule in every experiment (experiments/common/schema.py resolve_m_a): the system's own m_a (scalar or
per actuator) unless the experiment's m_a key overrides it; checked on the built parts (params and meta), no run."""

import numpy as np
import pytest
from selfid_jax.experiments.common.schema import m_a_summary, resolve_m_a

from selfid_jax import runner as experiment
from selfid_jax.systems.two_link import two_link

ARM = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body name="l1">
      <joint name="j1" type="hinge" axis="0 0 1"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="1"/>
      <body name="l2" pos="0.3 0 0">
        <joint name="j2" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.02" mass="1"/>
        <body name="l3" pos="0.25 0 0">
          <joint name="j3" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" mass="1"/>
          <site name="tip" pos="0.2 0 0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position joint="j1" kp="50"/>
    <position joint="j2" kp="50"/>
    <position joint="j3" kp="50"/>
  </actuator>
</mujoco>
"""

PER_ACTUATOR = [0.02, 0.03, 0.05]
PATH = {"kind": "star", "size": 0.02}
CONTROLLER = {"max_step": 0.002, "tol": 0.0005, "steps": 200}


@pytest.fixture(scope="module")
def user_arm(tmp_path_factory):
    path = tmp_path_factory.mktemp("robot") / "arm3.xml"
    path.write_text(ARM)
    return {"mjcf": str(path), "site": "tip", "task_dim": 3, "m_a": PER_ACTUATOR, "home": [0.0, 0.6, -1.0],
            "sample_half_width": 0.2, "min_sigma": 0.01}


def _rows(part, field="m_a"):
    return np.asarray(getattr(part.params, field))


def _check(part, expected, source, prefix=""):
    m_a = _rows(part, f"{prefix}m_a" if prefix else "m_a")
    assert m_a.shape == (len(part.meta), len(expected))
    np.testing.assert_allclose(m_a, np.broadcast_to(expected, m_a.shape), rtol=0, atol=0)
    assert m_a_summary(part.meta, prefix) == {"m_a": expected if len(set(expected)) > 1 else expected[0],
                                              "m_a_source": source}


def test_resolve_m_a_rule():
    arm = two_link()
    assert resolve_m_a(None, arm).source == "system"
    np.testing.assert_array_equal(resolve_m_a(None, arm).value, [0.05, 0.05])
    np.testing.assert_array_equal(resolve_m_a(0.01, arm).value, [0.01, 0.01])
    assert resolve_m_a([0.01, 0.02], arm).summary() == {"m_a": [0.01, 0.02], "m_a_source": "config"}
    with pytest.raises(ValueError, match="3 values for the 2 actuators"):
        resolve_m_a([0.01, 0.02, 0.03], arm)


@pytest.mark.slow  # builds (feasible starts) every experiment's part
def test_user_per_actuator_m_a_reaches_every_experiment(user_arm):
    common = dict(system=user_arm, path=PATH, controller=CONTROLLER, n_configs=1)
    exp = experiment.get("tracking")
    _check(exp.build(exp.config(**common)), PER_ACTUATOR, "system")
    _check(exp.build(exp.config(**common, m_a=0.01)), [0.01] * 3, "config")

    exp = experiment.get("ablation")
    ablation = dict(common, methods=[{"name": "ours", "method": "ours"}], iterations=[2, 4], n_trials=1,
                    pose_noise=[0.0], rot_noise=[0.0], eps=0.5)
    part = exp.build(exp.config(**ablation))
    np.testing.assert_array_equal(_rows(part), np.broadcast_to(PER_ACTUATOR, (len(part.meta), 3)))
    assert set(part.meta["m_a_source"]) == {"system"}
    part = exp.build(exp.config(**ablation, m_a=[0.01, [0.01, 0.02, 0.04]]))
    np.testing.assert_array_equal(np.unique(_rows(part), axis=0), [[0.01] * 3, [0.01, 0.02, 0.04]])
    assert sorted(set(np.round(part.meta["m_a"], 12))) == [0.01, round(float(np.cbrt(0.01 * 0.02 * 0.04)), 12)]

    exp = experiment.get("demo")
    run = dict(system=user_arm, n_configs=1, path=PATH, controller=CONTROLLER)
    (part,) = exp.build(exp.config(runs=[run]))
    _check(part, PER_ACTUATOR, "system")
    (part,) = exp.build(exp.config(runs=[dict(run, m_a=[0.01, 0.01, 0.02])]))
    _check(part, [0.01, 0.01, 0.02], "config")

    exp = experiment.get("design")
    cfg = dict(systems=[user_arm], path=PATH, controller=CONTROLLER, n_configs=1, pose_noise=[0.0],
               m_a_grid={"start": 0.01, "stop": 0.1, "num": 2})
    (part,) = exp.build(exp.config(**cfg))
    np.testing.assert_array_equal(_rows(part, "default_m_a"), [PER_ACTUATOR])
    (part,) = exp.build(exp.config(**dict(cfg, systems=[{"system": user_arm, "m_a": 0.04}])))
    np.testing.assert_array_equal(_rows(part, "default_m_a"), [[0.04] * 3])


@pytest.mark.slow  # the fixed robots of peg-in-hole (UR5e + Model O) and the articulated study (UR5e)
def test_fixed_robot_experiments_take_the_system_m_a_or_the_key():
    exp = experiment.get("peg_in_hole")
    base = dict(layouts=[{"yaw": 0.1, "grasp": [0.03, 0.0, -0.03], "hole": [0.05, 0.02]}],
                arm={"iters": 4, "eps": 0.5, "controller": {"steps": 10}},
                hand={"iters": 4, "eps_rel": 0.05, "controller": {"max_step": 0.0001, "tol": 0.00005, "steps": 5}})
    part = exp.build(exp.config(**base))
    _check(part, [0.03] * 6, "system", "arm_")
    _check(part, [0.0003] * 3, "system", "hand_")
    arm = [0.01, 0.02, 0.03, 0.03, 0.02, 0.01]
    part = exp.build(exp.config(**dict(base, arm=dict(base["arm"], m_a=arm))))
    _check(part, arm, "config", "arm_")
    with pytest.raises(ValueError, match="hand.m_a: 2 values for the 3 actuators"):
        exp.build(exp.config(**dict(base, hand=dict(base["hand"], m_a=[0.001, 0.002]))))

    exp = experiment.get("articulated")
    cfg = dict(objects={"prismatic": 1, "revolute": 0, "helical": 0, "bezier": 0}, controllers=["tacman"],
               arms=["selfid"], max_time=0.1, trace_points=2, selfid_iters=4)
    (part,) = exp.build(exp.config(**cfg))
    _check(part, [0.03] * 6, "system")
    (part,) = exp.build(exp.config(**cfg, m_a=arm))
    _check(part, arm, "config")
