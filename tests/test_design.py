"""Self-ID design (selfid_jax.design, experiments/design.py): the loss's gradient against central differences,
grid + gradient against a brute-force fine grid, the loss's direction on a linear system, NaN-free gradients
where rollouts fail, the unreliable-gradient guard, and the experiment end to end for a user robot."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
import yaml

from selfid_jax import control, design
from selfid_jax.control import paths
from selfid_jax.runner.errors import ConfigError
from selfid_jax.runner.registry import load as load_config
from selfid_jax.systems import from_pose_fn, two_link

A = np.array([[0.5, 0.1, 0.0], [0.0, 0.4, 0.1], [0.1, 0.0, 0.3]])  # m/rad, well conditioned
BOX = 0.3  # rad: the guarded map is NaN beyond it, as a closed-chain hand's pose map off its branch


def linear_pose(params, q):
    """A linear pose map ``p = A q`` [m]: no linearisation error anywhere."""
    return params @ q


def guarded_linear_pose(params, q):
    """``A q``, NaN outside ``|q_i| <= BOX`` (a pose map that fails where its solve would)."""
    p = params @ q
    return jnp.where(jnp.all(jnp.abs(q) <= BOX), p, jnp.nan)


def rigid_pose(params, q):
    """A 6-D task: position ``A q[:3]`` [m], orientation ``exp(q[3:])`` (rotation vector, rad)."""
    from selfid_jax.math import geometry

    return params @ q[:3], geometry.so3_exp(q[3:])


def implicit_pose(params, q):
    """``y`` solving ``A y + 0.1 y^3 = q`` by Newton (optimistix, implicit adjoint), NaN outside ``|q_i| <= BOX``:
    a closed-chain hand's kind of pose map, whose adjoint solve raises on a non-finite right-hand side."""
    import optimistix as optx

    sol = optx.root_find(lambda y, args: args[0] @ y + 0.1 * y**3 - args[1], optx.Newton(rtol=1e-12, atol=1e-12),
                         jnp.zeros(3, q.dtype), args=(params, q), max_steps=30, throw=False)
    ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.abs(q) <= BOX)
    return jnp.where(ok, sol.value, jnp.nan)


def linear_system(fn=linear_pose):
    return from_pose_fn(fn, 3, task_dim=3, q_low=-10.0, q_high=10.0, dq_max=10.0, m_a=0.01, params=jnp.asarray(A),
                        sample_low=-0.2, sample_high=0.2, name="linear")


LINEAR_PATH = paths.star(size=0.02, dim=3)  # perimeter 0.145 m: 73 steps at 2 mm
LINEAR_CTRL = control.ControllerParams(max_step=0.002, tol=0.0004)
ARM_PATH = paths.star(size=0.1, dim=2)
ARM_CTRL = control.ControllerParams(max_step=0.005, tol=0.001)


# ------------------------------------------------------------------ bad input (fast)

@pytest.mark.parametrize("m_a", [0.0, -0.01, np.nan, np.inf, [0.01, -0.02]])
def test_design_params_rejects_nonpositive_or_nonfinite_m_a(m_a):
    with pytest.raises(ValueError, match="m_a"):
        design.design_params(m_a)


def test_design_params_rejects_negative_noise_and_matrix_m_a():
    with pytest.raises(ValueError, match="pose_noise"):
        design.design_params(0.01, pose_noise=-1e-3)
    with pytest.raises(ValueError, match="m_a"):
        design.design_params(np.ones((2, 2)))


def test_design_loss_checks_shapes_before_compute():
    system = two_link()
    p = design.design_params(0.02, controller=ARM_CTRL)
    q0s = np.array([[0.3, 1.2]])
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="log_m_a"):
        design.design_loss(system, p._replace(log_m_a=jnp.zeros(3)), key, q0s, ARM_PATH, iters=4)
    with pytest.raises(ValueError, match="q0s"):
        design.design_loss(system, p, key, np.zeros((2, 3)), ARM_PATH, iters=4)
    with pytest.raises(ValueError, match="path"):
        design.design_loss(system, p, key, q0s, np.zeros((5, 3)), iters=4)
    with pytest.raises(ValueError, match="iters"):
        design.design_loss(system, p, key, q0s, ARM_PATH, iters=0)
    with pytest.raises(ValueError, match="follow_from"):
        design.design_loss(system, p, key, q0s, ARM_PATH, iters=4, follow_from="end")
    with pytest.raises(TypeError, match="System"):
        design.design_loss("two_link", p, key, q0s, ARM_PATH, iters=4)
    with pytest.raises(ValueError, match="m_a_grid"):
        design.optimize(system, p, np.array([0.01, 0.0]), key, q0s, ARM_PATH, iters=4)


