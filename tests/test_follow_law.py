"""The one follow loop with pluggable step laws (control.follow_law): the inverse-Jacobian law reproduces
control.follow and the constrained-QP law reproduces qp.follow and the QP follower's own loop as it was before
the two shared one (kept here as the reference), a stateful law's state moves only with the arm, the NaN-safe
norms (forward value unchanged, finite gradient at 0 under jit and vmap), and the one feasible-start selection."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax import control
from selfid_jax.control import paths, qp
from selfid_jax.math import geometry
from selfid_jax.systems import from_pose_fn, two_link

ARM = two_link()
PATH = paths.star(size=0.2, dim=2)
CTRL = control.ControllerParams(max_step=0.01, tol=0.002)
TOL = 1e-12  # float64: the same operations in the same order


def rigid_pose(params, q):
    """A 6-D task: position ``A q[:3]`` [m], orientation ``exp(q[3:])`` (rotation vector, rad)."""
    return params @ q[:3], geometry.so3_exp(q[3:])


RIGID = from_pose_fn(rigid_pose, 6, task_dim=6, q_low=-3.0, q_high=3.0, dq_max=1.0, m_a=0.01,
                     params=jnp.array([[0.5, 0.1, 0.0], [0.0, 0.4, 0.1], [0.1, 0.0, 0.3]]), sample_low=-0.2,
                     sample_high=0.2, name="rigid")


def _q0s(k=4):
    return ARM.sample_configs(jax.random.key(0), k)


def _assert_same(a, b, tol=TOL):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x, float), np.asarray(y, float), rtol=tol, atol=tol)


def _true_model(_, q):
    return ARM.jacobian(q), jnp.zeros(2)


def _broyden_linearise(J, q):
    return J, jnp.zeros(J.shape[0], J.dtype)


def _broyden_observe(J, q, da, V):
    """A secant update of a learned Jacobian ``J (m, n)`` from the executed step (an online model)."""
    return J + jnp.outer(V - J @ da, da) / (da @ da + 1e-12)


# ------------------------------------------------------------------ the QP follower's loop before it shared one
def _reference_qp_follow(system, linearise, model_state, path, q0, ctrl, *, observe=None, weights=1.0, steps,
                         qp_iters=20):
    """qp.follow as it was written before it ran in control.follow_law (its own scan, its own metrics)."""
    m = system.task_dim
    dtype = jnp.result_type(float)
    q0, path = jnp.asarray(q0, dtype), jnp.asarray(path, dtype)
    W = path.shape[0]
    p0 = system.pose(q0)[0][:m]
    targets = p0[None, :] + path
    verts = jnp.concatenate([p0[None, :], targets], axis=0)
    diverge = 2.0 * jnp.max(jnp.linalg.norm(path, axis=-1)) + 10.0 * ctrl.tol

    def seg(p, a, b):
        ab = b - a
        den = jnp.sum(ab * ab, axis=-1)
        t = jnp.clip(jnp.sum((p[None, :] - a) * ab, axis=-1) / jnp.where(den > 0, den, 1.0), 0.0, 1.0)
        return jnp.sqrt(jnp.sum((p[None, :] - (a + t[:, None] * ab)) ** 2, axis=-1))

    def advance(c, p):
        q, model, w, failed, es, em, used, wpe = c
        active = (w < W) & ~failed
        wc = jnp.minimum(w, W - 1)
        err = jnp.linalg.norm(targets[wc] - p)
        hit = active & (err <= ctrl.tol)
        wpe = jnp.where(hit, wpe.at[wc].set(err), wpe)
        w = w + hit.astype(jnp.int32)
        return (q, model, w, failed, es, em, used, wpe), active & (w < W)

    def step(c, _):
        p = system.pose(c[0])[0][:m]
        dist = jnp.min(seg(p, verts[:-1], verts[1:]))
        c, active = advance(c, p)
        q, model, w, failed, es, em, used, wpe = c
        e = targets[jnp.minimum(w, W - 1)] - p
        en = jnp.linalg.norm(ctrl.gain * e)
        v = ctrl.gain * e * jnp.minimum(1.0, ctrl.max_step / jnp.where(en > 0, en, 1.0))
        J, offset = linearise(model, q)
        da = qp.solve(J, v - offset, *qp.step_box(system, q), weights, iters=qp_iters).da
        q_new = system.apply(q, da)
        finite = jnp.all(jnp.isfinite(q_new)) & jnp.all(jnp.isfinite(p))
        failed = failed | (active & (~finite | (dist > diverge)))
        move = active & ~failed
        if observe is not None:
            learned = observe(model, q, q_new - q, system.pose(q_new)[0][:m] - p)
            model = jax.tree.map(lambda a, b: jnp.where(move, a, b), learned, model)
        counted = jnp.where(active & jnp.isfinite(dist), dist, 0.0)
        return (jnp.where(move, q_new, q), model, w, failed, es + counted, jnp.maximum(em, counted),
                used + active.astype(jnp.int32), wpe), None

    init = (q0, model_state, jnp.zeros((), jnp.int32), ~(jnp.all(jnp.isfinite(q0)) & jnp.all(jnp.isfinite(path))),
            jnp.zeros((), dtype), jnp.zeros((), dtype), jnp.zeros((), jnp.int32), jnp.full((W,), -1.0, dtype))
    c, _ = jax.lax.scan(step, init, None, length=steps)
    p_end = system.pose(c[0])[0][:m]
    c, _ = advance(c, p_end)
    q, model, w, failed, es, em, used, wpe = c
    end = jnp.linalg.norm(targets - p_end[None, :], axis=-1)
    wpe = jnp.where(wpe >= 0, wpe, jnp.where(jnp.isfinite(end), end, 0.0))
    res = control.FollowResult(completion=w.astype(dtype) / W, mean_error=es / jnp.maximum(used, 1).astype(dtype),
                               max_error=em, waypoint_error=jnp.mean(wpe), steps_used=used, failed=failed,
                               final_q=q, positions=None, start_pose=system.pose(q0), final_pose=system.pose(q),
                               waypoint_errors=wpe)
    return res, model


# ------------------------------------------------------------------ inverse-Jacobian law == control.follow
@pytest.mark.slow
@pytest.mark.parametrize("source", ["true", "fixed", "scaled", "function"])
def test_inverse_jacobian_law_in_the_loop_is_control_follow(source):
    J0 = 1.3 * ARM.true_inverse_jacobian(jnp.array([0.3, 1.4]))
    jinv = {"true": control.true_inverse(ARM), "fixed": control.fixed(J0),
            "scaled": control.scaled_true_inverse(ARM, jnp.array([[1.2, 0.9], [1.5, 0.7]])),
            "function": lambda q: 0.8 * ARM.true_inverse_jacobian(q)}[source]
    q0s = _q0s()
    both = jax.jit(jax.vmap(lambda q: (  # one program for the two loops
        control.follow(ARM, jinv, PATH, q, CTRL, steps=300, return_trajectory=True),
        control.follow_law(ARM, control.inverse_jacobian_law(ARM, jinv), PATH, q, CTRL, steps=300,
                           return_trajectory=True))))
    a, (b, state) = both(q0s)
    _assert_same(a, b)
    assert state == ()
    one, _ = control.follow_law(ARM, control.inverse_jacobian_law(ARM, jinv), PATH, q0s[1], CTRL, steps=300,
                                return_trajectory=True)  # eager == vmapped
    _assert_same(jax.tree.map(lambda x: x[1], a), one)


# ------------------------------------------------------------------ QP law == qp.follow == the old QP loop
@pytest.mark.slow
@pytest.mark.parametrize("online", [False, True])
def test_constrained_qp_law_in_the_loop_is_qp_follow_and_the_old_qp_loop(online):
    q0s = _q0s()
    if online:
        kw = dict(observe=_broyden_observe)
        lin, model = _broyden_linearise, 0.7 * ARM.jacobian(jnp.array([0.3, 1.4]))
    else:
        kw, lin, model = {}, _true_model, ()
    w = jnp.array([1.0, 3.0])
    run_all = jax.jit(jax.vmap(lambda q: (  # one program for the three loops
        qp.follow(ARM, lin, model, PATH, q, CTRL, weights=w, steps=300, qp_iters=12, **kw),
        control.follow_law(ARM, qp.constrained_law(ARM, lin, model, weights=w, iters=12, **kw), PATH, q, CTRL,
                           steps=300),
        _reference_qp_follow(ARM, lin, model, PATH, q, CTRL, weights=w, steps=300, qp_iters=12, **kw))))
    a, b, ref = run_all(q0s)
    _assert_same(a, b)
    _assert_same(a, ref)
    assert np.sum(np.asarray(a[0].completion) == 1.0) >= 3  # mostly completed: the comparison is of real runs
    if online:  # the model learned on the way: it changed
        assert np.all(np.abs(np.asarray(a[1]) - np.asarray(model)).max(axis=(1, 2)) > 1e-3)


@pytest.mark.slow
def test_qp_loop_fails_like_the_old_loop_on_a_divergent_model():
    """A model with the wrong sign: the rollout diverges and is frozen at the same step in both loops."""
    def wrong(_, q):
        return -ARM.jacobian(q), jnp.zeros(2)

    q0s = _q0s()
    a, ref = jax.jit(jax.vmap(lambda q: (qp.follow(ARM, wrong, (), PATH, q, CTRL, steps=200),
                                         _reference_qp_follow(ARM, wrong, (), PATH, q, CTRL, steps=200))))(q0s)
    _assert_same(a, ref)
    assert np.all(a[0].failed)


@pytest.mark.slow
def test_a_stateful_law_updates_its_state_only_on_steps_that_move():
    """A law counting its moves (state = count): the count equals the steps used on a completed rollout and stops
    at the failing step on a failed one, because the loop keeps a law's new state only where the arm moves."""
    base = control.inverse_jacobian_law(ARM, control.true_inverse(ARM))

    def counting(scale):
        def step(count, q, pose, aux, V):
            dq, _, ok = base.step((), q, pose, aux, V)
            return scale * dq, count + 1, ok
        return control.StepLaw(init=lambda q0: jnp.zeros((), jnp.int32), sense=lambda c, q: base.sense((), q),
                               step=step)

    q0 = jnp.array([0.3, 1.4])
    near = CTRL._replace(diverge_dist=0.05)  # moving away from the path: fails once 5 cm off it
    (res, count), (away, away_count) = jax.jit(lambda q: (  # one program for the two rollouts
        control.follow_law(ARM, counting(1.0), PATH, q, CTRL, steps=300),
        control.follow_law(ARM, counting(-1.0), PATH, q, near, steps=300)))(q0)
    assert float(res.completion) == 1.0 and int(count) == int(res.steps_used)
    assert bool(away.failed) and int(away_count) == int(away.steps_used) - 1  # the failing step does not move


