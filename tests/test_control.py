"""Path following with inverse Jacobians, self-ID on simulated systems, metrics and failure handling."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import numpy_reference as ref
import pytest

from selfid_jax import control
from selfid_jax.control import paths
from selfid_jax.identify import algorithm as selfid
from selfid_jax.systems import from_pose_fn, two_link, ur5e

UR5E = ur5e(task_dim=3)
STAR = paths.star(size=0.05, dim=3)
CTRL = control.ControllerParams(max_step=0.004, tol=0.001)
STEPS = 300
OLD_DEFAULTS = control.ControllerParams(max_step=0.005, tol=0.002)  # what these tests were written with
# one worker runs the module: the module-level jitted UR5e rollouts compile once, not once per worker
pytestmark = pytest.mark.xdist_group("control")


@pytest.fixture(scope="module")
def ur5e_configs():
    return UR5E.sample_configs(jax.random.key(0), 9)


@jax.jit
def _ur5e_true(q0s):
    return jax.vmap(lambda q: control.follow(UR5E, control.true_inverse(UR5E), STAR, q, CTRL, steps=STEPS))(q0s)


@jax.jit
def _ur5e_selfid_then_follow(keys, q0s):
    def one(key, q0):
        r = selfid.run(UR5E, key, q0, iters=24, eps=0.5)
        return r.converged_at, control.follow(UR5E, control.fixed(r.estimate), STAR, r.env, CTRL, steps=STEPS)

    return jax.vmap(one)(keys, q0s)


@pytest.mark.slow
def test_true_inverse_completes_star_on_ur5e(ur5e_configs):
    res = _ur5e_true(ur5e_configs)
    np.testing.assert_array_equal(res.completion, 1.0)
    assert not np.any(res.failed)
    assert np.all(res.mean_error < 1e-3)


@pytest.mark.slow
def test_controller_matches_numpy_loop_on_ur5e(ur5e_configs):
    """The scan controller equals an independent numpy loop using DH kinematics."""
    res = _ur5e_true(ur5e_configs)
    for b in range(2):
        q0 = np.asarray(ur5e_configs[b])
        comp, mean_err, max_err, used, failed, _ = ref.follow(
            ref.ur5e_position,
            lambda q: ref.right_inverse(ref.ur5e_position_jacobian(q)),
            np.asarray(STAR),
            q0,
            dq_max=np.asarray(UR5E.dq_max),
            q_low=np.asarray(UR5E.q_low),
            q_high=np.asarray(UR5E.q_high),
            steps=STEPS,
            max_step=CTRL.max_step,
            tol=CTRL.tol,
        )
        assert comp == float(res.completion[b]) and used == int(res.steps_used[b]) and not failed
        np.testing.assert_allclose(res.mean_error[b], mean_err, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(res.max_error[b], max_err, rtol=1e-6, atol=1e-12)


@pytest.mark.slow
def test_selfid_estimate_completes_star_on_ur5e(ur5e_configs):
    keys = jax.random.split(jax.random.key(1), 9)
    conv, res = _ur5e_selfid_then_follow(keys, ur5e_configs)
    assert np.mean(np.asarray(res.completion) == 1.0) >= 0.9
    assert not np.any(res.failed)
    converged = np.asarray(conv)[np.asarray(conv) > 0]
    print(f"UR5e self-ID: mean convergence iteration {converged.mean():.1f} ({len(converged)}/9 converged)")
    assert len(converged) >= 8


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_steps_and_errors_match_closed_form_on_identity_system():
    # p = (q1, q2): the true inverse is I, so each segment takes ceil(length / max_step) steps on the path.
    sys2 = from_pose_fn(lambda params, q: jnp.stack([q[0], q[1], 0.0]), 2, task_dim=2, q_low=[-9, -9],
                        q_high=[9, 9], dq_max=[1, 1], m_a=0.01)
    path = jnp.array([[0.3, 0.0], [0.3, 0.23], [0.0, 0.0]])
    skew = jnp.array([[1.0, 0.0], [0.8, 1.0]])
    # both rollouts in one jitted program (op by op each was a few dozen small compilations)
    res, skewed = jax.jit(lambda: (
        control.follow(sys2, control.true_inverse(sys2), path, jnp.zeros(2),
                       control.ControllerParams(max_step=0.007, tol=1e-9), steps=200),
        control.follow(sys2, control.fixed(skew), path, jnp.zeros(2),
                       control.ControllerParams(max_step=0.007, tol=1e-3), steps=200)))()
    lengths = np.linalg.norm(np.diff(np.vstack([np.zeros(2), path]), axis=0), axis=1)
    assert int(res.steps_used) == int(np.sum(np.ceil(lengths / 0.007)))
    assert float(res.completion) == 1.0 and float(res.max_error) < 1e-12
    # a skewed inverse Jacobian leaves the path; the numpy loop gives the same errors
    res = skewed
    comp, mean_err, max_err, used, _, _ = ref.follow(
        lambda q: np.array([q[0], q[1], 0.0]), lambda q: np.asarray(skew), np.asarray(path), np.zeros(2),
        steps=200, max_step=0.007, tol=1e-3, dq_max=1.0, q_low=-9.0, q_high=9.0,
    )
    assert float(res.completion) == comp == 1.0 and int(res.steps_used) == used
    np.testing.assert_allclose([res.mean_error, res.max_error], [mean_err, max_err], rtol=1e-9)
    assert max_err > 1e-3


@pytest.mark.slow
def test_estimate_or_true_lanes_are_fixed_and_true_inverse_and_the_result_holds_its_poses():
    """vmapped over ``use_true``, one program gives the fixed-estimate rollout and the true-inverse rollout (each
    equal to its own source's to round-off); ``start_pose``/``final_pose`` are the pose map at ``q0``/``final_q``."""
    arm = two_link()
    q0 = jnp.array([0.4, 1.2])
    path = paths.star(size=0.05, dim=2)
    est = 1.1 * arm.true_inverse_jacobian(q0)

    @chex.assert_max_traces(n=1)
    def both(est, q0):
        return jax.vmap(lambda t: control.follow(arm, control.estimate_or_true(est, t), path, q0, CTRL,
                                                 steps=120))(jnp.array([False, True]))

    lanes = jax.jit(both)(est, q0)
    # each source's own rollout: one jitted program for the two (op by op they were dozens of small compilations)
    sources = (control.fixed(est), control.true_inverse(arm))
    alones = jax.jit(lambda: [control.follow(arm, src, path, q0, CTRL, steps=120) for src in sources])()
    for lane, alone in enumerate(alones):
        for a, b in zip(jax.tree.leaves(alone), jax.tree.leaves(jax.tree.map(lambda x, i=lane: x[i], lanes)),
                        strict=True):
            np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=1e-12, atol=1e-12)
        for got, q in ((alone.start_pose, q0), (alone.final_pose, alone.final_q)):
            p, R = arm.pose(q)
            np.testing.assert_allclose(got[0], p, atol=1e-12)
            np.testing.assert_allclose(got[1], R, atol=1e-12)
    assert float(lanes.completion[1]) == 1.0 and float(lanes.mean_error[0]) != float(lanes.mean_error[1])