def _config(tmp_path, **changes):
    cfg = {"experiment": "design", "systems": ["two_link"], "path": {"kind": "star", "size": 0.1},
           "m_a_grid": {"start": 0.002, "stop": 0.3, "num": 5}, "pose_noise": [0.001], "n_configs": 2}
    cfg.update(changes)
    path = tmp_path / "design.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.parametrize("changes, key", [
    ({"systems": ["two_links"]}, "systems"),
    ({"m_a_grid": {"start": 0.01, "stop": 0.005, "num": 5}}, "m_a_grid.stop"),
    ({"m_a_grid": {"start": 0.0, "stop": 0.3, "num": 5}}, "m_a_grid.start"),
    ({"pose_noise": [0.001, 0.002], "rot_noise": [0.0]}, "rot_noise"),
    ({"pose_noise": [-0.001]}, "pose_noise"),
    ({"refine": {"steps": 0}}, "refine.steps"),
])
def test_config_errors_name_the_key(tmp_path, changes, key):
    with pytest.raises(ConfigError, match=key.split(".")[0]):
        load_config(_config(tmp_path, **changes))


def test_tabulate_reads_the_library_results_back_from_the_runner_columns():
    """compute returns design.DesignResult and the held-out DesignInfo; the runner's dotted columns of them
    (named_leaves, each row flattened) give one tidy row per evaluated point (here without the per-actuator stage)."""
    from types import SimpleNamespace

    from selfid_jax.experiments import design as exp

    from selfid_jax.runner.sweep import named_leaves

    B, G, K, E, n = 2, 3, 2, 4, 2
    rng = np.random.default_rng(0)

    def info(count):
        return design.DesignInfo(*(rng.uniform(0.1, 0.2, (B, count)) for _ in design.DesignInfo._fields))

    grid = design.GridResult(np.tile(np.geomspace(0.01, 0.1, G), (B, 1)), info(G), rng.normal(size=(B, G, n)),
                             np.zeros(B, np.int32))
    scalar = design.RefineResult(**{f: rng.uniform(0.1, 0.2, (B, K)) for f in design.RefineResult._fields})
    out = exp.Outputs(design.DesignResult(grid, scalar, None), exp.HeldOut(rng.normal(size=(B, E, n)), info(E)))
    cols, _ = named_leaves(out)
    assert "search.grid.info.loss" in cols and "held_out.log_m_a" in cols
    wide = pd.DataFrame({"system": "s", "noise_level": range(B), "pose_noise": [0.0, 1e-3], "rot_noise": 0.0,
                         **{k: list(np.asarray(v).reshape(B, -1)) for k, v in cols.items()}})
    part = SimpleNamespace(static=SimpleNamespace(system=SimpleNamespace(n_act=n)),
                           params=SimpleNamespace(m_a_grid=np.zeros((B, G))))
    df = exp.tabulate(wide, part, SimpleNamespace(refine=SimpleNamespace(steps=K, max_failed=0.5)))
    assert df.groupby(["noise_level", "stage"]).size().unstack().loc[0].to_dict() == {"eval": 3, "grid": G,
                                                                                      "scalar": K}
    assert list(df[df.stage == "eval"]["design"].unique()) == ["default", "grid", "scalar"]
    g = df[(df.stage == "grid") & (df["index"] == 1) & (df.noise_level == 1)].iloc[0]
    assert g["m_a"] == pytest.approx(grid.m_a[1, 1]) and g["loss"] == grid.info.loss[1, 1]
    assert g["grad"] == pytest.approx(grid.grad[1, 1].sum()) and g["reliable"]
    sc = df[(df.stage == "scalar") & (df["index"] == 1) & (df.noise_level == 0)].iloc[0]
    assert sc["m_a"] == pytest.approx(np.exp(scalar.log_m_a[0, 1])) and sc["grad"] == scalar.grad[0, 1]
    ev = df[(df.stage == "eval") & (df["index"] == 2) & (df.noise_level == 0)].iloc[0]
    np.testing.assert_allclose(ev["m_a_vec"], np.exp(out.held_out.log_m_a[0, 2]))
    assert ev["rms_error_mm"] == pytest.approx(1e3 * out.held_out.info.rms_error[0, 2]) and np.isnan(ev["grad"])


# ------------------------------------------------------------------ gradients (slow: compiles the rollout)

