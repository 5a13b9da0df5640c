"""Seed 003 (Tac-Man / TacMan-Turbo): Kabsch, constant-velocity prediction, alpha, and closed-loop rollouts.

References are independent: a known rigid transform, the closed-form screw
motion ``exp(t xi)``, and native MuJoCo against MJX.
"""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from helpers_articulated import PADS, rollout_params, ur5e_arm

from selfid_jax.articulated import scenes, sim, tacman, tactile


def _random_pose(seed, angle=0.1, shift=0.003):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=3)
    w *= angle / np.linalg.norm(w)
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.exp(jnp.asarray(w)),
                                                    jnp.asarray(rng.normal(size=3) * shift))


@pytest.mark.slow  # > 1 s on 2 shared cores (first-use compilation of the eager jaxlie/SVD ops)
def test_kabsch_recovers_known_transform_from_noisy_markers():
    T = _random_pose(0)
    ref = jnp.asarray(PADS.ref)
    mask = jnp.asarray(PADS.delta0 >= 3e-4)
    assert int(mask.sum()) == 32  # two columns of 8 on each pad at the default grasp
    noise = 2e-6 * jax.random.normal(jax.random.key(1), ref.shape)
    cur = jax.vmap(T.apply)(ref) + noise
    est, valid = jax.jit(tacman.kabsch)(ref, cur, mask)
    assert bool(valid)
    np.testing.assert_allclose(np.asarray(est.translation()), np.asarray(T.translation()), atol=2e-5)
    err = (est.rotation().inverse() @ T.rotation()).log()
    assert float(jnp.linalg.norm(err)) < 2e-3  # rad; 2 um noise over a 17.5 mm x 12 mm marker patch


@pytest.mark.slow  # > 1 s on 2 shared cores (first-use compilation of the eager jaxlie/SVD ops)
def test_kabsch_flags_collinear_and_too_few_points():
    ref = jnp.asarray(PADS.ref)
    T = _random_pose(2)
    cur = jax.vmap(T.apply)(ref)
    column = jnp.asarray((np.abs(PADS.ref[:, 0] - PADS.ref[0, 0] - 3 * 0.0025) < 1e-9) & (PADS.ref[:, 1] > 0))
    assert int(column.sum()) == 8  # one straight column of markers
    kabsch = jax.jit(tacman.kabsch)  # one program for the three masks (and the test above), not op by op
    est, valid = kabsch(ref, cur, column)
    assert not bool(valid) and np.all(np.isfinite(np.asarray(est.wxyz_xyz)))
    two = jnp.zeros(ref.shape[0], bool).at[jnp.array([0, 9])].set(True)
    assert not bool(kabsch(ref, cur, two)[1])
    tri = jnp.zeros(ref.shape[0], bool).at[jnp.array([0, 1, 8])].set(True)  # a right angle: not collinear
    est, valid = kabsch(ref, cur, tri)
    assert bool(valid)
    np.testing.assert_allclose(np.asarray(est.as_matrix()), np.asarray(T.as_matrix()), atol=1e-9)


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_constant_velocity_prediction_is_exact_on_a_screw_motion():
    xi = jnp.array([0.02, -0.01, 0.03, 0.3, -0.2, 0.5])  # [v, w] twist
    base = _random_pose(3, angle=1.0, shift=0.5)
    T = lambda t: base @ jaxlie.SE3.exp(t * xi)
    for t0, h in ((0.0, 0.1), (0.7, 0.02), (2.0, 0.5)):
        pred = jax.jit(tacman.predict)(T(t0), T(t0 + h))
        np.testing.assert_allclose(np.asarray(pred.as_matrix()), np.asarray(T(t0 + 2 * h).as_matrix()), atol=1e-12)


@pytest.mark.slow
def test_keep_speed_stays_on_the_screw_at_the_base_speed():
    xi = jnp.array([0.02, 0.0, 0.01, 0.0, 0.0, 0.4])
    T_u = jaxlie.SE3.exp(0.05 * xi)
    u0 = jnp.array([0.03, 0.0, 0.0, 0.0, 0.0, 0.0])
    out = tacman.keep_speed(T_u, u0, 0.02)
    # the scaled screw's translation is its chord: |v0| dt to second order in the rotation angle (0.4 * 0.015 rad)
    assert float(jnp.linalg.norm(out.translation())) == pytest.approx(0.03 * 0.02, rel=1e-4)
    a, b = np.asarray(out.log()), np.asarray(T_u.log())
    np.testing.assert_allclose(a, b * (np.linalg.norm(a) / np.linalg.norm(b)), atol=1e-15)  # same screw axis
    still = tacman.keep_speed(jaxlie.SE3.exp(jnp.zeros(6)), u0, 0.02)  # the handle has not moved: exp(u0 dt)
    np.testing.assert_allclose(np.asarray(still.translation()), [6e-4, 0, 0], atol=1e-15)


