"""Dynamic UR5e (selfid_jax.systems.dynamic): MJX servos against native MuJoCo, lag and overshoot, jit/vmap.

One compiled program (module fixture, ~30 s to trace and compile on 2 shared
cores, hence ``slow``) rolls out a batch of 6 rows, each its own arm (gains /
gravity compensation through ``with_servo``) and step-and-hold target
sequence: 3 arms x 2 sequences, 200 control steps of 10 physics steps (0.02 s
period, 4 s). Every row is compared with native ``mj_step`` on an
independently built ``MjModel`` (the reference lives here, not in the
library). x64 is on (conftest).
"""

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from selfid_jax.systems.dynamic import DynamicArm, Trace, dynamic_arm, dynamic_ur5e, substeps_for
from selfid_jax.systems.ur5e import UR5E_HOME, UR5E_XML, ur5e

SUBSTEPS = 10  # physics steps per control step: 0.02 s at dt 0.002 s
STEPS = 200  # control steps (4 s)
HOLD = 100  # the second target of each sequence starts at this control step
PARITY_Q = 1e-10  # rad: MJX float64 qpos vs native over the whole rollout (measured ~1e-15)
PARITY_P = 1e-10  # m: site position vs native
Q0 = np.asarray(UR5E_HOME)

# arms: (kp, kv, gravcomp) -- the shipped servos sagging under gravity, with gravity compensation, underdamped
# one worker runs the module: its compiled rollout (the `batched` fixture) is built once, not once per worker
pytestmark = pytest.mark.xdist_group("dynamic_arm")

ARMS = np.array([(500.0, 50.0, 0.0), (500.0, 50.0, 1.0), (500.0, 10.0, 1.0)])
STEP_A = np.array([0.05, 0.05, 0.05, 0.05, 0.05, 0.05])  # rad, per joint
STEP_B = np.array([0.1, -0.1, 0.1, 0.1, -0.1, 0.1])


def _targets(first, second):
    u = np.tile(Q0 + first, (STEPS, 1))
    u[HOLD:] = Q0 + second
    return u


SEQUENCES = np.stack([_targets(STEP_A, STEP_A), _targets(STEP_B, np.zeros(6))])  # (2, STEPS, 6)
ROWS = [(a, b) for a in range(len(ARMS)) for b in range(len(SEQUENCES))]  # the batch: (arm, sequence) pairs


def _row(a, b):
    return ROWS.index((a, b))


def native_rollout(kp, kv, gravcomp, q0, targets, substeps):
    """Reference: ``mj_step`` on a fresh MjModel of the shipped file; ``(q (T, 6), p (T, 3), R (T, 3, 3))``."""
    m = mujoco.MjModel.from_xml_path(UR5E_XML)
    m.actuator_gainprm[:, 0] = kp
    m.actuator_biasprm[:, 1] = -kp
    m.actuator_biasprm[:, 2] = -kv
    if gravcomp:
        m.body_gravcomp[1:] = gravcomp
        m.flg_gravcomp = 1
    d = mujoco.MjData(m)
    d.qpos[:] = q0
    qs, ps, Rs = [], [], []
    for u in targets:
        d.ctrl[:] = u
        for _ in range(substeps):
            mujoco.mj_step(m, d)
        qs.append(d.qpos.copy())
        mujoco.mj_kinematics(m, d)
        ps.append(d.site_xpos[0].copy())
        Rs.append(d.site_xmat[0].reshape(3, 3).copy())
    return np.array(qs), np.array(ps), np.array(Rs)


@pytest.fixture(scope="module")
def arm():
    return dynamic_ur5e(gravcomp=0.0)  # the term compiled in, so gravcomp can be batched


@pytest.fixture(scope="module")
def batched(arm):
    """``run(arms (B, 3), q0 (6,), targets (B, T, 6)) -> Trace (B, T, ...)`` compiled once, and its result on ROWS."""

    @chex.assert_max_traces(n=1)
    def one(a, q0, u):
        kp, kv, gc = a
        arm_i = arm.with_servo(kp=kp, kv=kv, gravcomp=gc)
        _, tr = arm_i.rollout(arm_i.init(q0), u, substeps=SUBSTEPS)
        return tr

    run = jax.jit(jax.vmap(one, in_axes=(0, None, 0)))
    arms = jnp.asarray(np.stack([ARMS[a] for a, _ in ROWS]))
    targets = jnp.asarray(np.stack([SEQUENCES[b] for _, b in ROWS]))
    tr = jax.tree.map(np.asarray, run(arms, jnp.asarray(Q0), targets))
    return run, tr, (arms, targets)