@pytest.mark.slow
def test_gradient_equals_central_difference_in_log_m_a():
    """float64 (conftest); scalar and per-actuator log m_a on a 2-link arm, 3 starts x 2 trials, a 5 cm star."""
    system = two_link()
    path = paths.star(size=0.05, dim=2)
    ctrl = control.ControllerParams(max_step=0.01, tol=0.002)
    q0s = control.feasible_starts(system, path, jax.random.key(0), 3, ctrl, steps=110)
    key = jax.random.key(1)
    kw = dict(iters=6, n_trials=2, steps=110)
    traces = []

    def value_and_grad(p):
        traces.append(None)
        return design.design_value_and_grad(system, p, key, q0s, path, **kw)

    vg = jax.jit(value_and_grad)
    h = 1e-5
    for log_m_a in (np.log(0.03), np.log(np.array([0.02, 0.05]))):
        p = design.DesignParams(jnp.asarray(log_m_a), 1e-3, 0.0, ctrl)
        info, g = vg(p)
        assert float(info.failed_fraction) == 0.0  # every rollout contributes a gradient
        g = np.atleast_1d(np.asarray(g))
        x = np.atleast_1d(np.asarray(log_m_a, float))
        fd = []
        for i in range(x.size):
            e = np.zeros_like(x)
            e[i] = h
            plus = vg(p._replace(log_m_a=jnp.asarray((x + e).reshape(np.shape(log_m_a)))))[0].loss
            minus = vg(p._replace(log_m_a=jnp.asarray((x - e).reshape(np.shape(log_m_a)))))[0].loss
            fd.append((float(plus) - float(minus)) / (2 * h))
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)
        assert np.all(np.abs(g) > 1e-3)  # a real slope, not a trivially passing zero
    assert len(traces) == 2  # one compilation per shape of log m_a, whatever its value and the noise


@pytest.mark.slow
def test_gradient_on_a_rotation_task_is_finite_and_equals_central_difference():
    """A 6-D task whose path holds the start orientation: the rotation error at the first step is exactly 0, where
    follow's norm has an infinite derivative; the design loss's gradient must still be finite and exact."""
    system = from_pose_fn(rigid_pose, 6, task_dim=6, q_low=-3.0, q_high=3.0, dq_max=1.0, m_a=0.01,
                          params=jnp.asarray(A), sample_low=-0.2, sample_high=0.2, name="rigid")
    path = paths.star(size=0.02, dim=6)
    ctrl = control.ControllerParams(max_step=0.002, tol=0.0004, max_rot_step=0.05, rot_tol=0.01)
    q0s = np.array([[0.0, 0.0, 0.0, 0.1, -0.1, 0.2], [0.1, -0.1, 0.05, 0.0, 0.2, -0.1]])
    vg = jax.jit(lambda p: design.design_value_and_grad(system, p, jax.random.key(5), q0s, path, iters=10,
                                                        steps=220))
    h = 1e-5
    p = design.design_params(0.03, pose_noise=1e-3, rot_noise=1e-3, controller=ctrl)
    info, g = vg(p)
    assert float(info.failed_fraction) == 0.0 and np.isfinite(float(g)) and abs(float(g)) > 1e-3
    fd = (float(vg(p._replace(log_m_a=p.log_m_a + h))[0].loss) - float(vg(p._replace(log_m_a=p.log_m_a - h))[0].loss))
    np.testing.assert_allclose(float(g), fd / (2 * h), rtol=1e-5)


@pytest.mark.slow
def test_linear_system_larger_m_a_is_always_better():
    """No linearisation error: the estimate's error is noise / m_a, so the loss falls and its gradient is negative."""
    system = linear_system()
    q0s = np.array([[0.0, 0.0, 0.0], [0.1, -0.1, 0.05], [-0.1, 0.1, 0.1]])
    p = design.design_params(0.01, pose_noise=1e-3, controller=LINEAR_CTRL)
    grid = np.geomspace(0.02, 1.0, 6)
    res = jax.jit(lambda g: design.grid_search(system, p, g, jax.random.key(2), q0s, LINEAR_PATH, iters=8,
                                               n_trials=2, steps=220))(grid)
    assert np.all(np.asarray(res.info.failed_fraction) == 0.0)
    assert np.all(np.diff(np.asarray(res.info.loss)) < 0.0)
    assert np.all(np.asarray(res.grad).sum(axis=1) < 0.0)
    assert int(res.best) == len(grid) - 1


