"""Estimation ablation at small size: oracle bound, ours vs direct, noise, convergence bookkeeping, figures."""

import json

import numpy as np
import pandas as pd
import pytest
import yaml

from selfid_jax import cli

slow = pytest.mark.slow  # end-to-end sweeps through the CLI
pytestmark = pytest.mark.xdist_group("ablation")  # one worker: the `run_dir` sweep is run once, not per worker

CONFIG = {
    "experiment": "ablation",
    "seed": 1,
    "system": "ur5e",
    "methods": [
        {"name": "true", "method": "true"},
        {"name": "ours", "method": "ours"},
        {"name": "direct", "method": "direct"},
        {"name": "broyden", "method": "broyden"},
    ],
    "iterations": [2, 20],
    "n_configs": 3,
    "n_trials": 2,
    "pose_noise": [0.0, 0.001],
    "rot_noise": [0.0, 0.0175],
    "m_a": [0.03],
    "eps": 0.5,
    "path": {"kind": "star", "size": 0.05},
    "controller": {"max_step": 0.0025, "tol": 0.0005, "steps": 435, "gain": 1.0},
    "chunk_size": 48,  # two chunks of 48 rows: a small batch runs the 435 steps about as long as a large one
}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("abl")
    cfg = tmp / "ablation_small.yaml"
    cfg.write_text(yaml.safe_dump(CONFIG, sort_keys=False))
    out = tmp / "run"
    assert cli.main(["sweep", str(cfg), "--out", str(out), "--no-progress"]) == 0
    return out


@slow
def test_ablation_table_bounds_and_methods(run_dir):
    df = pd.read_parquet(run_dir / "results.parquet")
    assert len(df) == 4 * 2 * (3 * 2 * 2)  # methods x iteration counts x (configs x trials x noise levels)
    for col in ("completion", "mean_error"):
        assert np.all(np.isfinite(df[col]))
    true = df[df.method == "true"]
    np.testing.assert_array_equal(true.completion, 1.0)
    clean = df[df.pose_noise == 0].sort_values(["config_id", "trial"])

    def completion(method, iterations):
        return clean[(clean.method == method) & (clean.iterations == iterations)].completion.to_numpy()

    # 2 samples < 3 task dims: least squares from zero ("direct") has no component along the unexcited
    # direction and cannot steer there; the signed x magnitude guess ("ours") fills it in
    assert completion("direct", 2).max() == 0.0
    assert completion("ours", 2).mean() > 0.0
    # 20 samples: least squares has one solution, so the initial guess no longer matters
    np.testing.assert_allclose(completion("ours", 20), completion("direct", 20))
    assert completion("ours", 20).mean() >= 0.9
    # with tracker noise nothing turns NaN and the estimates still steer somewhere
    noisy = df[(df.pose_noise > 0) & (df.method == "ours") & (df.iterations == 20)]
    assert np.all(np.isfinite(noisy.mean_error)) and noisy.completion.mean() > 0


@slow
def test_summary_and_figures(run_dir):
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["methods"]["true"]["iterations_to_threshold"] == 2
    assert set(summary["methods"]) == {"true", "ours", "direct", "broyden"}
    for name in ("ablation", "ablation_noise"):
        for ext in ("png", "pdf"):
            assert (run_dir / "figures" / f"{name}.{ext}").stat().st_size > 1000


@slow
def test_config_errors_name_key(tmp_path):
    from selfid_jax.runner.errors import ConfigError
    from selfid_jax.runner.registry import load as load_config

    bad = dict(CONFIG, rot_noise=[0.0])
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(ConfigError, match="rot_noise"):
        load_config(path)
    bad = dict(CONFIG, methods=[{"name": "x", "method": "ours", "options": {"magnitude": "mode"}}])
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(ConfigError, match="magnitude"):
        load_config(path)