@pytest.fixture(scope="module")
def native():
    """Native references per row of ROWS: ``(q, p, R)``."""
    return [native_rollout(*ARMS[a], Q0, SEQUENCES[b], SUBSTEPS) for a, b in ROWS]


@pytest.mark.slow
def test_trace_shapes_and_dtype(batched):
    _, tr, _ = batched
    assert isinstance(tr, Trace)
    B = len(ROWS)
    assert tr.q.shape == (B, STEPS, 6) and tr.qd.shape == (B, STEPS, 6)
    assert tr.p.shape == (B, STEPS, 3) and tr.R.shape == (B, STEPS, 3, 3)
    assert tr.q.dtype == np.float64
    assert np.all(np.isfinite(tr.q))


@pytest.mark.slow
def test_matches_native_mujoco(batched, native):
    """Every batched rollout (3 arms x 2 sequences) equals native ``mj_step`` to PARITY_Q rad / PARITY_P m over 4 s."""
    _, tr, _ = batched
    dq = max(np.abs(tr.q[i] - native[i][0]).max() for i in range(len(ROWS)))
    dp = max(np.abs(tr.p[i] - native[i][1]).max() for i in range(len(ROWS)))
    dR = max(np.abs(tr.R[i] - native[i][2]).max() for i in range(len(ROWS)))
    print(f"MJX vs native over {STEPS * SUBSTEPS} physics steps: |dq| {dq:.2e} rad, |dp| {dp:.2e} m, |dR| {dR:.2e}")
    assert dq < PARITY_Q and dp < PARITY_P and dR < PARITY_P


@pytest.mark.slow
def test_shipped_arm_is_the_file_as_shipped(batched):
    """Arm 0 (gravcomp 0 compiled in) against the file untouched (no gravcomp term): the same numbers."""
    _, tr, _ = batched
    m = mujoco.MjModel.from_xml_path(UR5E_XML)
    assert m.flg_gravcomp == 0
    d = mujoco.MjData(m)
    d.qpos[:] = Q0
    d.ctrl[:] = SEQUENCES[1, 0]
    for _ in range(SUBSTEPS):
        mujoco.mj_step(m, d)
    np.testing.assert_allclose(tr.q[_row(0, 1), 0], d.qpos, rtol=0, atol=PARITY_Q)


@pytest.mark.slow
def test_observe_is_the_kinematic_site_pose(batched):
    """The site pose equals the kinematic UR5e's pose at the dynamic q (same site 'ee')."""
    _, tr, _ = batched
    i = _row(1, 1)
    p, R = jax.jit(jax.vmap(ur5e(task_dim=6).pose))(jnp.asarray(tr.q[i, ::20]))  # one program, not op by op
    np.testing.assert_allclose(tr.p[i, ::20], np.asarray(p), atol=1e-12)
    np.testing.assert_allclose(tr.R[i, ::20], np.asarray(R), atol=1e-12)


def _fraction(q, first):
    return (q - Q0) / first  # (T, 6) fraction of the step covered


@pytest.mark.slow
def test_lags_behind_a_step_then_converges(batched):
    """Gravity-compensated shipped servos: one control step covers only part of a 0.05 rad step; 1 s later < 1e-4 rad.

    The kinematic backend would be at the target after the first step.
    """
    _, tr, _ = batched
    q = tr.q[_row(1, 0)]
    frac = _fraction(q, STEP_A)
    assert np.all(frac[0] > 0.01) and np.all(frac[0] < 0.5), frac[0]
    after_1s = np.abs(q[49] - (Q0 + STEP_A)).max()
    assert after_1s < 1e-4, after_1s
    assert np.abs(q[HOLD - 1] - (Q0 + STEP_A)).max() < 1e-6