@pytest.mark.slow
def test_divergent_and_singular_cases_fail_with_finite_metrics():
    arm = two_link()
    q0 = jnp.array([0.4, 1.2])
    path = paths.star(size=0.2, dim=2)
    # one jitted program for the three rollouts (op by op each was a few dozen small compilations)
    flipped, nan_jinv, singular = jax.jit(lambda: (
        control.follow(arm, control.scaled_true_inverse(arm, -jnp.ones((2, 2))), path, q0, OLD_DEFAULTS, steps=300),
        control.follow(arm, lambda q: jnp.full((2, 2), jnp.nan), path, q0, OLD_DEFAULTS, steps=50),
        control.follow(arm, control.true_inverse(arm), path, jnp.array([0.4, 0.0]), OLD_DEFAULTS, steps=50)))()
    for res in (flipped, nan_jinv, singular):
        assert bool(res.failed)
        for x in (res.completion, res.mean_error, res.max_error, res.waypoint_error, res.final_q):
            assert np.all(np.isfinite(x))
        assert float(res.completion) < 1.0


@pytest.mark.slow
def test_user_defined_three_link_arm_runs_through_selfid_and_control():
    def fk(params, q):
        a = jnp.cumsum(q)
        return jnp.stack([jnp.sum(params * jnp.cos(a)), jnp.sum(params * jnp.sin(a)), 0.0])

    arm3 = from_pose_fn(fk, 3, task_dim=2, params=jnp.array([0.5, 0.4, 0.3]), q_low=[-3, -3, -3],
                        q_high=[3, 3, 3], dq_max=[0.1, 0.1, 0.1], m_a=0.02, sample_low=[-1, 0.3, 0.3],
                        sample_high=[1, 1.5, 1.5])
    q0 = arm3.sample_configs(jax.random.key(2), 1)[0]

    @jax.jit  # one program (op by op, self-ID and the rollout were dozens of small compilations)
    def selfid_then_follow(key, q0):
        r = selfid.run(arm3, key, q0, iters=20, eps=0.05)
        return control.follow(arm3, control.fixed(r.estimate), paths.star(size=0.05, dim=2), r.env, OLD_DEFAULTS,
                              steps=300)

    res = selfid_then_follow(jax.random.key(3), q0)
    assert float(res.completion) == 1.0 and not bool(res.failed)