def test_qp_follow_rejects_rotation_tasks():
    for system in (RIGID, RIGID.with_task_axes(("x", "rz"))):
        with pytest.raises(ValueError, match="position tasks only"):
            qp.follow(system, lambda _, q, s=system: (s.jacobian(q), jnp.zeros(s.task_dim)), (),
                      np.zeros((3, system.task_dim)), jnp.zeros(6), CTRL, steps=10)


# ------------------------------------------------------------------ NaN-safe norms
def _old_clip_norm(v, limit):
    norm = jnp.sqrt(jnp.sum(v * v))
    return v * jnp.minimum(1.0, limit / jnp.where(norm > 0, norm, 1.0))


@pytest.mark.slow
def test_clip_norm_and_norm_forward_values_are_unchanged():
    rng = np.random.default_rng(0)
    vs = np.concatenate([rng.normal(size=(50, 3)) * 10.0 ** rng.uniform(-8, 1, (50, 1)), np.zeros((1, 3)),
                         [[np.nan, 0.0, 1.0], [np.inf, 0.0, 0.0], [1e-200, 0.0, 0.0]]])
    for limit in (0.01, 1.0, 100.0):
        np.testing.assert_array_equal(jax.vmap(lambda v, lim=limit: control.clip_norm(v, lim))(vs),
                                      jax.vmap(lambda v, lim=limit: _old_clip_norm(v, lim))(vs))
    np.testing.assert_array_equal(jax.vmap(control.safe_norm)(vs), jax.vmap(lambda v: jnp.sqrt(jnp.sum(v * v)))(vs))
    assert control.clip_norm(jnp.zeros((0,)), 1.0).shape == (0,)


