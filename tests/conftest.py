"""Test configuration: float64 (references are compared to 1e-6 and tighter) and
strict rank promotion, so accidental broadcasting fails loudly."""

import os
import shutil
import sys
from pathlib import Path

import jax
import pytest

import selfid_jax  # noqa: F401  (sets the CPU XLA flags before JAX initialises)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# One persistent XLA compilation cache for the whole test run, empty at its start: a program that several tests,
# pytest-xdist workers or the console-script subprocesses compile is compiled once (the tests build the same
# systems and rollouts many times, each under a new jit). The controller makes the folder; workers and
# subprocesses inherit it through the environment. Tests that need a cold process set SELFID_JAX_CACHE_DIR=off.
_CACHE_ENV = "SELFID_JAX_TEST_CACHE_DIR"


_CREATED: list[str] = []


def pytest_configure(config):
    if not hasattr(config, "workerinput") and _CACHE_ENV not in os.environ:
        import tempfile

        _CREATED.append(tempfile.mkdtemp(prefix="selfid_jax_test_xla_"))
        os.environ[_CACHE_ENV] = _CREATED[0]
    _use_test_cache()


def pytest_unconfigure(config):
    for where in _CREATED:  # only the folder this run made; one given in the environment is the user's
        shutil.rmtree(where, ignore_errors=True)


def _use_test_cache():
    where = os.environ.get(_CACHE_ENV)
    if not where:
        return
    os.environ.setdefault("SELFID_JAX_CACHE_DIR", where)  # the console script's cache (runner.cli)
    jax.config.update("jax_compilation_cache_dir", where)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


@pytest.fixture(scope="session")
def console() -> list[str]:
    """The ``selfid-jax`` console script as a command list (its installed script, else ``python -c`` calling it)."""
    exe = shutil.which("selfid-jax", path=os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]]))
    return [exe] if exe else [sys.executable, "-c", "import sys; from selfid_jax.cli import main; sys.exit(main())"]