@pytest.mark.slow
def test_sags_without_gravity_compensation(batched):
    """The shipped servos (kp 500) hold the shoulder and elbow ~0.04 rad off a held target under gravity."""
    _, tr, _ = batched
    err = tr.q[_row(0, 0), HOLD - 1] - (Q0 + STEP_A)
    assert 0.02 < err[1] < 0.08 and 0.02 < err[2] < 0.08, err
    assert np.abs(err[[0, 5]]).max() < 1e-6  # base and last wrist joint carry no gravity torque at this pose


@pytest.mark.slow
def test_low_damping_overshoots(batched):
    """kv 10 (instead of 50) overshoots a step on every joint (>= 2.5%); the shipped kv 50 wrist joints do not."""
    _, tr, _ = batched
    peak_low = _fraction(tr.q[_row(2, 0), :HOLD], STEP_A).max(axis=0)
    peak_shipped = _fraction(tr.q[_row(1, 0), :HOLD], STEP_A).max(axis=0)
    assert np.all(peak_low > 1.02), peak_low
    assert np.all(peak_shipped[3:] < 1.0 + 1e-6), peak_shipped


@pytest.mark.slow
def test_one_compilation_serves_new_values(batched):
    """Other gains, start and targets (same shapes): no retrace (chex.assert_max_traces(n=1) inside)."""
    run, _, (arms, targets) = batched
    out = run(arms[::-1], jnp.asarray(Q0 + 0.01), targets[::-1])
    assert np.all(np.isfinite(np.asarray(out.q)))


@pytest.mark.slow
def test_step_fn_shape_for_the_control_loop(arm):
    """``step_fn(state, target) -> (state, q (6,), (p (3,), R (3, 3)))``, checked abstractly (no compilation)."""
    step = arm.step_fn(substeps=substeps_for(arm, 0.02))
    state = jax.eval_shape(arm.init, jnp.asarray(Q0))
    out_state, q, (p, R) = jax.eval_shape(step, state, jnp.asarray(Q0))
    assert jax.tree.structure(out_state) == jax.tree.structure(state)
    assert all(a.dtype == b.dtype and a.shape == b.shape for a, b in zip(jax.tree.leaves(out_state),
                                                                        jax.tree.leaves(state)))
    assert q.shape == (6,) and p.shape == (3,) and R.shape == (3, 3)


@pytest.mark.slow
def test_arm_is_a_pytree(arm):
    leaves, tree = jax.tree.flatten(arm)
    rebuilt = jax.tree.unflatten(tree, leaves)
    assert isinstance(rebuilt, DynamicArm) and rebuilt.qpos_adr == arm.qpos_adr == (0, 1, 2, 3, 4, 5)
    assert arm.n_act == 6 and arm.site_id == 0 and arm.timestep == 0.002


@pytest.mark.slow
def test_substeps_for(arm):
    assert substeps_for(arm, 0.02) == 10
    assert substeps_for(arm, 0.0021) == 1
    for bad in (0.0, -0.01, float("nan"), 0.0009):
        with pytest.raises(ValueError):
            substeps_for(arm, bad)
    with pytest.raises(ValueError, match="substeps"):
        arm.step_fn(substeps=0)


@pytest.mark.slow
def test_with_servo_needs_gravcomp_compiled_in():
    plain = dynamic_ur5e()
    assert not plain.model.flg_gravcomp
    with pytest.raises(ValueError, match="gravcomp"):
        plain.with_servo(gravcomp=1.0)
    assert plain.with_servo(kp=300.0).model.actuator_gainprm[0, 0] == 300.0


_ONE_JOINT = """
<mujoco>
  <worldbody>
    <body><joint name="j" type="hinge"/><geom size="0.1" mass="1"/><site name="s"/></body>
  </worldbody>
  <actuator>{act}</actuator>
</mujoco>
"""


@pytest.mark.parametrize("act, match", [
    ('<motor joint="j"/>', "position servo"),
    ('<position joint="j" kp="10" gear="2"/>', "gear"),
    ('', "no actuators"),
])
def test_rejects_non_servo_actuators(act, match):
    with pytest.raises(ValueError, match=match):
        dynamic_arm(_ONE_JOINT.format(act=act), "s")


def test_rejects_missing_site():
    with pytest.raises(ValueError, match="site"):
        dynamic_arm(_ONE_JOINT.format(act='<position joint="j" kp="10"/>'), "nope")