@pytest.mark.slow
@pytest.mark.parametrize("wrap", ["eager", "jit", "vmap", "jit_vmap"])
def test_clip_norm_and_norm_gradients_at_zero_are_finite(wrap):
    fns = {
        "clip": lambda v: jnp.sum(control.clip_norm(v, 0.5) * jnp.arange(1.0, 4.0)),
        "norm": control.safe_norm,
    }
    for name, f in fns.items():
        g = jax.grad(f)
        if wrap in ("vmap", "jit_vmap"):
            g = jax.vmap(g)
        if wrap in ("jit", "jit_vmap"):
            g = jax.jit(g)
        x = jnp.zeros((4, 3)) if "vmap" in wrap else jnp.zeros(3)
        out = np.asarray(g(x))
        assert np.all(np.isfinite(out)), (name, out)
        if name == "clip":  # min(1, limit) times the weights: the clip is inactive at 0
            np.testing.assert_allclose(out, np.broadcast_to(0.5 * np.arange(1.0, 4.0), out.shape))
        else:
            np.testing.assert_array_equal(out, 0.0)
    v = jnp.array([3.0, 4.0, 0.0])  # away from 0: the ordinary derivatives
    np.testing.assert_allclose(jax.grad(control.safe_norm)(v), v / 5.0, rtol=1e-15)
    np.testing.assert_allclose(jax.jacobian(lambda v: control.clip_norm(v, 10.0))(v), np.eye(3), rtol=1e-15)


