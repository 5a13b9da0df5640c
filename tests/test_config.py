"""Config loading: validation errors name the file, the dotted key and what is allowed."""

from __future__ import annotations

import re
import textwrap

import numpy as np
import pydantic
import pytest
from selfid_jax.experiments.valid_region import ValidRegionConfig

from selfid_jax import runner as experiment
from selfid_jax.runner.config import BaseConfig, apply_overrides, dump_config, parse_override
from selfid_jax.runner.errors import ConfigError
from selfid_jax.runner.registry import load as load_config

VALID = textwrap.dedent(
    """\
    experiment: valid_region
    seed: 3
    chunk_size: 64
    systems: [two_link, ur5e]
    eps_limits: {start: 0.0, stop: 3.0, num: 13}
    n_configs: 10
    n_trials: 10
    controller: {max_step: 1e-2, tol: 1e-3, steps: 400}
    path: {size: 0.5}
    """
)


@pytest.fixture
def cfg_file(tmp_path):
    path = tmp_path / "vr.yaml"
    path.write_text(VALID)
    return path


def _error(path, overrides=(), text=None) -> str:
    if text is not None:
        path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path, overrides)
    return str(info.value)


def test_valid_config_loads_with_defaults_and_exponent_floats(cfg_file):
    cfg = load_config(cfg_file)
    assert isinstance(cfg, ValidRegionConfig)
    assert cfg.controller.tol == pytest.approx(1e-3) and isinstance(cfg.controller.tol, float)
    assert cfg.controller.gain == 1.0 and cfg.path.kind == "star" and cfg.completion_threshold == 0.95
    np.testing.assert_allclose(cfg.eps_limits.values(), np.linspace(0, 3, 13))
    with pytest.raises(pydantic.ValidationError):
        cfg.seed = 4  # frozen
    dumped = dump_config(cfg)
    assert dumped["controller"] == {"max_step": 0.01, "tol": 0.001, "steps": 400, "gain": 1.0,
                                    "max_rot_step": 0.05, "rot_tol": 0.01}
    assert ValidRegionConfig.model_validate(dumped) == cfg


def test_unknown_key_lists_allowed_keys(cfg_file):
    msg = _error(cfg_file, text=VALID + "foo: 1\n")
    assert str(cfg_file) in msg and "key 'foo'" in msg and "unknown key" in msg
    assert "n_trials" in msg and "controller" in msg
    msg = _error(cfg_file, text=VALID.replace("steps: 400", "steps: 400, kp: 2"))
    assert "key 'controller.kp'" in msg
    assert "allowed keys at 'controller': max_step, tol, steps, gain, max_rot_step, rot_tol" in msg


def test_wrong_type_names_key_value_and_type(cfg_file):
    msg = _error(cfg_file, text=VALID.replace("n_configs: 10", "n_configs: ten"))
    assert str(cfg_file) in msg and "key 'n_configs'" in msg
    assert "valid integer" in msg and "'ten'" in msg and "allowed: integer >= 1" in msg
    msg = _error(cfg_file, text=VALID.replace("[two_link, ur5e]", "[two_link, panda]"))
    assert "key 'systems[1]'" in msg and "'panda'" in msg
    assert "'two_link', 'ur5e', 'ur5e_6d', 'stewart_hand', 'model_o' or 'arm5'" in msg


def test_out_of_range_value(cfg_file):
    msg = _error(cfg_file, text=VALID.replace("max_step: 1e-2", "max_step: -1"))
    assert f"{cfg_file}: key 'controller.max_step': input should be greater than 0 (got -1)" in msg
    assert "allowed: number > 0" in msg
    msg = _error(cfg_file, text=VALID.replace("stop: 3.0", "stop: 0.0"))
    assert "key 'eps_limits.stop'" in msg and "greater than start" in msg
    msg = _error(cfg_file, ["completion_threshold=1.5"])
    assert "key 'completion_threshold'" in msg and "<= 1" in msg


