"""Robot files as they come: a URDF with a fixed-joint tool link, a model without sites (POM = body + offset),
keyframes as home, and qpos0 outside a joint's range; Jacobians checked against MuJoCo's own ``mj_jac``."""

from __future__ import annotations

import textwrap
import warnings

import mujoco
import numpy as np
import pytest
from helpers_mjcf import URDF  # tests/ is on the path
from helpers_mjcf import body_point_jacobian as _body_point_jacobian

from selfid_jax.systems.mjcf import POM_SITE, from_mjcf

# Two hinges, no site, a 'home' keyframe and a second keyframe; qpos0 of j2 (0) is outside its range [0.2, 2].
SITELESS = textwrap.dedent("""\
    <mujoco model="siteless">
      <compiler angle="radian"/>
      <worldbody>
        <body name="link1" pos="0 0 0.1">
          <joint name="j1" type="hinge" axis="0 0 1" range="-3 3"/>
          <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02"/>
          <body name="link2" pos="0.3 0 0">
            <joint name="j2" type="hinge" axis="0 1 0" range="0.2 2"/>
            <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.02"/>
            <body name="hand" pos="0.25 0 0"><geom type="sphere" size="0.02"/></body>
          </body>
        </body>
      </worldbody>
      <actuator><position name="a1" joint="j1"/><position name="a2" joint="j2"/></actuator>
      <keyframe>
        <key name="home" qpos="0.4 0.9"/>
        <key name="low" qpos="-0.5 0.5"/>
      </keyframe>
    </mujoco>
    """)





@pytest.mark.slow
def test_urdf_loads_with_its_tool_link_and_matches_mujocos_jacobian(tmp_path):
    path = tmp_path / "arm3.urdf"
    path.write_text(URDF)
    offset = (0.0, 0.0, 0.03)
    system = from_mjcf(path, body="tool", offset=offset, actuators="joints", task_dim=6, m_a=0.02)
    spec = mujoco.MjSpec.from_file(str(path))
    spec.compiler.fusestatic = False  # the reference keeps the tool link too, without any site
    model = spec.compile()
    assert system.n_act == 3 and "tool" in [model.body(i).name for i in range(model.nbody)]
    for q in (np.array([0.3, -0.4, 0.8]), np.array([-1.0, 0.7, -1.2])):
        point, J = _body_point_jacobian(model, q, "tool", offset)
        np.testing.assert_allclose(np.asarray(system.pose(q)[0]), point, atol=1e-12)
        np.testing.assert_allclose(np.asarray(system.jacobian(q)), J, atol=1e-10)
    np.testing.assert_allclose(np.asarray(system.q_low), [-3, -2, -2.5])  # the URDF's joint limits
    # from an XML string too, and the plain compiler would have fused the tool link away
    assert "tool" not in [mujoco.MjModel.from_xml_path(str(path)).body(i).name
                          for i in range(mujoco.MjModel.from_xml_path(str(path)).nbody)]
    s2 = from_mjcf(URDF, body="tool", offset=offset, actuators="joints", task_dim=3, m_a=0.02)
    q = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(np.asarray(s2.pose(q)[0]), np.asarray(system.pose(q)[0]), atol=1e-12)


@pytest.mark.slow
def test_body_and_offset_replace_a_missing_site_and_errors_name_the_way_forward():
    offset = (0.05, 0.0, 0.01)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the 'home' keyframe is used: no qpos0 warning
        system = from_mjcf(SITELESS, body="hand", offset=offset, task_dim=3, m_a=0.02)
    model = mujoco.MjModel.from_xml_string(SITELESS)
    q = np.array([0.4, 1.1])
    point, J = _body_point_jacobian(model, q, "hand", offset)
    np.testing.assert_allclose(np.asarray(system.pose(q)[0]), point, atol=1e-12)
    np.testing.assert_allclose(np.asarray(system.jacobian(q))[:3], J[:3], atol=1e-10)
    assert POM_SITE == "selfid_jax_pom"
    with pytest.raises(ValueError, match=r"site 'tip' not found.*sites are \[\].*body='name'.*'hand'"):
        from_mjcf(SITELESS, "tip", task_dim=3, m_a=0.02)
    with pytest.raises(ValueError, match=r"body 'palm' not found.*\['link1', 'link2', 'hand'\]"):
        from_mjcf(SITELESS, body="palm", task_dim=3, m_a=0.02)
    with pytest.raises(ValueError, match="exactly one of them"):
        from_mjcf(SITELESS, "x", body="hand", task_dim=3, m_a=0.02)
    with pytest.raises(ValueError, match="compiled mujoco.MjModel cannot gain a site"):
        from_mjcf(model, body="hand", task_dim=3, m_a=0.02)


def test_home_comes_from_keyframes_and_qpos0_outside_a_range_is_named():
    from selfid_jax.systems.mjcf import HINGE_HALF_WIDTH

    home = np.array([0.4, 0.9])  # the 'home' keyframe, used by default
    s = from_mjcf(SITELESS, body="hand", task_dim=3, m_a=0.02)
    np.testing.assert_allclose(np.asarray(s.sample_low), np.maximum([-3, 0.2], home - HINGE_HALF_WIDTH))
    np.testing.assert_allclose(np.asarray(s.sample_high), np.minimum([3, 2], home + HINGE_HALF_WIDTH))
    low = from_mjcf(SITELESS, body="hand", task_dim=3, m_a=0.02, home={"keyframe": "low"})
    np.testing.assert_allclose(np.asarray(low.sample_low), np.maximum([-3, 0.2], [-1.0, 0.0]))
    with pytest.raises(ValueError, match=r"keyframe 'rest' not found.*\['home', 'low'\]"):
        from_mjcf(SITELESS, body="hand", task_dim=3, m_a=0.02, home={"keyframe": "rest"})
    no_keys = SITELESS.split("<keyframe>")[0] + "</mujoco>\n"
    with pytest.warns(UserWarning, match=r"qpos0 puts actuator 'a2' at 0 outside \[0.2, 2\]; home is clipped"):
        from_mjcf(no_keys, body="hand", task_dim=3, m_a=0.02)


def test_configs_accept_body_offset_joints_and_keyframes(tmp_path):
    import pydantic
    from selfid_jax.experiments.common.specs import MjcfSystem, build_system

    (tmp_path / "arm3.urdf").write_text(URDF)
    (tmp_path / "siteless.xml").write_text(SITELESS)
    ctx = {"config_dir": str(tmp_path)}
    urdf = MjcfSystem.model_validate({"mjcf": "arm3.urdf", "body": "tool", "offset": [0, 0, 0.03],
                                      "actuators": "joints", "task_dim": 3}, context=ctx)
    assert build_system(urdf).n_act == 3
    keyed = MjcfSystem.model_validate({"mjcf": "siteless.xml", "body": "hand", "home": {"keyframe": "low"}},
                                      context=ctx)
    np.testing.assert_allclose(np.asarray(build_system(keyed).sample_low), [-1.0, 0.2])
    for bad, words in (({"mjcf": "siteless.xml"}, "exactly one of them"),
                       ({"mjcf": "siteless.xml", "site": "s", "offset": [0, 0, 1]}, "'offset' needs 'body'"),
                       ({"mjcf": "siteless.xml", "body": "hand", "actuators": "all"}, "joints")):
        with pytest.raises(pydantic.ValidationError, match=words):
            MjcfSystem.model_validate(bad, context=ctx)