@pytest.mark.slow
def test_follow_gradient_is_finite_where_the_rotation_error_is_exactly_zero():
    """A 6-D task whose path holds the start orientation: the rotation error at the first step is exactly 0, the
    point where the clip's norm has an infinite derivative; reverse mode through follow is now finite (the design
    loss no longer needs its waypoint nudge for this)."""
    system = RIGID
    path = paths.star(size=0.02, dim=6)
    ctrl = control.ControllerParams(max_step=0.002, tol=0.0004, max_rot_step=0.05, rot_tol=0.01)
    q0 = jnp.array([0.0, 0.0, 0.0, 0.1, -0.1, 0.2])
    J = system.true_inverse_jacobian(q0)

    def loss(s):
        res = control.follow(system, control.fixed(s * J), path, q0, ctrl, steps=120, return_trajectory=True)
        return jnp.sum(res.positions ** 2) + res.waypoint_error

    g = jax.jit(jax.grad(loss))(1.1)
    assert np.isfinite(float(g)) and float(g) != 0.0
    h = 1e-6
    value = jax.jit(loss)  # one program for the two evaluations
    np.testing.assert_allclose(float(g), (float(value(1.1 + h)) - float(value(1.1 - h))) / (2 * h), rtol=1e-5)


# ------------------------------------------------------------------ one feasible-start selection
def test_feasible_indices_selects_the_first_k_and_names_the_shortfall():
    valid = np.array([True, True, False, True, True, True])
    completion = np.array([1.0, 0.5, 1.0, 1.0, 1.0, 1.0])
    failed = np.array([False, False, False, True, False, False])
    np.testing.assert_array_equal(control.feasible_indices(ARM, valid, completion, failed, 2), [0, 4])
    with pytest.raises(ValueError, match=r"only 3 of 6 sampled configurations of 'two_link' complete the path with "
                                         r"the true inverse Jacobian; need 4 \(raise oversample"):
        control.feasible_indices(ARM, valid, jnp.asarray(completion), jnp.asarray(failed), 4)
    np.testing.assert_array_equal(control.completed(jnp.asarray(completion), jnp.asarray(failed)),
                                  [True, False, True, False, True, True])


@pytest.mark.slow
def test_a_path_of_the_wrong_width_names_the_task_and_the_fix():
    import jax

    import selfid_jax as sj

    arm = sj.two_link()
    q0 = arm.sample_configs(jax.random.key(0), 1)[0]
    with pytest.raises(ValueError, match=r"for the 2-D task of 'two_link', got \(10, 3\).*paths.star\(size, dim=2\)"):
        sj.follow(arm, sj.control.true_inverse(arm), sj.control.paths.star(size=0.05, dim=3), q0)