def test_several_errors_reported_together(cfg_file):
    msg = _error(cfg_file, ["n_trials=0", "eps_limits.num=1"])
    assert "key 'n_trials'" in msg and "key 'eps_limits.num'" in msg


def test_overrides_apply_and_bad_overrides_error(cfg_file):
    cfg = load_config(cfg_file, ["controller.gain=0.5", "systems=[ur5e]", "name=quick"])
    assert cfg.controller.gain == 0.5 and cfg.systems == ["ur5e"] and cfg.name == "quick"
    msg = _error(cfg_file, ["controller.kp=2"])
    assert str(cfg_file) in msg and "key 'controller.kp'" in msg and "unknown key" in msg
    assert "max_step, tol, steps, gain" in msg and "--set controller.kp=2" in msg
    msg = _error(cfg_file, ["n_configs=many"])
    assert "key 'n_configs'" in msg and "--set n_configs=many" in msg
    msg = _error(cfg_file, ["controller"])
    assert "KEY=VALUE" in msg
    msg = _error(cfg_file, ["seed.x=1"])
    assert "'seed'" in msg and "not a mapping" in msg


def test_missing_file_and_unknown_experiment(tmp_path, cfg_file):
    missing = tmp_path / "nope.yaml"
    msg = _error(missing)
    assert str(missing) in msg and "not found" in msg
    msg = _error(cfg_file, ["experiment=no_such_experiment"])
    assert "key 'experiment'" in msg and "no_such_experiment" in msg and "valid_region" in msg
    msg = _error(cfg_file, text="seed: 1\n")
    assert "key 'experiment'" in msg and "missing" in msg
    msg = _error(cfg_file, text="experiment: [\n")
    assert "invalid YAML" in msg


def test_registered_model_and_parse_override(tmp_path):
    class Tiny(BaseConfig):
        experiment: str = "tiny_test"
        scale: float = pydantic.Field(gt=0)

    experiment.register(experiment.Experiment(
        name="tiny_test", config=Tiny, build=lambda cfg: [], compute=lambda static, p: p,
        summarize=lambda table, cfg: {},
    ))
    path = tmp_path / "tiny.yaml"
    path.write_text("experiment: tiny_test\nscale: 2\n")
    cfg = load_config(path, ["chunk_size=8"])
    assert isinstance(cfg, Tiny) and cfg.scale == 2.0 and cfg.chunk_size == 8
    assert parse_override("a.b=[1, 2.5e-3]") == (("a", "b"), [1, 0.0025])
    assert apply_overrides({"a": {"c": 1}}, ["a.b=x"]) == {"a": {"c": 1, "b": "x"}}


@pytest.mark.parametrize(
    "override, key",
    [
        ("controller.tol=.inf", "controller.tol"),
        ("controller.max_step=.nan", "controller.max_step"),
        ("eps_limits.stop=.inf", "eps_limits.stop"),
        ("path.size=.inf", "path.size"),
        ("seed=9223372036854775808", "seed"),
        ("seed=-1", "seed"),
        ("controller.tol=0.3", "controller.tol"),  # not below half the path size (0.5 m)
    ],
)
def test_non_finite_and_out_of_range_numbers_are_refused(cfg_file, override, key):
    msg = _error(cfg_file, [override])
    assert str(cfg_file) in msg and key in msg, msg


def test_ablation_refuses_infinite_eps_and_noise(tmp_path):
    import yaml

    base = {"experiment": "ablation", "methods": [{"name": "ours", "method": "ours"}], "iterations": [1],
            "n_configs": 1, "n_trials": 1, "pose_noise": [0.0], "rot_noise": [0.0], "m_a": [0.03], "eps": 0.5,
            "path": {"size": 0.05}}
    path = tmp_path / "abl.yaml"
    for change, key in (({"eps": float("inf")}, "eps"), ({"pose_noise": [float("inf")]}, "pose_noise[0]"),
                        ({"methods": [{"name": "r", "method": "rls", "options": {"lam": float("nan")}}]}, "methods")):
        path.write_text(yaml.safe_dump({**base, **change}))
        with pytest.raises(ConfigError, match=re.escape(f"key '{key}")):
            load_config(path)


