"""SIGINT and SIGTERM at every phase of ``selfid-jax sweep`` and ``plot``: exit 130 / 143 and one line, never a crash.

Each case starts the console script in a subprocess with ``$SELFID_JAX_TRACE_PHASES``
set (it marks its phases on stderr: start, setup, trace, compile, chunk,
figures, plot), waits for the marker of one phase and sends the signal then.
The compile cache is off, so the compile phase really compiles.
"""

from __future__ import annotations

import concurrent.futures
import os
import signal
import subprocess
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest

pytestmark = pytest.mark.slow  # subprocesses that import JAX and compile: about a minute in all

CONFIG = textwrap.dedent("""\
    experiment: valid_region
    systems: [two_link]
    eps_limits: {start: 0.5, stop: 1.5, num: 2}
    n_configs: 1
    n_trials: 4
    path: {kind: star, size: 0.2}
    controller: {max_step: 0.01, tol: 0.002, steps: 200}
    chunk_size: 2
    """)
EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143}



def _interrupt(console: list[str], args: list[str], phase: str, sig: int, cwd: Path) -> tuple[int, list[str]]:
    """Run ``selfid-jax ARGS``, send ``sig`` once ``phase`` is marked; the exit code and stderr's other lines."""
    env = dict(os.environ, SELFID_JAX_TRACE_PHASES="1", SELFID_JAX_CACHE_DIR="off")
    p = subprocess.Popen([*console, *args], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    seen = []
    assert p.stderr is not None
    deadline = time.monotonic() + 240
    for line in p.stderr:
        seen.append(line)
        if line.strip() == f"selfid-jax phase: {phase}":
            p.send_signal(sig)
            break
        assert time.monotonic() < deadline, f"phase {phase!r} not reached: {seen}"
    else:
        p.wait(timeout=60)
        raise AssertionError(f"the command ended before phase {phase!r}: rc {p.returncode}, {seen}")
    rest = p.stderr.read()
    p.wait(timeout=120)
    other = [s.rstrip("\n") for s in [*seen, *rest.splitlines()] if "phase:" not in s and s.strip()]
    return p.returncode, other


@pytest.fixture(scope="module")
def finished(tmp_path_factory, console) -> Path:
    """A directory with the config and one finished run of it (``run/``), the reference table."""
    d = tmp_path_factory.mktemp("signals")
    (d / "vr.yaml").write_text(CONFIG)
    out = subprocess.run([*console, "sweep", "vr.yaml", "--out", "run", "--no-progress"], cwd=d,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return d


CASES = [(phase, sig) for phase in ("start", "setup", "trace", "compile", "chunk", "figures")
         for sig in (signal.SIGINT, signal.SIGTERM)]


@pytest.fixture(scope="module")
def stopped_at_chunk(finished, console) -> tuple[int, list[str]]:
    """SIGINT once the first chunk is marked, into ``resumed/``: one case of the every-phase test, and the
    interrupted run the resume test finishes."""
    return _interrupt(console, ["sweep", "vr.yaml", "--out", "resumed", "--no-progress"], "chunk", signal.SIGINT,
                      finished)


def test_sweep_interrupted_at_every_phase_exits_cleanly(finished, console, stopped_at_chunk):
    """Every (phase, signal) ends with 128 + signal and exactly one line; no segfault, none swallowed."""

    def case(c):
        phase, sig = c
        if (phase, sig) == ("chunk", signal.SIGINT):  # run once, for the resume test too
            return c, stopped_at_chunk
        out = f"run_{phase}_{int(sig)}"
        return c, _interrupt(console, ["sweep", "vr.yaml", "--out", out, "--no-progress"], phase, sig, finished)

    with concurrent.futures.ThreadPoolExecutor(max_workers=3) as pool:
        results = list(pool.map(case, CASES))
    for (phase, sig), (rc, lines) in results:
        assert rc == EXIT[sig], (phase, signal.Signals(sig).name, rc, lines)
        assert len(lines) == 1 and lines[0].startswith("selfid-jax: "), (phase, signal.Signals(sig).name, lines)
        if phase == "chunk":
            assert "finished chunks are kept" in lines[0] and "--fresh" in lines[0]


def test_interrupted_sweep_resumes_to_the_clean_table(finished, console, stopped_at_chunk):
    """SIGINT after the first chunk, then the same command: the table equals an uninterrupted run's."""
    rc, lines = stopped_at_chunk
    assert rc == 130, lines
    assert not (finished / "resumed" / "results.parquet").exists()  # nothing that looks finished
    again = subprocess.run([*console, "sweep", "vr.yaml", "--out", "resumed", "--no-progress"], cwd=finished,
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-2000:]
    pd.testing.assert_frame_equal(pd.read_parquet(finished / "resumed" / "results.parquet"),
                                  pd.read_parquet(finished / "run" / "results.parquet"))


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_plot_interrupted_keeps_whole_figures(finished, console, sig):
    """``plot`` stopped while it draws: exit 128 + signal, one line, and every figure is a whole PNG/PDF."""
    rc, lines = _interrupt(console, ["plot", "run"], "plot", sig, finished)
    assert rc == EXIT[sig] and len(lines) == 1, (rc, lines)
    for f in (finished / "run" / "figures").iterdir():
        data = f.read_bytes()
        if f.suffix == ".png":
            assert data.startswith(b"\x89PNG") and data.rstrip().endswith(b"IEND\xaeB`\x82"), f
        elif f.suffix == ".pdf":
            assert data.startswith(b"%PDF") and b"%%EOF" in data[-64:], f
        else:
            pytest.fail(f"unexpected file {f.name} in figures/ (a temporary file left behind?)")
