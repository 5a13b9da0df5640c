"""``selfid-jax demo`` as a whole process with an empty compilation cache: wall seconds and peak memory.

The README's first command runs this job; issue 27's goal is 20 s wall on an
idle 2-core machine with an empty cache. Each run is a fresh interpreter
(``python -m selfid_jax.cli demo`` with ``SELFID_JAX_CACHE_DIR=off``, its run
directory in a temporary folder), timed from its start to its exit; the
report gives the minimum, median and maximum over ``--runs``, the median CPU
seconds (user + system, the child's own accounting) and the largest peak RSS,
and the load average before and after.

    python benchmarks/demo_cold.py [--runs 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from emit import emit
from timing import run_process

GOAL_S = 20.0


def one_run(timeout: int) -> dict:
    """One cold ``selfid-jax demo``: ``{wall_s}`` (the caller adds the child's CPU seconds)."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "selfid_jax.cli", "demo", "--out", str(Path(tmp) / "demo")]
        env = {**os.environ, "SELFID_JAX_CACHE_DIR": "off"}
        proc, wall = run_process(cmd, cwd=tmp, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                 timeout=timeout)  # killed on timeout
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr.decode()[-3000:]}")
    return {"wall_s": wall}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--timeout", type=int, default=600, help="seconds per run")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    load_before = os.getloadavg()
    runs = []
    for _ in range(args.runs):
        before = os.times()
        r = one_run(args.timeout)
        after = os.times()
        r["cpu_s"] = (after.children_user - before.children_user) + (after.children_system - before.children_system)
        runs.append(r)
    import resource

    peak_mib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024  # the largest child's, Linux KiB
    walls = [r["wall_s"] for r in runs]
    record = {
        "runs": runs, "wall_min_s": min(walls), "wall_median_s": statistics.median(walls), "wall_max_s": max(walls),
        "cpu_median_s": statistics.median(r["cpu_s"] for r in runs), "peak_rss_mib": peak_mib,
        "load_before": load_before, "load_after": os.getloadavg(), "goal_s": GOAL_S,
    }
    text = (f"selfid-jax demo, empty cache, {args.runs} runs: wall min {record['wall_min_s']:.1f} / median "
            f"{record['wall_median_s']:.1f} / max {record['wall_max_s']:.1f} s (goal <= {GOAL_S:g} s), CPU median "
            f"{record['cpu_median_s']:.1f} s, peak RSS {peak_mib:.0f} MiB; load {load_before[0]:.1f} before, "
            f"{record['load_after'][0]:.1f} after")
    emit(record, text, args.json)


if __name__ == "__main__":
    main()