@pytest.mark.slow
def test_selfid_run_noise_jit_vmap_and_no_retrace():
    arm = two_link()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def batch(keys, q0s, m_a, noise):
        return jax.vmap(lambda k, q, a, s: selfid.run(arm, k, q, iters=10, eps=1e-3, m_a=a, pose_noise=s,
                                                      rot_noise=s))(keys, q0s, m_a, noise)

    keys = jax.random.split(jax.random.key(4), 3)
    q0s = arm.sample_configs(jax.random.key(5), 3)
    m_a = np.full(3, 0.02)
    clean = batch(keys, q0s, m_a, np.zeros(3))
    noisy = batch(keys, q0s, m_a, np.full(3, 1e-3))
    assert np.all(np.isfinite(noisy.estimates))
    assert not np.allclose(clean.V, noisy.V)
    one = jax.jit(lambda k, q: selfid.run(arm, k, q, iters=10, eps=1e-3, m_a=0.02))(keys[1], q0s[1])  # unbatched
    np.testing.assert_allclose(clean.estimate[1], one.estimate, rtol=1e-9)
    # noise-free 2-link self-ID lands near the true inverse Jacobian where self-ID ended
    truth = jax.jit(jax.vmap(arm.true_inverse_jacobian))(clean.env)
    assert np.max(np.abs(clean.estimate - truth) / np.abs(truth).max(axis=(1, 2), keepdims=True)) < 0.1


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_rollout_metrics_are_differentiable_in_the_inverse_jacobian_scale():
    """The pipeline differentiates end to end: d(mean tracking error)/d(m_eps) through the scan controller."""
    arm = two_link()
    q0 = jnp.array([0.4, 1.2])
    path = paths.star(size=0.2, dim=2)

    def err(scale):
        res = control.follow(arm, control.scaled_true_inverse(arm, scale), path, q0,
                             control.ControllerParams(max_step=0.01, tol=0.002), steps=300)
        return res.mean_error

    g = jax.jit(jax.grad(err))(jnp.full((2, 2), 1.3))
    assert g.shape == (2, 2) and np.all(np.isfinite(g)) and np.abs(g).max() > 0
    # first-order check against a central difference of the (piecewise smooth) error (one jitted program, twice)
    d = jnp.zeros((2, 2)).at[0, 0].set(1e-4)
    err_jit = jax.jit(err)
    fd = (err_jit(jnp.full((2, 2), 1.3) + d) - err_jit(jnp.full((2, 2), 1.3) - d)) / 2e-4
    np.testing.assert_allclose(g[0, 0], fd, rtol=0.2, atol=1e-6)


