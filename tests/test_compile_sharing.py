"""Compile-time work of issue 14: fewer programs. The sweep shares one compilation between a pre-run
(compute_rows) and the sweep; the valid-region feasibility check runs on the study's own program and
picks the same configurations as control.feasible_starts; the ablation compiles two rollout loops
whatever the number of methods."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from selfid_jax.experiments.common.schema import ControllerConfig

from selfid_jax import control
from selfid_jax import runner as experiment
from selfid_jax.control import paths
from selfid_jax.runner import sweep


def _fn(p):
    return {"y": jnp.sin(p["x"]).sum(axis=1) * p["s"], "z": p["x"][:, :2]}


def test_compute_rows_matches_run_chunked_and_shares_its_compilation(tmp_path):
    rng = np.random.default_rng(0)
    params = {"x": rng.normal(size=(10, 3)), "s": rng.uniform(size=10)}
    batch = sweep.compiled_batch(10, 4)
    before = len(sweep._EXECUTABLES)
    rows = sweep.compute_rows(_fn, params, batch=batch)
    assert len(sweep._EXECUTABLES) == before + 1
    df = sweep.run_chunked(_fn, params, chunk_size=4, out_dir=tmp_path / "run", progress=False)
    assert len(sweep._EXECUTABLES) == before + 1  # the sweep found the program compute_rows compiled
    np.testing.assert_allclose(df["y"].to_numpy(), rows["y"], rtol=1e-12)
    np.testing.assert_allclose(np.stack(df["z"].to_numpy()), rows["z"], rtol=1e-12)
    np.testing.assert_allclose(rows["y"], np.sin(params["x"]).sum(axis=1) * params["s"], rtol=1e-12)
    assert rows["y"].shape == (10,) and rows["z"].shape == (10, 2)


@pytest.mark.slow
def test_valid_region_feasibility_equals_control_feasible_starts():
    from selfid_jax.experiments import valid_region as vr

    from selfid_jax.systems import two_link

    system = two_link()
    ctrl = ControllerConfig(max_step=0.01, tol=0.002, steps=200, gain=1.0)
    path = paths.star(size=0.2, dim=system.task_dim)
    static = vr.Static(system, path, ctrl.steps)
    key = jax.random.key(3)
    got = vr.feasible_configs(static, key, 5, ctrl, batch=32)
    want = control.feasible_starts(system, path, key, 5, control.ControllerParams(**ctrl.traced()), steps=ctrl.steps)
    np.testing.assert_array_equal(got, np.asarray(want))


@pytest.mark.slow
def test_ablation_program_has_two_rollout_loops_whatever_the_methods(monkeypatch):
    """The fixed estimates of every method share one vmapped rollout; `true` has the other."""
    from selfid_jax.experiments import ablation

    calls = []
    follow = control.follow

    def counting(*args, **kwargs):
        calls.append(type(args[1]).__name__)
        return follow(*args, **kwargs)

    monkeypatch.setattr(ablation.control, "follow", counting)
    base = {"experiment": "ablation", "system": "two_link", "iterations": [2, 5], "n_configs": 1, "n_trials": 1,
            "pose_noise": [0.0], "rot_noise": [0.0], "m_a": [0.03], "eps": 0.5, "path": {"kind": "star", "size": 0.2},
            "controller": {"max_step": 0.01, "tol": 0.002, "steps": 300, "gain": 1.0}}
    names = ["true", "ours", "direct", "rls", "broyden"]
    exp = experiment.get("ablation")
    for k in (2, 5):
        cfg = exp.config.model_validate({**base, "methods": [{"name": n, "method": n} for n in names[:k]]})
        part = exp.parts(cfg)[0]
        calls.clear()
        out = jax.eval_shape(exp.batched(part.static), part.params)
        assert sorted(calls) == ["Fixed", "JacobianInverse"], (k, calls)
        assert out.completion.shape == (1, k, 2) and out.converged_at.shape == (1, k)


class _Scale:
    """A host function whose behaviour lives in its state, as a native-MuJoCo callback's model does."""

    def __init__(self, factor):
        self.factor = factor

    def __call__(self, x):
        return np.asarray(x) * self.factor


def test_programs_with_different_host_callbacks_are_not_shared():
    """Two programs that lower to the same text but call different host functions keep their own compilation."""
    def rows(cb):
        return lambda p: {"y": jax.pure_callback(cb, jax.ShapeDtypeStruct(p["x"].shape, p["x"].dtype), p["x"],
                                                 vmap_method="sequential")}

    params = {"x": np.arange(4.0)}
    twice = sweep.compute_rows(rows(_Scale(2.0)), params, batch=4)
    thrice = sweep.compute_rows(rows(_Scale(3.0)), params, batch=4)
    np.testing.assert_array_equal(twice["y"], 2 * params["x"])
    np.testing.assert_array_equal(thrice["y"], 3 * params["x"])