# ----------------------------------------------------------------------------- E-KM rows (issue 16)
HARD = {"scale": [1.5, 0.6], "offset": [0.6, -0.6]}
EASY = {"scale": [1.2, 0.8], "offset": [0.1, -0.1]}
EKM_CONFIG = {
    "experiment": "ablation",
    "seed": 0,
    "system": "two_link",
    "methods": [
        {"name": "true", "method": "true"},
        {"name": "ours", "method": "ours"},
        {"name": "ekm fixed easy", "method": "ekm", "options": {"mode": "fixed"}, "nominal": EASY},
        {"name": "ekm online easy", "method": "ekm", "options": {"mode": "online"}, "nominal": EASY},
        {"name": "ekm fixed hard", "method": "ekm", "options": {"mode": "fixed"}, "nominal": HARD},
        {"name": "ekm online hard", "method": "ekm", "options": {"mode": "online"}, "nominal": HARD},
    ],
    "iterations": [1, 5],
    "n_configs": 2,
    "n_trials": 1,
    "pose_noise": [0.0],
    "rot_noise": [0.0],
    "m_a": [0.05],
    "eps": 0.1,
    "path": {"kind": "star", "size": 0.2},
    "controller": {"max_step": 0.01, "tol": 0.002, "steps": 435, "gain": 1.0},
    "chunk_size": 24,  # the 24 rows in one chunk: twelve chunks of 2 took ~5 s more to run the same rows
}


@slow
def test_ekm_rows_end_to_end(tmp_path):
    """Fixed / online x easy / hard E-KM rows next to ours and true on a 2-link star, one compiled program."""
    cfg = tmp_path / "ekm.yaml"
    cfg.write_text(yaml.safe_dump(EKM_CONFIG, sort_keys=False))
    out = tmp_path / "run"
    assert cli.main(["sweep", str(cfg), "--out", str(out), "--no-progress"]) == 0
    df = pd.read_parquet(out / "results.parquet")
    assert len(df) == 6 * 2 * 2  # methods x iteration counts x configs
    assert np.all(np.isfinite(df.completion)) and np.all(np.isfinite(df.mean_error)) and not df.failed.any()
    np.testing.assert_array_equal(df[df.method == "true"].completion, 1.0)
    # the study's finding (experiments/ekm_study.py): the hard wrong model plus an online GP completes the
    # star from ONE self-ID sample, where the model-free estimate from one sample cannot
    hard = df[(df.method == "ekm online hard") & (df.iterations == 1)]
    np.testing.assert_array_equal(hard.completion, 1.0)
    assert df[(df.method == "ours") & (df.iterations == 1)].completion.max() < 0.5
    assert df[df.method.str.startswith("ekm")].converged_at.ge(-1).all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["methods"]["ekm online hard"]["iterations_to_threshold"] == 1


def _ekm_error(tmp_path, match, **method):
    from selfid_jax.runner.errors import ConfigError
    from selfid_jax.runner.registry import load as load_config

    bad = dict(EKM_CONFIG, methods=[{"name": "true", "method": "true"}, {"name": "x", **method}])
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(ConfigError, match=match):
        load_config(path)


def test_ekm_config_errors_name_key(tmp_path):
    _ekm_error(tmp_path, r"methods\[1\].*nominal: required", method="ekm", options={"mode": "online"})
    _ekm_error(tmp_path, r"methods\[1\].*nominal: only model-based", method="ours", nominal=EASY)
    _ekm_error(tmp_path, r"methods\[1\].*nominal\.scale", method="ekm", nominal={"scale": [1.0, 1.0, 1.0]})
    _ekm_error(tmp_path, r"methods\[1\].*nominal\.offset", method="ekm", nominal={"offset": [0.1]})
    _ekm_error(tmp_path, r"nominal.*unexpected|extra|scales", method="ekm", nominal={"scales": 1.0})
    _ekm_error(tmp_path, r"methods\[1\].*options: q0", method="ekm", options={"q0": 0.1}, nominal=EASY)
    _ekm_error(tmp_path, "mode", method="ekm", options={"mode": "sometimes"}, nominal=EASY)
