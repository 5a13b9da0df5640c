"""Shipped configs are package data, found by name from any directory: ``selfid-jax sweep valid_region_two_link``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from selfid_jax import cli
from selfid_jax.runner.cli import _find_config
from selfid_jax.runner.errors import ConfigError

INSTALLED = dict(cli._config_dirs())["installed"]  # the data package selfid_jax.configs


def test_configs_are_installed_and_names_resolve_local_first(tmp_path, monkeypatch):
    repo = Path(__file__).resolve().parents[1] / "configs"
    assert sorted(p.name for p in INSTALLED.glob("*.yaml")) == sorted(p.name for p in repo.glob("*.yaml"))
    monkeypatch.chdir(tmp_path)
    dirs = cli._config_dirs()
    assert _find_config(Path("valid_region_ur5e"), dirs) == INSTALLED / "valid_region_ur5e.yaml"
    assert _find_config(Path("valid_region_ur5e.yaml"), dirs) == INSTALLED / "valid_region_ur5e.yaml"
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "valid_region_ur5e.yaml").write_text("experiment: valid_region\n")
    assert _find_config(Path("valid_region_ur5e"), dirs) == Path("configs/valid_region_ur5e.yaml")  # local first
    with pytest.raises(ConfigError, match=r"no nonesuch.yaml in configs or .*selfid-jax list"):
        _find_config(Path("nonesuch"), dirs)
    assert _find_config(Path("sub/nonesuch"), dirs) == Path("sub/nonesuch")  # a path is reported as that path


def test_list_names_where_configs_live_and_a_named_config_runs_from_an_empty_directory(tmp_path, monkeypatch,
                                                                                        capsys):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    assert f"configs (installed: {INSTALLED}" in out and "valid_region_ur5e " in out
    assert "configs (./configs: configs): none" in out
    args = ["sweep", "valid_region_two_link", "--no-progress", "--set", "n_configs=2", "--set", "n_trials=1",
            "--set", "eps_limits.num=2"]
    assert cli.main(args) == 0
    assert (tmp_path / "runs" / "valid_region_two_link" / "results.parquet").is_file()
    source = json.loads((tmp_path / "runs" / "valid_region_two_link" / "versions.json").read_text())["config_source"]
    assert Path(source).resolve() == (INSTALLED / "valid_region_two_link.yaml").resolve()
