"""The test suite's two tiers as the README runs them: pytest seconds, wall seconds and the test count.

Each run is a fresh ``python -m pytest -q -n 2 [-m "not slow"] tests`` from the
project's root (no compilation cache, as in CI). The suite compiles
at LLVM optimisation level 0 (``tests/conftest.py``); ``--shipped`` also times
the fast tier at level 3 (``XLA_FLAGS=--xla_backend_optimization_level=3``) in
the same run, the baseline of the ratio. Goals: the fast tier under a minute
(issue 57; issue 27 asked 45 s) and the whole suite <= 300 s on the 2-core machine.

    python benchmarks/suite_time.py [--tiers fast whole] [--shipped] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from emit import emit
from timing import run_process

ROOT = Path(__file__).resolve().parent.parent
GOALS_S = {"fast": 60.0, "whole": 300.0}


def one_tier(tier: str, level: int | None, timeout: int) -> dict:
    """One pytest run of ``tier`` ("fast" or "whole"); ``level`` None: the suite's own level, else that LLVM level."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "no:cacheprovider", "tests"]
    if tier == "fast":
        cmd[4:4] = ["-m", "not slow"]
    env = dict(os.environ)
    env.pop("SELFID_JAX_TEST_CACHE_DIR", None)  # each run without a compilation cache, as in CI
    if level is not None:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_backend_optimization_level={level}".strip()
    load = os.getloadavg()[0]
    proc, wall = run_process(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    tail = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    found = re.search(r"(\d+) passed.* in ([\d.]+)s", tail)
    if proc.returncode != 0 or not found:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}{proc.stderr[-2000:]}")
    return {"tier": tier, "level": level, "passed": int(found[1]), "pytest_s": float(found[2]), "wall_s": wall,
            "load_before": load}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiers", nargs="+", default=["fast", "whole"], choices=["fast", "whole"])
    ap.add_argument("--shipped", action="store_true", help="also the fast tier at LLVM level 3 (the baseline)")
    ap.add_argument("--timeout", type=int, default=1800, help="seconds per run")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    plan = [(t, None) for t in args.tiers] + ([("fast", 3)] if args.shipped else [])
    rows, lines = [], []
    for tier, level in plan:
        r = one_tier(tier, level, args.timeout)
        rows.append(r)
        what = f"{tier} tier" + (f", LLVM level {level}" if level is not None else "")
        lines.append(f"{what:28s} {r['passed']:4d} passed, pytest {r['pytest_s']:6.1f} s, wall {r['wall_s']:6.1f} s "
                     f"(goal <= {GOALS_S[tier]:g} s), load {r['load_before']:.1f} before")
    record = {"rows": rows, "goals_s": GOALS_S, "cpus": os.cpu_count()}
    base = [r for r in rows if r["tier"] == "fast" and r["level"] == 3]
    ours = [r for r in rows if r["tier"] == "fast" and r["level"] is None]
    if base and ours:
        record["fast_vs_shipped_level"] = ours[0]["pytest_s"] / base[0]["pytest_s"]
        lines.append(f"fast tier at the suite's level against level 3 in this run: "
                     f"{record['fast_vs_shipped_level']:.2f}x")
    emit(record, "\n".join(lines), args.json)


if __name__ == "__main__":
    main()