@pytest.mark.slow
def test_no_nan_gradient_when_rollouts_fail():
    """A pose map that returns NaN off its box (as a hand's): failed rollouts give zero gradient, never NaN."""
    system = linear_system(guarded_linear_pose)
    q0s = np.array([[0.0, 0.0, 0.0], [0.25, 0.25, 0.25], [-0.27, 0.2, 0.0], [0.1, -0.26, 0.2]])
    kw = dict(iters=8, n_trials=1, steps=220)
    key = jax.random.key(3)
    vg = jax.jit(lambda p: design.design_value_and_grad(system, p, key, q0s, LINEAR_PATH, **kw))
    p = design.design_params(0.03, pose_noise=1e-4, controller=LINEAR_CTRL)
    info, g = vg(p)
    assert 0.0 < float(info.failed_fraction) < 1.0  # some rollouts leave the box
    assert np.isfinite(float(info.loss)) and np.all(np.isfinite(np.asarray(g))) and float(g) != 0.0
    # the gate matters: the same batch differentiated without it is NaN (0 * NaN inside the frozen rollouts)
    fe = jnp.asarray(1.0)
    keys = jax.random.split(key, q0s.shape[0])

    def ungated(log_m_a):
        pp = p._replace(log_m_a=log_m_a)
        losses, _ = jax.vmap(lambda k, q: design.search._rollout(pp, (system, k, q, jnp.asarray(LINEAR_PATH), fe),
                                                                 iters=8, steps=220, follow_from="selfid_end",
                                                                 safe=False))(
            keys, jnp.asarray(q0s))
        return jnp.mean(losses)

    assert not np.isfinite(float(jax.jit(jax.grad(ungated))(p.log_m_a)))
    # every rollout failing: a saturated, finite loss and an exactly zero gradient
    info, g = vg(design.design_params(3.0, pose_noise=1e-4, controller=LINEAR_CTRL))
    assert float(info.failed_fraction) == 1.0 and np.isfinite(float(info.loss))
    assert float(g) == 0.0


@pytest.mark.slow
def test_implicit_pose_map_gradient_is_exact_and_never_raises_where_rollouts_fail():
    """An implicit-function pose map (Newton + implicit adjoint, as the hands'): where a rollout leaves the domain,
    0 * NaN cotangents reach the start pose through the waypoint targets and the adjoint solve raises; the guarded
    pose map (SafeTangentPose) does not, and where every rollout succeeds it gives the plain gradient."""
    system = linear_system(implicit_pose)
    q0s = np.array([[0.0, 0.0, 0.0], [0.25, 0.25, 0.25], [-0.27, 0.2, 0.0], [0.1, -0.26, 0.2]])
    kw = dict(iters=8, steps=220)
    key = jax.random.key(3)

    jitted = {safe: jax.jit(lambda p, q, safe=safe: design.design_value_and_grad(
        system, p, key, q, LINEAR_PATH, safe_tangent=safe, **kw)) for safe in (True, False)}

    def vg(p, safe, q=q0s):
        return jitted[safe](p, q)

    p = design.design_params(0.03, pose_noise=1e-4, controller=LINEAR_CTRL)
    info, g = vg(p, True)
    assert 0.0 < float(info.failed_fraction) < 1.0 and np.isfinite(float(g))
    with pytest.raises(jax.errors.JaxRuntimeError, match="non-finite"):
        vg(p, False)
    inside = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, -0.05, 0.02], [0.02, 0.02, -0.05]])  # stay in the box
    (i_safe, g_safe), (i_raw, g_raw) = vg(p, True, inside), vg(p, False, inside)
    assert float(i_safe.failed_fraction) == 0.0 and float(g_safe) != 0.0
    np.testing.assert_allclose(float(i_safe.loss), float(i_raw.loss), rtol=1e-12)
    np.testing.assert_allclose(float(g_safe), float(g_raw), rtol=1e-10)


@pytest.mark.slow
def test_refine_does_not_follow_an_unreliable_gradient():
    """From a point where most rollouts fail, every step is flagged and the point does not move; from a reliable
    point it descends."""
    system = linear_system(guarded_linear_pose)
    q0s = np.array([[0.0, 0.0, 0.0], [0.05, -0.05, 0.02]])
    run = jax.jit(lambda p: design.refine(system, p, jax.random.key(4), q0s, LINEAR_PATH, opt_steps=6,
                                          learning_rate=0.2, max_failed=0.1, iters=8, steps=220))
    bad = run(design.design_params(3.0, pose_noise=1e-4, controller=LINEAR_CTRL))
    assert not np.any(np.asarray(bad.reliable))
    np.testing.assert_allclose(np.asarray(bad.log_m_a), np.log(3.0))
    assert float(bad.best_loss) == np.inf and float(bad.best_log_m_a) == pytest.approx(np.log(3.0))
    good = run(design.design_params(0.02, pose_noise=1e-3, controller=LINEAR_CTRL))
    assert np.all(np.asarray(good.reliable))
    assert float(good.best_loss) < float(good.loss[0])
    assert float(good.best_log_m_a) > np.log(0.02)  # larger m_a is better on a linear map


