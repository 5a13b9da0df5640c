"""The experiment contract: entry-point registry, one compilation per sweep, the layer contracts."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pydantic
import pytest
from selfid_jax.experiments.common.schema import ControllerConfig, EpsLimits, PathConfig

import selfid_jax
from selfid_jax import cli
from selfid_jax import runner as experiment
from selfid_jax.runner.config import BaseConfig
from selfid_jax.runner.errors import ConfigError

PACKAGE = Path(selfid_jax.__file__).resolve().parent


def test_shipped_experiments_come_from_entry_points():
    names = experiment.available()
    assert {"demo", "valid_region", "ablation"} <= set(names)
    for name in ("demo", "valid_region", "ablation"):
        exp = experiment.get(name)
        assert exp.name == name and exp.config.model_fields["experiment"].default == name
        assert exp.description
    with pytest.raises(ConfigError, match="unknown experiment 'nope'.*valid_region"):
        experiment.get("nope")


@pytest.mark.slow
def test_layer_contracts_hold():
    """import-linter's contracts of pyproject.toml: layers, a domain-free runner, a lean API, no import cycle."""
    lint = shutil.which("lint-imports", path=os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]]))
    assert lint is not None, "lint-imports (import-linter, in the test extra) is not installed"
    out = subprocess.run([lint, "--no-cache"], cwd=PACKAGE.parent, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert " kept, 0 broken" in out.stdout


@pytest.mark.slow
def test_experiments_install_under_the_package_namespace(tmp_path):
    """An ``experiments`` folder in the user's working directory does not shadow the registered experiments."""
    (tmp_path / "experiments").mkdir()
    (tmp_path / "experiments" / "__init__.py").write_text("raise ImportError('the user package was imported')\n")
    code = ("import selfid_jax as sj; e = sj.runner.get('valid_region'); "
            "print(type(e).__module__, e.config.__module__)")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(PACKAGE.parent)})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["selfid_jax.runner.contract", "selfid_jax.experiments.valid_region"]
    bare = tmp_path / "bare"
    bare.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([sys.executable, "-c", "import importlib.util as u; print(u.find_spec('experiments'))"],
                         cwd=bare, capture_output=True, text=True, timeout=60, env=env)
    # no top-level package installed
    assert out.returncode == 0 and out.stdout.strip() == "None", out.stdout + out.stderr


@pytest.mark.slow  # compile-heavy: the fast tier stays about a minute
def test_valid_region_sweep_of_controller_and_eps_values_compiles_once():
    """Every sweepable number is a traced Params field: one trace for rows with different values."""
    from selfid_jax.experiments.valid_region import ValidRegionConfig

    cfg = ValidRegionConfig(systems=["two_link"], eps_limits=EpsLimits(start=0.5, stop=1.5, num=2), n_configs=1,
                            n_trials=2, controller=ControllerConfig(max_step=0.01, tol=0.002, steps=200),
                            path=PathConfig(size=0.2))
    exp = experiment.get("valid_region")
    (part,) = exp.parts(cfg)
    assert part.params.controller.tol.shape == (4,)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def run(params):
        return exp.batched(part.static)(params)

    first = run(part.params)
    swept = part.params._replace(
        controller=part.params.controller._replace(max_step=np.full(4, 0.02), tol=np.full(4, 0.004),
                                                   gain=np.full(4, 0.5)),
        eps_limit=np.asarray([0.9, 1.0, 1.1, 1.2]),
    )
    second = run(swept)
    assert first.steps_used.shape == (4,) and not np.array_equal(first.steps_used, second.steps_used)


# --------------------------------------------------------------------------- a user's own experiment

class DoublingConfig(BaseConfig):
    experiment: str = "user_doubling"
    values: list[float] = pydantic.Field(min_length=1)
    scale: float = 2.0


class DoublingParams(NamedTuple):
    x: jax.Array  # ()
    scale: jax.Array  # ()


class DoublingOutputs(NamedTuple):
    y: jax.Array  # () scale * x
    pair: jax.Array  # (2,) (x, y)