def _lead_run(vs, *, speed=0.03, dt=0.02, lead_max=1e-3, tau=0.06):
    """``lead_step`` along a screw at handle speeds ``vs`` [m/s] per step (exact markers, gripper at the handle)."""
    xi = jnp.array([0.8, 0.0, 0.6, 0.0, 0.0, 2.0])  # unit origin speed along the screw; 2 rad/m
    u0 = jnp.array([speed, 0.0, 0.0, 0.0, 0.0, 0.0])
    p = tacman.TurboParams(u0, dt, jnp.asarray(False), lead_max, tau)
    ref = jnp.asarray(PADS.ref)
    mask = jnp.asarray(PADS.delta0 >= 3e-4)
    step = jax.jit(lambda st, T_g: tacman.lead_step(st, tacman.Reading(T_g, ref, ref, mask), p))
    T = _random_pose(6)
    st = tacman.turbo_init(T)
    out = []
    for k, v in enumerate(vs):  # the gripper sits on the handle (X = identity), which moved v dt along xi since k - 1
        if k > 0:
            T = T @ jaxlie.SE3.exp(xi * v * dt)
        st, u, (valid, _) = step(st, T)
        assert bool(valid)
        out.append((st, u, T))
    return out, xi


@pytest.mark.slow  # > 1 s on 2 shared cores (eager jaxlie ops compile on first use)
def test_lead_grows_by_the_speed_deficit_saturates_and_aims_ahead_along_the_screw():
    speed, dt, lead_max = 0.03, 0.02, 1e-3
    vs = [0.0] + [0.01] * 5 + [0.03] * 3  # step 0 is u0 alone; then 20 mm/s short of |v0|, then at |v0|
    out, xi = _lead_run(vs, speed=speed, dt=dt, lead_max=lead_max)
    s = np.array([float(o[0].s) for o in out])
    expect = np.minimum(np.arange(len(vs)) * (speed - 0.01) * dt, lead_max)  # 0.4 mm per step, capped at 1 mm
    expect[6:] = lead_max  # the handle at |v0|: no deficit, the lead stays
    np.testing.assert_allclose(s, expect, atol=1e-9)
    a = 1.0 - np.exp(-dt / 0.06)  # smoothing factor per step, tau = 0.06 s
    xf = np.array([speed * dt, 0, 0, 0, 0, 0])  # the smoothed twist starts from u0 dt
    for k, (st, u, T_g) in enumerate(out[1:], start=1):
        xf = xf + a * (np.asarray(xi) * vs[k] * dt - xf)
        np.testing.assert_allclose(np.asarray(st.xi), xf, atol=1e-9)
        # closed form: the gripper moves onto T_h exp(xf (|v0| dt + s) / |xf_v|) in dt: an arc |v0| dt + s along xf
        target = T_g @ jaxlie.SE3.exp(jnp.asarray(xf * (speed * dt + float(st.s)) / np.linalg.norm(xf[:3])))
        moved = T_g @ jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.exp(u[3:] * dt), u[:3] * dt)
        np.testing.assert_allclose(np.asarray(moved.as_matrix()), np.asarray(target.as_matrix()), atol=1e-9)
    # the smoothed screw turns from u0 to the handle's: 8 steps of a = 0.28 leave 7 % of the prior
    cos = xf[:3] @ np.asarray(xi[:3]) / np.linalg.norm(xf[:3])
    assert cos > 0.99


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_offset_velocity_reaches_the_prediction_and_alpha_scales_to_the_limit():
    T_g, T_pred, dt = _random_pose(4), _random_pose(5), 0.02
    u0 = jnp.array([0.03, 0.0, 0.0, 0.0, 0.0, 0.1])
    u = u0 + tacman.offset_velocity(T_g, T_pred, u0, dt)
    moved = T_g @ jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.exp(u[3:] * dt), u[:3] * dt)
    np.testing.assert_allclose(np.asarray(moved.as_matrix()), np.asarray(T_pred.as_matrix()), atol=1e-12)
    qdot = jnp.array([0.5, -2.0, 0.1])
    a = tacman.alpha_scale(qdot, jnp.array([1.0, 1.0, 1.0]), 0.9)
    assert float(a) == pytest.approx(0.45)
    assert float(jnp.max(jnp.abs(a * qdot))) == pytest.approx(0.9)
    assert float(tacman.alpha_scale(0.01 * qdot, jnp.ones(3), 0.9)) == 1.0


