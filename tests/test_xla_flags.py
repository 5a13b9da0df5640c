"""The CPU XLA flags set at import: merged with the user's, opt-out honoured, gated by jaxlib release, active in a fresh
process; the console script's garbage-collector thresholds."""

import gc
import os
import subprocess
import sys

import pytest

from selfid_jax._gc import TRACING_THRESHOLD, collect_less_often
from selfid_jax._xla import (
    DEFAULT_XLA_FLAGS,
    MIN_JAXLIB,
    QUICK_COMPILE_FLAGS,
    defaults_for,
    jaxlib_version,
    merged_xla_flags,
    quick_compile_flags,
    release_tuple,
    request_quick_compile,
)

ALL = {flag: value for flag, value in DEFAULT_XLA_FLAGS.items()}


def test_xla_flags_merge_keeps_user_settings():
    flags = merged_xla_flags("--xla_cpu_use_fusion_emitters=true --foo=1", ALL)
    assert "--xla_cpu_use_fusion_emitters=true" in flags and "--xla_cpu_use_fusion_emitters=false" not in flags
    assert "--xla_cpu_enable_concurrency_optimized_scheduler=false" in flags and "--foo=1" in flags
    assert merged_xla_flags(None, ALL).split() == [
        "--xla_cpu_use_fusion_emitters=false",
        "--xla_cpu_enable_concurrency_optimized_scheduler=false",
        "--xla_cpu_experimental_ynn_fusion_type=",
    ]
    assert merged_xla_flags("--xla_cpu_use_fusion_emitters", ALL).count("fusion_emitters") == 1  # bare flag counts
    assert merged_xla_flags("--xla_cpu_experimental_ynn_fusion_type=dot", ALL).count("ynn") == 1


def test_flags_only_for_jaxlib_releases_that_know_them():
    # an unknown flag aborts XLA at start-up: a release before a flag's minimum must not get it
    assert set(defaults_for((0, 4, 30))) == {"--xla_cpu_enable_concurrency_optimized_scheduler"}
    assert set(defaults_for((0, 5, 3))) == {"--xla_cpu_enable_concurrency_optimized_scheduler"}
    assert set(defaults_for((0, 8, 0))) == {"--xla_cpu_enable_concurrency_optimized_scheduler",
                                           "--xla_cpu_use_fusion_emitters"}
    assert set(defaults_for((0, 8, 1))) == set(DEFAULT_XLA_FLAGS) == set(defaults_for((0, 10, 2)))
    assert set(defaults_for(None)) == set(DEFAULT_XLA_FLAGS) - set(MIN_JAXLIB)
    assert release_tuple("0.9.0.1") == (0, 9, 0, 1) and release_tuple("0.7.0rc1") == (0, 7, 0)
    assert release_tuple("0.10.2+cuda12") == (0, 10, 2) and release_tuple("dev") is None
    assert jaxlib_version() is not None and jaxlib_version() >= (0, 4, 30)
    assert merged_xla_flags(None).split() == merged_xla_flags(None, defaults_for(jaxlib_version())).split()
    # the quick-compile flags are gated the same way: the whole-module compile from jaxlib 0.4.32 (the released wheels)
    level = "--xla_backend_optimization_level"
    assert set(defaults_for((0, 4, 31), QUICK_COMPILE_FLAGS)) == {level} == set(defaults_for(None, QUICK_COMPILE_FLAGS))
    assert defaults_for((0, 4, 32), QUICK_COMPILE_FLAGS) == QUICK_COMPILE_FLAGS == quick_compile_flags()


def _flags_after_import(env_extra: dict[str, str]) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "SELFID_JAX_NO_XLA_FLAGS")}
    env.update(env_extra)
    code = "import os, selfid_jax; print(os.environ.get('XLA_FLAGS', ''))"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          check=True).stdout.strip()


@pytest.mark.slow
def test_import_sets_flags_and_opt_out_leaves_them():
    flags = _flags_after_import({"XLA_FLAGS": "--foo=1"})
    assert flags.split()[0] == "--foo=1"
    for flag, value in defaults_for(jaxlib_version()).items():
        assert f"{flag}={value}" in flags
    assert _flags_after_import({"XLA_FLAGS": "--foo=1", "SELFID_JAX_NO_XLA_FLAGS": "1"}) == "--foo=1"


def test_quick_compile_adds_level_0_and_the_whole_module_compile_unless_set(monkeypatch):
    monkeypatch.delenv("SELFID_JAX_NO_XLA_FLAGS", raising=False)
    split = "--xla_cpu_parallel_codegen_split_count"
    for given, want in [("--foo=1", f"--foo=1 --xla_backend_optimization_level=0 {split}=1"),
                        ("--xla_backend_optimization_level=2", f"--xla_backend_optimization_level=2 {split}=1"),
                        (f"{split}=8", f"{split}=8 --xla_backend_optimization_level=0")]:
        monkeypatch.setenv("XLA_FLAGS", given)
        request_quick_compile()
        assert os.environ["XLA_FLAGS"] == want
    monkeypatch.setenv("SELFID_JAX_NO_XLA_FLAGS", "1")
    monkeypatch.setenv("XLA_FLAGS", "--foo=1")
    request_quick_compile()
    assert os.environ["XLA_FLAGS"] == "--foo=1"


def test_collect_less_often_raises_each_threshold_to_the_tracing_one_and_never_lowers_one():
    before = gc.get_threshold()
    try:
        gc.set_threshold(700, 10, 10)  # Python's default
        collect_less_often()
        assert gc.get_threshold() == TRACING_THRESHOLD == (10_000, 10, 10)
        gc.set_threshold(50_000, 5, 100)
        collect_less_often()
        assert gc.get_threshold() == (50_000, 10, 100)
    finally:
        gc.set_threshold(*before)


@pytest.mark.slow
def test_console_script_asks_for_quick_compiles_for_the_demo_only_and_collects_less_often():
    code = ("import gc, os, sys\nfrom selfid_jax.cli import main\nsys.argv = ['selfid-jax', *sys.argv[1:], '--help']\n"
            "print('GC0', gc.get_threshold())\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\nprint('GC', gc.get_threshold())\n"
            "print('FLAGS', os.environ.get('XLA_FLAGS', ''))")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "SELFID_JAX_NO_XLA_FLAGS")}
    for command, quick in (("demo", True), ("sweep", False)):
        out = subprocess.run([sys.executable, "-c", code, command], env=env, capture_output=True, text=True,
                             check=True).stdout
        flags = out.split("FLAGS", 1)[1].split()
        assert ("--xla_backend_optimization_level=0" in flags) == quick, out
        assert ("--xla_cpu_parallel_codegen_split_count=1" in flags) == quick, out
        assert "GC0 (700, 10, 10)" in out and f"GC {TRACING_THRESHOLD}" in out, out
