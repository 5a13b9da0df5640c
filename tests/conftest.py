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


@pytest.fixture(scope="session")
def console() -> list[str]:
    """The ``selfid-jax`` console script as a command list (its installed script, else ``python -c`` calling it)."""
    exe = shutil.which("selfid-jax", path=os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]]))
    return [exe] if exe else [sys.executable, "-c", "import sys; from selfid_jax.cli import main; sys.exit(main())"]