@pytest.mark.slow
def test_controller_params_are_traced_one_compilation_for_a_sweep():
    """Every ControllerParams field is traced: sweeping step, tolerance and gain compiles follow once."""
    arm = two_link()
    q0 = jnp.array([0.4, 1.2])
    path = paths.star(size=0.2, dim=2)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def sweep(ctrl):
        return jax.vmap(lambda c: control.follow(arm, control.true_inverse(arm), path, q0, c, steps=200))(ctrl)

    for gain in (1.0, 0.5):
        ctrl = control.ControllerParams(max_step=jnp.array([0.01, 0.02]), tol=jnp.array([0.002, 0.004]),
                                        gain=jnp.full(2, gain), max_rot_step=jnp.full(2, 0.05),
                                        rot_tol=jnp.full(2, 0.01), diverge_dist=jnp.full(2, 1.0))
        res = sweep(ctrl)
        assert np.all(np.asarray(res.completion) == 1.0)
    # a larger step needs fewer steps: the swept value reached the computation
    assert int(res.steps_used[1]) < int(res.steps_used[0])


def test_follow_defaults_are_the_shipped_protocol():
    from selfid_jax.experiments.common.schema import ControllerConfig

    cfg = ControllerConfig()
    untraced = ("diverge_dist", "max_dq")  # set by the study (a default from the path) or the live runner
    assert cfg.traced() == {k: v for k, v in control.ControllerParams()._asdict().items() if k not in untraced}
    assert cfg.steps == control.DEFAULT_STEPS
    with pytest.raises(TypeError, match="ControllerParams"):
        control.follow(two_link(), control.fixed(jnp.eye(2)), paths.star(size=0.2, dim=2), jnp.array([0.4, 1.2]),
                       {"tol": 0.1})


@pytest.mark.slow
def test_bad_follow_inputs_raise_or_fail_with_finite_metrics():
    arm = two_link()
    path = paths.star(size=0.2, dim=2)
    q0 = jnp.array([0.4, 1.2])
    with pytest.raises(ValueError, match=r"jinv: the inverse Jacobian has shape \(3, 2\), expected \(2, 2\)"):
        control.follow(arm, control.fixed(jnp.ones((3, 2))), path, q0)
    with pytest.raises(ValueError, match=r"jinv: .*shape \(2,\)"):
        control.follow(arm, control.fixed(jnp.ones(2)), path, q0)
    with pytest.raises(ValueError, match="q0 holds non-finite"):
        control.follow(arm, control.true_inverse(arm), path, jnp.array([jnp.nan, 1.2]))
    with pytest.raises(ValueError, match="path holds non-finite"):
        control.follow(arm, control.true_inverse(arm), path.at[3, 0].set(jnp.nan), q0)
    with pytest.raises(ValueError, match="controller.tol: must be finite"):
        control.follow(arm, control.true_inverse(arm), path, q0, control.ControllerParams(tol=float("inf")))
    with pytest.raises(ValueError, match="controller.max_step: must be > 0"):
        control.follow(arm, control.true_inverse(arm), path, q0, control.ControllerParams(max_step=0.0))
    # traced NaN inputs cannot raise: the rollout is failed from the start and every metric is finite
    run = jax.jit(lambda q, p: control.follow(arm, control.true_inverse(arm), p, q, OLD_DEFAULTS, steps=50))
    for q, p in ((jnp.array([jnp.nan, 1.2]), path), (q0, path.at[3, 0].set(jnp.nan))):
        res = run(q, p)
        assert bool(res.failed)
        for x in (res.completion, res.mean_error, res.max_error, res.waypoint_error):
            assert np.isfinite(float(x))


@pytest.mark.slow
def test_a_pose_map_that_returns_nan_fails_the_rollout():
    """A closed-chain hand returns NaN where its solve fails: the rollout stops there, flagged, metrics finite."""
    def fk(params, q):  # a planar identity arm whose "solve" fails beyond x = 0.05
        return jnp.where(q[0] > 0.05, jnp.nan, jnp.stack([q[0], q[1], 0.0]))

    arm = from_pose_fn(fk, 2, task_dim=2, q_low=-1, q_high=1, dq_max=0.1, m_a=0.01)
    line = jnp.array([[0.1, 0.0]])
    res = jax.jit(lambda: control.follow(arm, control.fixed(jnp.eye(2)), line, jnp.zeros(2),
                                         control.ControllerParams(max_step=0.01, tol=1e-3), steps=40))()
    assert bool(res.failed) and float(res.completion) == 0.0
    assert 0.05 < float(res.final_q[0]) < 0.065  # frozen at the first configuration whose pose was lost
    for x in (res.mean_error, res.max_error, res.waypoint_error):
        assert np.isfinite(float(x))
