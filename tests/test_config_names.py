"""Shipped configs are package data, grouped by experiment and found by name from any directory:
``selfid-jax sweep valid_region_two_link`` runs ``configs/valid_region/valid_region_two_link.yaml``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from selfid_jax import cli
from selfid_jax.runner.command_line import find_config
from selfid_jax.runner.errors import ConfigError

INSTALLED = dict(cli._config_dirs())["installed"]  # the data package selfid_jax.configs
REPO = Path(__file__).resolve().parents[1] / "configs"
APART = {"robot": "the online and robot-sim commands' configs, not sweeps",
         "studies/gap": "the gap study of scripts/gap_study.py, sweeps of three experiments"}


def test_configs_are_installed_and_names_resolve_local_first(tmp_path, monkeypatch):
    def shipped(folder):
        return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*.yaml"))

    assert shipped(INSTALLED) == shipped(REPO) and len(shipped(REPO)) > 40
    monkeypatch.chdir(tmp_path)
    dirs = cli._config_dirs()
    # a bare name resolves inside a subfolder, with or without .yaml
    assert find_config(Path("valid_region_ur5e"), dirs) == INSTALLED / "valid_region" / "valid_region_ur5e.yaml"
    assert find_config(Path("valid_region_ur5e.yaml"), dirs) == INSTALLED / "valid_region" / "valid_region_ur5e.yaml"
    assert find_config(Path("gap_peg_in_hole"), dirs) == INSTALLED / "studies" / "gap" / "gap_peg_in_hole.yaml"
    (tmp_path / "configs" / "mine").mkdir(parents=True)
    (tmp_path / "configs" / "mine" / "valid_region_ur5e.yaml").write_text("experiment: valid_region\n")
    local = Path("configs/mine/valid_region_ur5e.yaml")
    assert find_config(Path("valid_region_ur5e"), dirs) == local  # ./configs (any subfolder) before the installed
    assert find_config(Path("configs/mine/valid_region_ur5e.yaml"), dirs) == local  # a path is a path
    with pytest.raises(ConfigError, match=r"no nonesuch.yaml in configs or .* or their subfolders .*selfid-jax list"):
        find_config(Path("nonesuch"), dirs)
    assert find_config(Path("sub/nonesuch"), dirs) == Path("sub/nonesuch")  # a path is reported as that path


@pytest.mark.slow
def test_list_names_where_configs_live_and_a_named_config_runs_from_an_empty_directory(tmp_path, monkeypatch,
                                                                                        capsys):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    assert f"configs (installed: {INSTALLED}" in out and "valid_region_ur5e " in out
    listed = out[out.index("configs (installed"):]
    for group in ("ablation/", "robot/", "studies/gap/", "valid_region/"):  # grouped by folder, each group once
        assert listed.count(f"\n  {group}\n") == 1, group
    at = listed.index
    assert at("\n  valid_region/\n") < at("\n    valid_region_ur5e ") < at("\n  workspace/")
    assert "configs (./configs: configs): none" in out
    args = ["sweep", "valid_region_two_link", "--no-progress", "--set", "n_configs=2", "--set", "n_trials=1",
            "--set", "eps_limits.num=2"]
    assert cli.main(args) == 0
    assert (tmp_path / "runs" / "valid_region_two_link" / "results.parquet").is_file()
    source = json.loads((tmp_path / "runs" / "valid_region_two_link" / "versions.json").read_text())["config_source"]
    assert Path(source).resolve() == (INSTALLED / "valid_region" / "valid_region_two_link.yaml").resolve()


def test_a_name_twice_under_one_folder_is_refused_naming_both(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for sub in ("a", "b/c"):
        (tmp_path / "configs" / sub).mkdir(parents=True)
        (tmp_path / "configs" / sub / "twice.yaml").write_text("experiment: valid_region\n")
    dirs = cli._config_dirs()
    for name in ("twice", "twice.yaml"):
        with pytest.raises(ConfigError) as err:
            find_config(Path(name), dirs)
        assert "configs/a/twice.yaml" in str(err.value) and "configs/b/c/twice.yaml" in str(err.value)
    # the same name in ./configs and in the installed folder is no conflict: ./configs wins
    (tmp_path / "configs" / "b" / "c" / "twice.yaml").rename(tmp_path / "configs" / "a" / "valid_region_ur5e.yaml")
    assert find_config(Path("twice"), dirs) == Path("configs/a/twice.yaml")
    assert find_config(Path("valid_region_ur5e"), dirs) == Path("configs/a/valid_region_ur5e.yaml")


@pytest.mark.slow
def test_every_config_is_in_its_experiments_folder_and_names_are_unique():
    """configs/<experiment>/NAME.yaml, NAME unique over the tree (so that every bare name resolves); the robot
    commands' configs (no experiment key) in configs/robot/, the gap study in configs/studies/gap/."""
    from selfid_jax.runner import registry

    paths = sorted(REPO.rglob("*.yaml"))
    stems = [p.stem for p in paths]
    assert len(stems) == len(set(stems)), sorted({s for s in stems if stems.count(s) > 1})
    assert not list(REPO.glob("*.yaml")), "a config at the top of configs/: move it to its experiment's folder"
    known = set(registry.available())
    for path in paths:
        folder = path.parent.relative_to(REPO).as_posix()
        experiment = yaml.safe_load(path.read_text(encoding="utf-8")).get("experiment")
        if folder == "robot":
            assert experiment is None, f"{path}: a sweep config in configs/robot/"
        elif folder in APART:
            assert experiment in known, path
        else:
            assert folder == experiment, f"{path}: experiment {experiment!r}, move it to configs/{experiment}/"


def test_robot_commands_find_shipped_configs_by_name(tmp_path, monkeypatch, capsys):
    """``selfid-jax online NAME`` and ``robot-sim NAME`` look a bare name up as ``sweep`` does (here a name that no
    folder holds: the error says where it looked; a shipped name gets past the lookup to the config's own checks)."""
    from selfid_jax.cli import main

    monkeypatch.chdir(tmp_path)
    for command in ("online", "robot-sim"):
        assert main([command, "no_such_robot_config"]) == 2
        err = capsys.readouterr().err
        assert "no_such_robot_config: config file not found" in err and "configs" in err, err
    assert main(["online", "online_trossen_sim", "--out", str(tmp_path / "run"), "--set", "selfid.m_a=-1"]) == 2
    err = capsys.readouterr().err
    assert "not found" not in err and "m_a" in err, err
