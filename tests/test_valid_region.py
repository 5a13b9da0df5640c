"""The valid-region study end to end at small size: bounds, files, resume, plot without simulation."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from selfid_jax import cli, control
from selfid_jax.runner.registry import load as load_config

pytestmark = pytest.mark.slow  # end-to-end sweep through the CLI

CONFIG = {
    "experiment": "valid_region",
    "seed": 0,
    "systems": ["two_link"],
    "eps_limits": {"start": 0.2, "stop": 2.2, "num": 11},
    "n_configs": 3,
    "n_trials": 3,
    "path": {"kind": "star", "size": 0.2},
    "controller": {"max_step": 0.01, "tol": 0.002, "steps": 435, "gain": 1.0},
    "completion_threshold": 0.95,
    "chunk_size": 40,
}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("vr")
    cfg_path = tmp / "vr_small.yaml"
    cfg_path.write_text(yaml.safe_dump(CONFIG))
    out = tmp / "run"
    assert cli.main(["sweep", str(cfg_path), "--out", str(out), "--no-progress"]) == 0
    return out


def is_png(path: Path) -> bool:
    return path.stat().st_size > 1000 and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_two_link_valid_region_contains_one(run_dir):
    import json

    summary = json.loads((run_dir / "summary.json").read_text())
    bounds = summary["systems"]["two_link"]
    assert bounds["contains_one"]
    assert bounds["lower"] < 0.7 and bounds["upper"] > 1.3
    df = pd.read_parquet(run_dir / "results.parquet")
    assert len(df) == 11 * 3 * 3
    assert set(df.columns) >= {"system", "eps_limit", "config_id", "trial", "completion", "mean_error", "failed"}
    at_one = df[np.isclose(df.eps_limit, 1.0)]
    np.testing.assert_array_equal(at_one.completion, 1.0)  # m_eps = 1: the true inverse Jacobian
    assert np.all(np.isfinite(df.mean_error))
    assert summary["controller"]["max_step"] == 0.01  # the protocol is stated beside the bounds
    for ext in ("png", "pdf"):
        f = run_dir / "figures" / f"valid_region.{ext}"
        assert f.stat().st_size > 1000
    assert is_png(run_dir / "figures" / "valid_region.png")


def test_plot_redraws_from_saved_results_without_simulating(run_dir, monkeypatch):
    fig = run_dir / "figures" / "valid_region.png"
    fig.unlink()

    def no_sim(*args, **kwargs):
        raise AssertionError("plot must not simulate")

    monkeypatch.setattr(control, "follow", no_sim)
    assert cli.main(["plot", str(run_dir)]) == 0
    assert is_png(fig)


def test_resume_gives_identical_table(run_dir, tmp_path):
    from selfid_jax import runner as experiment

    exp = experiment.get("valid_region")
    cfg = load_config(run_dir / "config.yaml")
    full = pd.read_parquet(run_dir / "results.parquet")
    part = tmp_path / "part"
    experiment.run(exp, cfg, part)
    chunks = sorted((part / "parts" / "two_link" / "chunks").glob("*.parquet"))
    assert len(chunks) == 3
    # simulate a sweep killed after its first chunk: later chunks and the final tables are missing
    for f in chunks[1:] + [part / "results.parquet", part / "parts" / "two_link" / "results.parquet"]:
        f.unlink()
    first_chunk_mtime = chunks[0].stat().st_mtime_ns
    resumed, _ = experiment.run(exp, cfg, part)
    assert chunks[0].stat().st_mtime_ns == first_chunk_mtime  # finished work was not recomputed
    pd.testing.assert_frame_equal(resumed.reset_index(drop=True), full.reset_index(drop=True))
    pd.testing.assert_frame_equal(pd.read_parquet(part / "results.parquet"), full)


def test_infeasible_path_is_a_usage_error_before_the_run_directory_exists(tmp_path, capsys):
    cfg_path = tmp_path / "too_big.yaml"
    cfg_path.write_text(yaml.safe_dump(dict(CONFIG, path={"kind": "star", "size": 5.0})))  # 2-link reach is 2 m
    out = tmp_path / "run"
    assert cli.main(["sweep", str(cfg_path), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert str(cfg_path) in err and "cannot set up experiment 'valid_region'" in err and "complete" in err
    assert "Traceback" not in err and not out.exists()