def _build(cfg):
    meta = pd.DataFrame({"x": cfg.values})
    params = DoublingParams(np.asarray(cfg.values), np.full(len(cfg.values), cfg.scale))
    return experiment.Part("only", None, params, meta)


def _compute(static, p):
    y = p.scale * p.x
    return DoublingOutputs(y, jnp.stack([p.x, y]))


def _plot(table, summary, out_dir):
    from matplotlib.figure import Figure
    from selfid_jax.experiments.common.figures import save_figure

    fig = Figure(figsize=(2, 2))
    fig.subplots().plot(table["x"], table["y"], "o")
    return save_figure(fig, out_dir, "doubling")


USER = experiment.Experiment(
    name="user_doubling", config=DoublingConfig, build=_build, compute=_compute,
    summarize=lambda table, cfg: {"sum_y": float(table["y"].sum())}, plot=_plot,
    report=lambda s: f"sum of y: {s['sum_y']:g}", description="doubles numbers (a user's experiment)",
)


@pytest.mark.slow
def test_user_registered_experiment_runs_through_the_cli(tmp_path, capsys):
    experiment.register(USER)
    cfg = tmp_path / "user.yaml"
    cfg.write_text("experiment: user_doubling\nvalues: [1.0, 2.5, -3.0]\nchunk_size: 2\n")
    out = tmp_path / "run"
    assert cli.main(["sweep", str(cfg), "--out", str(out), "--no-progress", "--set", "scale=3"]) == 0
    printed = capsys.readouterr().out
    assert "sum of y: 1.5" in printed and "doubling.png" in printed
    table = pd.read_parquet(out / "results.parquet")
    np.testing.assert_allclose(table["y"], [3.0, 7.5, -9.0])
    np.testing.assert_allclose(np.stack(table["pair"].to_numpy()), [[1.0, 3.0], [2.5, 7.5], [-3.0, -9.0]])
    assert (out / "parts" / "only" / "chunks").is_dir()
    assert cli.main(["list"]) == 0
    listing = capsys.readouterr().out
    assert "user_doubling" in listing and "doubles numbers" in listing and "valid_region" in listing
    assert "ur5e" in listing and "two_link" in listing


def test_experiment_definition_errors():
    with pytest.raises(ValueError, match="identifier"):
        experiment.Experiment(name="bad name", config=DoublingConfig, build=_build, compute=_compute,
                              summarize=lambda t, c: {})
    with pytest.raises(TypeError, match="BaseConfig"):
        experiment.Experiment(name="bad", config=dict, build=_build, compute=_compute, summarize=lambda t, c: {})
    with pytest.raises(TypeError, match="Experiment"):
        experiment.register("valid_region")


