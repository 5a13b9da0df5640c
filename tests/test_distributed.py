"""A sweep run as two ``jax.distributed`` CPU processes on localhost equals one process's; a process killed mid-run
leaves no finished-looking result and the rerun completes to the same table."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import textwrap
import time
from pathlib import Path

import jax
import pandas as pd
import pytest

from selfid_jax import cli

pytestmark = pytest.mark.slow  # four processes that import JAX and compile

CONFIG = textwrap.dedent("""\
    experiment: valid_region
    systems: [two_link]
    eps_limits: {start: 0.5, stop: 1.5, num: 2}
    n_configs: 1
    n_trials: 12
    path: {kind: star, size: 0.2}
    controller: {max_step: 0.01, tol: 0.002, steps: 200}
    chunk_size: 2
    """)



def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pair(console: list[str], cwd: Path, out: str, port: int) -> list[subprocess.Popen]:
    env = dict(os.environ, SELFID_JAX_CACHE_DIR="off", SELFID_JAX_TRACE_PHASES="1")
    return [subprocess.Popen([*console, "sweep", "vr.yaml", "--out", out, "--no-progress",
                              "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i),
                              "--heartbeat-timeout", "10"],
                             cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for i in (1, 0)]


def _single(cwd: Path, out: str) -> None:
    """One process's sweep: the console script's ``main`` in this process (x64 off, as in a fresh process), so the
    test pays for no third JAX import and the resume reuses the reference's compiled chunk program."""
    with jax.enable_x64(False):
        assert cli.main(["sweep", str(cwd / "vr.yaml"), "--out", str(cwd / out), "--no-progress"]) == 0


def test_two_processes_equal_one_and_a_killed_process_resumes(tmp_path, console):
    """Two processes' table equals one process's; process 1 killed once process 0 saved a chunk ends process 0
    with a failure and leaves chunks but no results or summary; one process then resumes to the same table."""
    (tmp_path / "vr.yaml").write_text(CONFIG)
    procs = _pair(console, tmp_path, "two", _port())
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [o[1][-1500:] for o in outs]

    # process 1 killed once process 0 (the writer) has saved a chunk
    p1, p0 = _pair(console, tmp_path, "killed", _port())
    assert p0.stderr is not None
    deadline = time.monotonic() + 240
    for line in p0.stderr:
        if line.strip() == "selfid-jax phase: chunk":
            p1.send_signal(signal.SIGKILL)
            break
        assert time.monotonic() < deadline
    p1.wait(timeout=60)
    _single(tmp_path, "one")  # the reference, while XLA ends process 0 (heartbeat 10 s: it waits on its dead peer)
    p0.communicate(timeout=120)
    assert p0.returncode != 0
    reference = pd.read_parquet(tmp_path / "one" / "results.parquet")
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "two" / "results.parquet"), reference)
    killed = tmp_path / "killed"
    assert not (killed / "results.parquet").exists() and not (killed / "summary.json").exists()
    assert any((killed / "parts" / "two_link" / "chunks").glob("chunk_*.parquet"))
    _single(tmp_path, "killed")
    pd.testing.assert_frame_equal(pd.read_parquet(killed / "results.parquet"), reference)
