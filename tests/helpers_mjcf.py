"""Robot files the tests share, with MuJoCo's Jacobian of a body point (``mj_jac``, no site involved).

The tendon arm MJCF of tests/test_mjcf.py and tests/test_user_robot.py (a Menagerie-style model with an implicit
integrator, joint, servo and tendon actuators, an equality, held joints and a free-floating box) and the URDF arm of
tests/test_robot_files.py (also driven by test_user_robot and test_robot_sim).
"""

import textwrap

import mujoco
import numpy as np

# A 3-hinge arm (j1 yaw, j2/j3 pitch), a passive hinge jf = 0.5 j3 (joint equality), a wrist pair ja/jb
# driven by one actuator on the fixed tendon 'pair' (length ja + 0.5 jb; ja has ref 0.2, so qpos0 = 0.2),
# an unactuated hinge jh (held by joints_fixed) and slide ext (held at qpos0 = ref = 0.01), the tip site,
# a finger slide off the site's chain, a site-transmission actuator (unsupported: skipped), and a free box
# (7 qpos before the arm). Actuators: a1 position servo (ctrlrange narrower than the joint range),
# a2 Menagerie-style <general> servo, a3 motor (ctrlrange is a torque), a_pair position servo on the tendon.
TENDON_ARM_XML = """
<mujoco model="tendon_arm">
  <compiler angle="radian" autolimits="true"/>
  <option integrator="implicit" timestep="0.002" density="1.2" viscosity="1e-5"/>
  <default><joint damping="0.5"/><geom size="0.03"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="box" pos="0.6 0.4 0.1">
      <joint name="box_free" type="free"/>
      <geom type="box" size="0.05 0.05 0.05"/>
      <site name="box_site"/>
    </body>
    <body name="base" pos="0 0 0.1">
      <joint name="j1" axis="0 0 1" range="-2.5 2.5"/>
      <geom type="cylinder" size="0.05 0.05"/>
      <body name="upper" pos="0 0 0.1" euler="0.1 0 0">
        <joint name="j2" axis="0 1 0" range="-2 2"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0"/>
        <body name="fore" pos="0.3 0 0">
          <joint name="j3" axis="0 1 0" range="-2 2"/>
          <geom type="capsule" fromto="0 0 0 0.2 0 0"/>
          <body name="passive" pos="0.2 0 0">
            <joint name="jf" axis="0 0 1" pos="0.01 0 0" range="-0.5 0.5"/>
            <joint name="ext" type="slide" axis="1 0 0" ref="0.01" range="-0.05 0.05"/>
            <geom type="capsule" fromto="0 0 0 0.06 0 0"/>
            <body name="wrist" pos="0.06 0 0">
              <joint name="ja" axis="0 1 0" ref="0.2" range="-1 1"/>
              <geom type="sphere"/>
              <body name="hand" pos="0.05 0 0" quat="0.9 0.1 0.3 -0.2">
                <joint name="jb" axis="1 0 0" range="-1 1"/>
                <joint name="jh" axis="0 0 1" pos="0 0.01 0"/>
                <geom type="box" size="0.02 0.03 0.01"/>
                <site name="tip" pos="0.08 0.01 0.02" euler="0.2 -0.1 0.3"/>
                <body name="finger" pos="0.03 0 0">
                  <joint name="finger" type="slide" axis="0 1 0" range="0 0.04"/>
                  <geom type="box" size="0.01 0.01 0.02"/>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon>
    <fixed name="pair"><joint joint="ja" coef="1"/><joint joint="jb" coef="0.5"/></fixed>
  </tendon>
  <equality>
    <joint name="follow" joint1="jf" joint2="j3" polycoef="0 0.5 0 0 0"/>
  </equality>
  <actuator>
    <position name="a1" joint="j1" kp="100" ctrlrange="-2 2"/>
    <general name="a2" joint="j2" biastype="affine" gainprm="200" biasprm="0 -200 -20" ctrlrange="-1.5 1.5"/>
    <motor name="a3" joint="j3" ctrlrange="-5 5"/>
    <position name="a_pair" tendon="pair" kp="50" ctrlrange="-1 1"/>
    <motor name="a_finger" joint="finger" ctrlrange="-1 1"/>
    <general name="a_site" site="tip" gear="0 0 1 0 0 0"/>
  </actuator>
</mujoco>
"""

URDF = textwrap.dedent("""\
    <robot name="arm3">
      <link name="base"/>
      <link name="l1"><inertial><origin xyz="0 0 0.1"/><mass value="1"/>
        <inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
      <link name="l2"><inertial><origin xyz="0.15 0 0"/><mass value="1"/>
        <inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
      <link name="l3"><inertial><origin xyz="0.1 0 0"/><mass value="0.5"/>
        <inertia ixx="0.005" iyy="0.005" izz="0.005" ixy="0" ixz="0" iyz="0"/></inertial></link>
      <link name="tool"/>
      <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.1"/>
        <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="10" velocity="1"/></joint>
      <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0 0 0.2"/>
        <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="10" velocity="1"/></joint>
      <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0.3 0 0"/>
        <axis xyz="0 1 0"/><limit lower="-2.5" upper="2.5" effort="10" velocity="1"/></joint>
      <joint name="flange" type="fixed"><parent link="l3"/><child link="tool"/><origin xyz="0.25 0 0.02"/></joint>
    </robot>
    """)


def body_point_jacobian(model: mujoco.MjModel, qpos, body: str, offset) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's own position and (3, nv) Jacobian of a point fixed in ``body`` (mj_jac, no site involved)."""
    d = mujoco.MjData(model)
    d.qpos[:] = qpos
    mujoco.mj_forward(model, d)
    b = model.body(body).id
    point = d.xpos[b] + d.xmat[b].reshape(3, 3) @ np.asarray(offset, float)
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    mujoco.mj_jac(model, d, jacp, jacr, point, b)
    return point, np.vstack([jacp, jacr])