@pytest.mark.slow
def test_demo_takes_any_system_from_a_config(tmp_path, capsys):
    cfg = tmp_path / "demo_two_link.yaml"
    cfg.write_text("experiment: demo\nruns:\n  - {system: two_link, n_configs: 2, iters: 20, m_a: 0.02, eps: 0.05,\n"
                   "     path: {size: 0.2}, controller: {max_step: 0.01, tol: 0.002, steps: 300}}\n")
    out = tmp_path / "run"
    assert cli.main(["sweep", str(cfg), "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "two_link self-ID from 2 start configurations" in printed and "null-space" not in printed  # n == m
    summary = json.loads((out / "summary.json").read_text())["runs"]["two_link"]
    assert summary["n_act"] == 2 and summary["task_dim"] == 2
    assert summary["completion_estimated"] == [1.0, 1.0]
    assert (out / "figures" / "demo.png").stat().st_size > 1000


@pytest.mark.slow
def test_demo_law_is_the_inverse_jacobian_law_and_keeps_the_start_jacobian():
    """The demo's step law moves as control.follow with estimate_or_true does, and its state is the Jacobian at
    the start (MuJoCo-free closed form: the two-link arm's), read by the loop's first step."""
    from selfid_jax.experiments import demo

    from selfid_jax import control
    from selfid_jax.control import paths
    from selfid_jax.systems import two_link

    arm, q0, path = two_link(), jnp.array([0.4, 1.2]), paths.star(size=0.05, dim=2)
    est = 1.1 * arm.true_inverse_jacobian(q0)
    ctrl = control.ControllerParams(max_step=0.004, tol=0.001)
    l1, l2 = 1.0, 1.0  # the two-link arm's link lengths
    s1, c1, s12, c12 = np.sin(0.4), np.cos(0.4), np.sin(1.6), np.cos(1.6)
    J_closed = np.array([[-l1 * s1 - l2 * s12, -l2 * s12], [l1 * c1 + l2 * c12, l2 * c12]])

    @chex.assert_max_traces(n=1)
    def run(use_true):
        return control.follow_law(arm, demo.start_jacobian_law(arm, est, use_true), path, q0, ctrl, steps=120)

    lanes, (J0, seen) = jax.jit(jax.vmap(run))(jnp.array([False, True]))
    # the references: one jitted program for both (op by op they were dozens of small compilations)
    refs = jax.jit(lambda: [control.follow(arm, control.estimate_or_true(est, use_true), path, q0, ctrl, steps=120)
                            for use_true in (False, True)])()
    for lane, ref in enumerate(refs):
        got = jax.tree.map(lambda x, i=lane: x[i], lanes)
        for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got), strict=True):
            np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(J0[lane], J_closed, rtol=1e-12, atol=1e-12)
        assert bool(seen[lane])
    assert float(lanes.completion[1]) == 1.0


def planar_two_link(params, q):
    """Unit 2-link arm in the plane (for a pose_fn system spec)."""
    a = jnp.cumsum(q)
    return jnp.stack([jnp.sum(jnp.cos(a)), jnp.sum(jnp.sin(a))])


@pytest.mark.slow
def test_a_float64_system_beside_a_float32_one_in_one_sweep(tmp_path):
    """x64: true on one system runs its part in float64; the other part keeps the default dtype and its numbers."""
    import jax as _jax
    import yaml

    base = {"experiment": "valid_region", "eps_limits": {"start": 0.8, "stop": 1.2, "num": 3}, "n_configs": 2,
            "n_trials": 2, "path": {"size": 0.2}, "controller": {"max_step": 0.01, "tol": 0.002, "steps": 300},
            "chunk_size": 12}
    spec = {"pose_fn": "test_experiment:planar_two_link", "n_act": 2, "task_dim": 2, "name": "two_link_f64",
            "sample_box": {"low": [-1.0, 0.4], "high": [1.0, 2.4]}, "x64": True}
    runs = {}
    with _jax.enable_x64(False):
        cfg = tmp_path / "mixed.yaml"
        cfg.write_text(yaml.safe_dump({**base, "systems": ["two_link", spec]}))
        assert cli.main(["sweep", str(cfg), "--out", str(tmp_path / "mixed"), "--no-progress"]) == 0
        runs["mixed"] = pd.read_parquet(tmp_path / "mixed" / "results.parquet")
        # the reference: the same sweep of two_link alone, through the runner (the command line's figures and
        # report are not what is compared)
        exp = experiment.get("valid_region")
        experiment.run(exp, exp.config(**{**base, "systems": ["two_link"]}), tmp_path / "alone")
        runs["alone"] = pd.read_parquet(tmp_path / "alone" / "results.parquet")
    manifests = {p: json.loads((tmp_path / "mixed" / "parts" / p / "manifest.json").read_text())
                 for p in ("two_link", "two_link_f64")}
    assert manifests["two_link_f64"]["x64"] is True and manifests["two_link"]["x64"] is False
    mixed = runs["mixed"]
    # same numbers (the combined table holds them in float64 beside the float64 part)
    pd.testing.assert_frame_equal(mixed[mixed.system == "two_link"].reset_index(drop=True), runs["alone"],
                                  check_dtype=False)
    assert np.all(mixed[mixed.system == "two_link_f64"].completion.notna())


