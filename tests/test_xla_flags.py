"""The CPU XLA flags set at import: merged with the user's, opt-out honoured, active in a fresh process."""

import os
import subprocess
import sys

import pytest

from selfid_jax._xla import DEFAULT_XLA_FLAGS, merged_xla_flags


def test_xla_flags_merge_keeps_user_settings():
    flags = merged_xla_flags("--xla_cpu_use_fusion_emitters=true --foo=1")
    assert "--xla_cpu_use_fusion_emitters=true" in flags and "--xla_cpu_use_fusion_emitters=false" not in flags
    assert "--xla_cpu_enable_concurrency_optimized_scheduler=false" in flags and "--foo=1" in flags
    assert merged_xla_flags(None).split() == [
        "--xla_cpu_use_fusion_emitters=false",
        "--xla_cpu_enable_concurrency_optimized_scheduler=false",
    ]
    assert merged_xla_flags("--xla_cpu_use_fusion_emitters").count("fusion_emitters") == 1  # bare flag counts


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
    for flag, value in DEFAULT_XLA_FLAGS.items():
        assert f"{flag}={value}" in flags
    assert _flags_after_import({"XLA_FLAGS": "--foo=1", "SELFID_JAX_NO_XLA_FLAGS": "1"}) == "--foo=1"
