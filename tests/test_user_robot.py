"""A user's MuJoCo robot from a config alone: implicit integrator, tendon-driven pair, a held joint and a
free-floating box; self-identified and following a star through `selfid-jax sweep`."""

import json

import numpy as np
import pandas as pd
import pytest
import yaml
from helpers_mjcf import TENDON_ARM_XML

from selfid_jax import cli

pytestmark = pytest.mark.slow  # end-to-end sweep through the CLI


def test_user_mjcf_runs_through_sweep_from_a_config(tmp_path, capsys):
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "tendon_arm.xml").write_text(TENDON_ARM_XML)
    config = {
        "experiment": "ablation",
        "seed": 0,
        "system": {
            "mjcf": "robots/tendon_arm.xml",  # relative to this config file
            "site": "tip",
            "actuators": ["a1", "a_pair", "a2", "a3"],
            "joints_fixed": {"jh": 0.3},
            "task_dim": 3,
            "home": [0.0, 0.2, 0.5, 0.8],
            "min_sigma": 0.05,
        },
        "methods": [{"name": "ours", "method": "ours"}, {"name": "true", "method": "true"}],
        "iterations": [2, 30],
        "n_configs": 2,
        "n_trials": 1,
        "pose_noise": [0.0],
        "rot_noise": [0.0],
        "m_a": [0.02],
        "eps": 0.5,
        "path": {"kind": "star", "size": 0.02},
        "controller": {"max_step": 0.002, "tol": 0.0005, "steps": 150},
        "chunk_size": 4,
    }
    cfg = tmp_path / "user_arm.yaml"  # names the MJCF relative to itself; the tests run from another directory
    cfg.write_text(yaml.safe_dump(config, sort_keys=False))
    out = tmp_path / "run"
    assert cli.main(["sweep", str(cfg), "--out", str(out), "--no-progress"]) == 0
    df = pd.read_parquet(out / "results.parquet")
    assert (out / "parts" / "tendon_arm" / "manifest.json").is_file()
    ours = df[(df.method == "ours") & (df.iterations == 30)]
    np.testing.assert_array_equal(ours.completion, 1.0)
    np.testing.assert_array_equal(df[df.method == "true"].completion, 1.0)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["methods"]["ours"]["converged_fraction"] == 1.0
    assert "ours" in capsys.readouterr().out


def test_urdf_arm_runs_through_sweep_from_a_config(tmp_path):
    """A URDF with no sites or actuators: POM on its fixed-joint tool link (body + offset), actuators = joints."""
    from helpers_mjcf import URDF

    (tmp_path / "arm3.urdf").write_text(URDF)
    config = {
        "experiment": "ablation",
        "seed": 0,
        "system": {"mjcf": "arm3.urdf", "body": "tool", "offset": [0.0, 0.0, 0.03], "actuators": "joints",
                   "task_dim": 3, "home": [0.0, 0.6, 1.0], "min_sigma": 0.02},
        "methods": [{"name": "ours", "method": "ours"}, {"name": "true", "method": "true"}],
        "iterations": [30],
        "n_configs": 2,
        "n_trials": 1,
        "pose_noise": [0.0],
        "rot_noise": [0.0],
        "m_a": [0.02],
        "eps": 0.5,
        "path": {"kind": "star", "size": 0.02},
        "controller": {"max_step": 0.002, "tol": 0.0005, "steps": 150},
        "chunk_size": 4,
    }
    cfg = tmp_path / "urdf_arm.yaml"
    cfg.write_text(yaml.safe_dump(config, sort_keys=False))
    out = tmp_path / "run"
    assert cli.main(["sweep", str(cfg), "--out", str(out), "--no-progress"]) == 0
    df = pd.read_parquet(out / "results.parquet")
    np.testing.assert_array_equal(df[df.method == "ours"].completion, 1.0)
    np.testing.assert_array_equal(df[df.method == "true"].completion, 1.0)