def test_system_specs_name_the_problem_and_resolve_paths(cfg_file, tmp_path):
    msg = _error(cfg_file, ["systems=[{mjcf: robots/arm.xml, site: tip}]"])
    assert "key 'systems[0].mjcf'" in msg and str(tmp_path / "robots" / "arm.xml") in msg
    assert "relative to the config" in msg
    msg = _error(cfg_file, ["systems=[{site: tip}]"])
    assert "key 'systems[0]'" in msg and "'mjcf' or a 'pose_fn' key" in msg
    msg = _error(cfg_file, ["systems=[{pose_fn: 'not a target', n_act: 2}]"])
    assert "key 'systems[0].pose_fn'" in msg
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "arm.xml").write_text("<mujoco/>")
    cfg = load_config(cfg_file, ["systems=[two_link, {mjcf: robots/arm.xml, site: tip, m_a: [0.01, 0.02]}]"])
    assert cfg.systems[1].mjcf == str((tmp_path / "robots" / "arm.xml").resolve())
    msg = _error(cfg_file, ["systems=[two_link, {mjcf: robots/arm.xml, site: tip, name: two_link}]"])
    assert "repeated: two_link" in msg


def test_systems_entries_may_carry_their_own_protocol(cfg_file):
    cfg = load_config(cfg_file, ["systems=[two_link, {system: ur5e, path: {size: 0.05}, "
                                 "controller: {max_step: 0.0025, tol: 0.0005, steps: 435}}]"])
    from selfid_jax.experiments.valid_region import SystemRun, protocol

    assert isinstance(cfg.systems[1], SystemRun)
    spec, path, controller = protocol(cfg, cfg.systems[1])
    assert spec == "ur5e" and path.size == 0.05 and controller.tol == 0.0005
    assert protocol(cfg, cfg.systems[0])[1].size == 0.5  # the top level fills in
    msg = _error(cfg_file, ["systems=[{system: ur5e, path: {size: 0.001}}]"])  # tol 1e-3 does not fit 1 mm
    assert "controller.tol" in msg and "path.size" in msg


