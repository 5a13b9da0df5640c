"""Every Python block of README.md runs as written, and the CLI commands it shows exist."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_readme_has_python_blocks():
    assert len(BLOCKS) >= 2


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_python_block_runs(index, tmp_path):
    """Run in a fresh interpreter, as a reader pasting it would (default float32, no test config)."""
    script = tmp_path / f"block_{index}.py"
    script.write_text(BLOCKS[index])
    res = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]


def test_readme_cli_subcommands_exist():
    from selfid_jax.runner.cli import _parser

    commands = set(re.findall(r"^selfid-jax (\w+)", README.read_text(), re.M))
    known = set(_parser()._subparsers._group_actions[0].choices)
    assert commands and commands <= known, commands - known