@pytest.mark.slow  # > 1 s on 2 shared cores (first-use compilation of the eager jaxlie/SVD ops)
def test_marker_contact_set_follows_eq2():
    # pulling the handle 0.7 mm away from the +y pad takes its markers out of contact (deformation < eps)
    X = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.identity(), jnp.array([0.0, -7e-4, 0.0]))
    cur, mask, delta = tactile.read(PADS, X, jax.random.key(0), 0.0, 3e-4)
    on_plus = PADS.ref[:, 1] > 0
    assert not bool(jnp.any(mask[on_plus])) and int(mask[~on_plus].sum()) == 16
    np.testing.assert_allclose(np.asarray(cur[np.asarray(mask)] - PADS.ref[np.asarray(mask)]), [[0, -7e-4, 0]] * 16,
                               atol=1e-15)


def test_controller_labels_round_trip_and_unknown_labels_are_refused():
    assert sim.CONTROLLERS == ("tacman", "turbo", "turbo_u0", "turbo_lead", "tacman_reaim")
    for c in sim.Controller:
        assert sim.Controller.parse(c.label) is c and sim.CONTROLLERS[c] == c.label
    with pytest.raises(ValueError, match="allowed: tacman, turbo, turbo_u0, turbo_lead, tacman_reaim"):
        sim.Controller.parse("turbo_fast")


@pytest.mark.slow  # about 8 s on 2 shared cores: the UR5e's eager forward kinematics compile on first use
def test_tactile_options_keep_their_config_names_in_the_rollout_params():
    """``pads.marker_noise``, ``tacman.recovery_gain``, ``turbo_lead.twist_tau``: one name from YAML to the row."""
    from selfid_jax.experiments.articulated import ArticulatedConfig, _build

    cfg = ArticulatedConfig(objects={"prismatic": 1}, controllers=["turbo_lead", "tacman"], arms=["true"],
                            pads={"marker_noise": 7e-6}, tacman={"recovery_gain": 0.25},
                            turbo_lead={"twist_tau": 0.1})
    (part,) = _build(cfg)
    r = part.params.rollout
    assert list(r.controller) == [sim.Controller.TURBO_LEAD, sim.Controller.TACMAN]
    for name, value in (("marker_noise", 7e-6), ("recovery_gain", 0.25), ("twist_tau", 0.1)):
        np.testing.assert_array_equal(getattr(r, name), [value, value])


# ----------------------------------------------------------------------------- closed loop (slow)


def _objects(kind, n_rows, frictionloss=1.0):
    pop = scenes.population(kind, 1, 3, misalign_deg=10.0, radius=(0.25, 0.25), damping=(5.0, 5.0),
                            frictionloss=(frictionloss, frictionloss))
    return scenes.ObjectParams(*(np.repeat(a, n_rows, axis=0) for a in pop))


@pytest.mark.slow
@pytest.mark.parametrize("kind,steps", [("prismatic", 600), ("revolute", 650)])
def test_drawer_and_door_opened_by_both_controllers(kind, steps):
    """Tac-Man re-aiming (1 mm / 0.2 mm thresholds), TacMan-Turbo keeping u0 and with the integral lead open a drawer
    (> 250 mm) and a door (> 60 deg) under the weld grasp (about 7.3 kN/m) and 1 N friction, 5 N s/m damping.

    Literal Turbo stalls; the lead keeps |v0| where keep_speed's proportional shear slows down. The step budgets
    (600, 650) are above the successful rows' needs (at most 544 and 560 steps) and the stalled row runs them all."""
    with jax.numpy_rank_promotion("allow"):
        arm, q0, p1, R1 = ur5e_arm()
        m, lay = scenes.compile_scene(kind, p1, R1)
        st = sim.make_static("native", lay, m, PADS, arm, q0, steps=steps, substeps=10, stride=50)
        C = sim.Controller
        ctrl = [C.TACMAN_REAIM, C.TURBO_U0, C.TURBO, C.TURBO_LEAD]
        r = jax.jit(jax.vmap(lambda p: sim.rollout(st, p)))(rollout_params(_objects(kind, 4), ctrl))
    assert list(np.asarray(r.success)) == [True, True, False, True]
    assert not np.any(np.asarray(r.failed))
    assert float(r.progress[2]) < 0.2  # the literal Eq. 16-18 drive the force-carrying shear to zero
    # the handle really moved: independent of the progress bookkeeping, from its traced path
    h = np.asarray(r.handle_trace)[[0, 1, 3]]
    assert np.all(np.linalg.norm(h[:, -1] - h[:, 0], axis=-1) > 0.2)
    assert int(r.steps_used[3]) < int(r.steps_used[1])
    assert float(r.dev_max[3]) < 1.5e-3  # the lead (<= 1 mm) plus the in-step motion, far from the 5 mm slip


# Native against MJX (with and without joint friction loss): tests/test_articulated_mjx.py