@pytest.mark.slow
def test_strict_yaml_refuses_duplicates_bad_encodings_and_bombs(tmp_path):
    """Duplicate keys at any depth (with both lines), non-UTF-8 files and alias bombs: one bounded ConfigError."""
    cases = {
        "dup_nested.yaml": ("experiment: valid_region\ncontroller: {tol: 0.002, tol: 0.09}\n",
                            r"duplicate key 'tol' \(line 2 and line 2\)"),
        "dup_top.yaml": ("experiment: valid_region\nseed: 1\nseed: 2\n", r"duplicate key 'seed' \(line 2 and line 3\)"),
        "latin1.yaml": ("experiment: valid_region\nname: caf\xe9\n".encode("latin-1"),
                        r"not UTF-8 text \(byte 0xe9 at offset 34\)"),
        "utf16.yaml": ("experiment: valid_region\n".encode("utf-16"), r"not UTF-8 text \(byte 0xff at offset 0\)"),
        "bomb.yaml": ("experiment: valid_region\na: &a [1,1,1,1,1,1,1,1,1,1]\n"
                      + "".join(f"{c}: &{c} [{', '.join([f'*{p}'] * 10)}]\n" for p, c in zip("abcdef", "bcdefg"))
                      + "seed: *g\n", r"more than 1,000,000 values"),
    }
    for name, (content, match) in cases.items():
        path = tmp_path / name
        (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
        with pytest.raises(ConfigError, match=match) as err:
            load_config(path)
        assert len(str(err.value)) < 2000, name
    merged = tmp_path / "merge.yaml"  # a merge key may be overridden: not a duplicate
    merged.write_text("experiment: valid_region\nbase: &b {tol: 0.002}\ncontroller: {<<: *b, tol: 0.003}\n")
    with pytest.raises(ConfigError) as err:
        load_config(merged)
    assert "duplicate" not in str(err.value)


def test_error_values_are_summarised(tmp_path):
    """A huge value in a typed key is summarised in the message, never dumped."""
    path = tmp_path / "big.yaml"
    path.write_text("experiment: valid_region\na: &a [1,1,1,1,1,1,1,1,1,1]\nb: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a,*a]\n"
                    "c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b,*b]\nseed: *c\n")
    with pytest.raises(ConfigError, match=r"key 'seed'.*\.\.\.") as err:
        load_config(path)
    assert len(str(err.value)) < 20 * 700


def test_system_names_stay_inside_the_run_directory(tmp_path):
    """A system name with a separator, '..', a leading dot or an absolute path is refused at validation."""
    for bad in ["../other", "/abs/path", "a/b", "..", ".hidden", "x" * 101, "tab\there"]:
        path = tmp_path / "names.yaml"
        spec = f"systems: [{{pose_fn: 'm:f', n_act: 2, name: {bad!r}}}]"
        path.write_text(VALID.replace("systems: [two_link, ur5e]", spec))
        with pytest.raises(ConfigError, match="name"):
            load_config(path)


def test_sweep_too_large_is_refused_before_allocating(tmp_path, monkeypatch):
    """A grid within every per-key bound but 10^11 rows in all: a SizeError naming the axes, in well under a second."""
    import time

    from selfid_jax.runner.grids import grid_table
    from selfid_jax.runner.limits import SizeError, check_memory

    t0 = time.perf_counter()
    with pytest.raises(SizeError, match=r"100,000,000,000 rows \(eps_limit 100,000 x config_id 1,000 x trial 1,000"):
        grid_table({"eps_limit": range(100_000), "config_id": range(1000), "trial": range(1000)})
    assert time.perf_counter() - t0 < 1.0
    monkeypatch.setenv("SELFID_JAX_MAX_ROWS", "10")
    with pytest.raises(SizeError, match="above the limit of 10"):
        grid_table({"a": range(4), "b": range(3)})
    assert len(grid_table({"a": range(2), "b": range(5)})) == 10
    monkeypatch.setenv("SELFID_JAX_MAX_MEMORY_GB", "1")
    with pytest.raises(SizeError, match=r"about 3\.0 GiB.*limit of 1\.0 GiB"):
        check_memory(2**20, 2**10)


def test_set_reaches_list_entries_by_index(cfg_file):
    """``--set systems.1.controller.steps=300`` (or ``systems[1]...``) edits one entry; a bad index names the length."""
    base = "systems=[two_link, {system: ur5e, controller: {max_step: 0.0025, tol: 0.0005, steps: 435}}]"
    for key in ("systems.1.controller.steps", "systems[1].controller.steps"):
        cfg = load_config(cfg_file, [base, f"{key}=300"])
        assert cfg.systems[1].controller.steps == 300 and cfg.systems[0] == "two_link"
    assert apply_overrides({"a": [1, 2, 3]}, ["a.2=9"]) == {"a": [1, 2, 9]}
    msg = _error(cfg_file, ["systems.5.controller.steps=1"])
    assert "systems has 2 entries (indices 0 .. 1), no entry 5" in msg
    msg = _error(cfg_file, ["systems.steps=1"])
    assert "index it by number" in msg and "'two_link'" not in msg  # the list is not printed
    msg = _error(cfg_file, [base, "systems.1.controller.steps=-4"])
    assert "key 'systems[1].controller.steps'" in msg and "(from --set systems.1.controller.steps=-4)" in msg


def test_oversample_is_a_config_key_and_the_advice_names_it(cfg_file):
    """The 'too few feasible starts' advice names ``oversample``, which configs now accept."""
    assert load_config(cfg_file).oversample == 4
    assert load_config(cfg_file, ["oversample=12"]).oversample == 12
    assert "oversample" in _error(cfg_file, ["oversample=0"])
    import numpy as np

    from selfid_jax import control, systems

    with pytest.raises(ValueError, match="raise oversample: the feasible_starts argument, or the config key"):
        control.feasible_indices(systems.two_link(), np.zeros(4, bool), np.ones(4), np.zeros(4, bool), 2)