def test_part_names_cannot_leave_the_run_directory():
    """The runner refuses part names that are not one safe path component, whatever the experiment builds."""
    for bad in ["../escape", "/tmp/abs", "a/b", "..", ".x", ""]:
        exp = experiment.Experiment(name="bad_names", config=BaseConfig,
                                    build=lambda cfg, n=bad: experiment.Part(n, None, {}, pd.DataFrame()),
                                    compute=lambda s, p: p, summarize=lambda df, cfg: {})
        with pytest.raises(ValueError, match="one path component"):
            exp.parts(BaseConfig(experiment="bad_names"))


def _build_two(cfg):
    meta = pd.DataFrame({"x": cfg.values})
    params = DoublingParams(np.asarray(cfg.values), np.full(len(cfg.values), cfg.scale))
    return [experiment.Part("first", None, params, meta),
            experiment.Part("second", None, params._replace(scale=params.scale + 1.0), meta)]


_TRACED_IN: list[str] = []


def _compute_noting_thread(static, p):
    import threading

    _TRACED_IN.append(threading.current_thread().name)
    return _compute(static, p)


TWO_PARTS = experiment.Experiment(
    name="user_doubling_two_parts", config=DoublingConfig, build=_build_two, compute=_compute_noting_thread,
    summarize=lambda table, cfg: {"sum_y": float(table["y"].sum())}, description="two parts (a user's experiment)",
)


def test_parts_run_side_by_side_in_threads_and_give_the_tables_they_give_in_turn(tmp_path, monkeypatch, capsys):
    """Two parts on two threads: the same table, row for row, as one after the other, each part traced in a worker
    thread under the caller's float width; SELFID_JAX_PART_THREADS chooses, and a bad value is named."""
    import jax as _jax

    from selfid_jax.runner.execute import part_threads

    cfg = DoublingConfig(experiment="user_doubling_two_parts", values=[1.0, 2.5, -3.0, 4.0], chunk_size=3)
    tables = {}
    for threads in ("1", "2"):
        monkeypatch.setenv("SELFID_JAX_PART_THREADS", threads)
        _TRACED_IN.clear()
        with _jax.enable_x64(False):  # a caller's setting context: the worker threads must see it too
            table, _ = experiment.run(TWO_PARTS, cfg, tmp_path / threads, fresh=True)
        assert len(_TRACED_IN) == 2
        assert all(name.startswith("selfid-jax-part") for name in _TRACED_IN) == (threads == "2"), _TRACED_IN
        tables[threads] = table
        for part in ("first", "second"):
            manifest = json.loads((tmp_path / threads / "parts" / part / "manifest.json").read_text())
            assert manifest["x64"] is False
    pd.testing.assert_frame_equal(tables["1"], tables["2"])
    np.testing.assert_allclose(tables["2"]["y"], [2.0, 5.0, -6.0, 8.0, 3.0, 7.5, -9.0, 12.0])
    monkeypatch.setenv("SELFID_JAX_PART_THREADS", "0")
    with pytest.raises(ValueError, match="SELFID_JAX_PART_THREADS must be a positive integer, got '0'"):
        part_threads(2)
    # the command line names it in one line, exit 2, before it builds anything
    from selfid_jax.runner import command_line as runner_cli

    experiment.register(TWO_PARTS)
    path = tmp_path / "two.yaml"
    path.write_text("experiment: user_doubling_two_parts\nvalues: [1.0]\n")
    monkeypatch.setattr(runner_cli, "_build", lambda *a: pytest.fail("built before the bad setting was named"))
    assert cli.main(["sweep", str(path), "--out", str(tmp_path / "bad"), "--no-progress"]) == 2
    assert "SELFID_JAX_PART_THREADS must be a positive integer, got '0'" in capsys.readouterr().err
    monkeypatch.delenv("SELFID_JAX_PART_THREADS")
    assert part_threads(1) == 1 and 1 <= part_threads(64) <= 64