@pytest.mark.slow
def test_two_link_grid_plus_gradient_finds_the_fine_grid_optimum_and_it_grows_with_noise():
    system = two_link()
    q0s = control.feasible_starts(system, ARM_PATH, jax.random.key(0), 12, ARM_CTRL, steps=435)
    key = jax.random.key(1)
    kw = dict(iters=12, n_trials=1, steps=435)
    coarse = np.geomspace(0.003, 0.3, 7)
    step = np.log(coarse[1] / coarse[0])
    fine = np.geomspace(0.003, 0.3, 31)
    opt = jax.jit(lambda p: design.optimize(system, p, coarse, key, q0s, ARM_PATH, opt_steps=15, learning_rate=0.1,
                                            **kw))
    brute = jax.jit(jax.vmap(lambda m, p: design.design_loss(system, p._replace(log_m_a=jnp.log(m)), key, q0s,
                                                             ARM_PATH, **kw), in_axes=(0, None)))
    optima = []
    for noise in (1e-3, 5e-3):
        p = design.design_params(0.01, pose_noise=noise, controller=ARM_CTRL)
        res = opt(p)
        best = float(res.scalar.best_log_m_a)
        losses = np.asarray(brute(fine, p))
        assert abs(best - np.log(fine[np.argmin(losses)])) <= step
        assert float(res.scalar.best_loss) <= float(res.grid.info.loss[res.grid.best])  # refinement never worse
        optima.append(best)
    assert optima[1] > optima[0]


# ------------------------------------------------------------------ the experiment

USER_ROBOT = {
    "experiment": "design",
    "seed": 0,
    "systems": [{"pose_fn": "selfid_jax.systems.two_link:two_link_pose", "n_act": 2, "task_dim": 2,
                 "params": [0.6, 0.4], "m_a": 0.02, "sample_box": {"low": [-1.0, 0.4], "high": [1.0, 2.2]},
                 "min_sigma": 0.05, "name": "my_arm"}],
    "path": {"kind": "star", "size": 0.04},
    "controller": {"max_step": 0.004, "tol": 0.001, "steps": 110},
    "m_a_grid": {"start": 0.003, "stop": 0.3, "num": 4},
    "pose_noise": [0.0005, 0.003],
    "n_configs": 2,
    "n_trials": 1,
    "eval_trials": 1,
    "iters": 6,
    "refine": {"steps": 3, "learning_rate": 0.1, "max_failed": 0.5},
    "chunk_size": 1,
}


@pytest.mark.slow
def test_experiment_end_to_end_for_a_user_robot(tmp_path, monkeypatch, capsys):
    from selfid_jax import cli

    cfg = tmp_path / "design_user.yaml"
    cfg.write_text(yaml.safe_dump(USER_ROBOT, sort_keys=False))
    out = tmp_path / "run"
    assert cli.main(["sweep", str(cfg), "--out", str(out), "--no-progress"]) == 0
    assert "my_arm: noise 0.5 mm" in capsys.readouterr().out
    df = pd.read_parquet(out / "results.parquet")
    counts = df.groupby(["noise_level", "stage"]).size().unstack()
    assert counts.loc[0].to_dict() == {"eval": 4, "grid": 4, "per_actuator": 3, "scalar": 3}
    assert np.all(np.isfinite(df["loss"])) and np.all(np.isfinite(df[df.stage != "eval"]["grad"]))
    summary = json.loads((out / "summary.json").read_text())
    levels = summary["systems"]["my_arm"]["noise_levels"]
    assert len(levels) == 2 and len(levels[0]["per_actuator_m_a"]) == 2
    for lv in levels:
        assert 0.003 <= lv["scalar_m_a"] <= 0.3
        assert set(lv["held_out"]) == {"default", "grid", "scalar", "per_actuator"}
    # the figures redraw from the saved results alone
    for name in ("design_curves.png", "design_optimum.png"):
        (out / "figures" / name).unlink()

    def no_compute(*args, **kwargs):
        raise AssertionError("plot must not compute")

    monkeypatch.setattr(design, "optimize", no_compute)
    monkeypatch.setattr(design, "design_loss", no_compute)
    assert cli.main(["plot", str(out)]) == 0
    for name in ("design_curves.png", "design_optimum.png"):
        assert (out / "figures" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
