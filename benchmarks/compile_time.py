"""Compile and run seconds per shipped config, cold (empty compile cache) and warm (the same cache again).

Each config runs as a whole process (:func:`whole_process.measure`) twice: with
an empty persistent compilation cache, then with the cache the first run left.
Per config it prints the rows, the cold and warm wall seconds (interpreter
start to exit), the cold run's seconds to its first result (the first chunk
file on disk, from the start of the script's ``main``), the cold run's seconds
per compile stage (JAX's duration events: tracing, lowering to MLIR, XLA's
backend compile; totals over every program) and its longest single XLA
compile, against the goals of issue 27: no program compiles longer than 30 s,
a config's first result within 60 s, a second run of a config compiling
nothing (every program of the warm run read back from the cache).

    python benchmarks/compile_time.py [--configs NAME ...] [--json out.json]

Default: every shipped config except the ``*_full`` ones and the robot
commands' configs (``configs/robot/``), which are not sweeps. About
1-5 minutes per config on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from emit import emit
from whole_process import measure

ROOT = Path(__file__).resolve().parents[1]
LONGEST_GOAL_S = 30.0
FIRST_RESULT_GOAL_S = 60.0


def shipped(names: list[str] | None) -> list[Path]:
    """The configs to time: ``names`` (stems, found in any subfolder of ``configs/``) or every sweep config of
    ``configs/`` but the ``_full`` ones and ``configs/robot/`` (the online and robot-sim commands' configs)."""
    folder = ROOT / "configs"
    every = {p.stem: p for p in sorted(folder.rglob("*.yaml"))}
    if names:
        stems = [n.removesuffix(".yaml") for n in names]
        missing = [f"{n}.yaml" for n in stems if n not in every]
        if missing:
            raise SystemExit(f"no such config under {folder}: {', '.join(missing)}")
        return [every[n] for n in stems]
    return [p for p in every.values() if not p.stem.endswith("_full") and p.parent.name != "robot"]


def row(config: Path, timeout: int) -> dict:
    with tempfile.TemporaryDirectory() as cache:
        cold = measure(config, cache, timeout=timeout)
        warm = measure(config, cache, timeout=timeout)
    c = cold["compile"]
    return dict(config=config.stem, rows=cold["rows"], cold_wall_s=cold["wall_s"], warm_wall_s=warm["wall_s"],
                trace_s=c["trace"]["total_s"], lower_s=c["lower"]["total_s"], xla_s=c["xla"]["total_s"],
                xla_max_s=c["xla"]["max_s"], programs=c["xla"]["count"] - cold["cache_hits"],
                warm_programs=warm["compile"]["xla"]["count"] - warm["cache_hits"],
                run_s=cold["run_s"], first_result_s=cold["first_chunk_s"])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", nargs="*", default=None, help="config stems (default: every shipped sweep config)")
    ap.add_argument("--timeout", type=int, default=1800, help="seconds per process")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rows = []
    for config in shipped(args.configs):
        try:
            rows.append(row(config, args.timeout))
        except Exception as exc:  # noqa: BLE001  (one config's failure is reported, the rest still run)
            rows.append(dict(config=config.stem, error=str(exc).splitlines()[0][:200]))
        print(f"  {config.stem} done", file=sys.stderr, flush=True)
    head = (f"{'config':<34} {'rows':>7} {'cold s':>7} {'first s':>7} {'warm s':>7} {'trace s':>8} {'lower s':>8} "
            f"{'xla s':>7} {'longest':>8} {'progs':>5} {'warm progs':>10}  goals")
    lines = [head]
    for r in rows:
        if "error" in r:
            lines.append(f"{r['config']:<34} failed: {r['error']}")
            continue
        goals = []
        if r["xla_max_s"] > LONGEST_GOAL_S:
            goals.append(f"longest > {LONGEST_GOAL_S:g} s")
        if r["first_result_s"] > FIRST_RESULT_GOAL_S:
            goals.append(f"first result > {FIRST_RESULT_GOAL_S:g} s")
        if r["warm_programs"]:
            goals.append("warm run compiles")
        lines.append(f"{r['config']:<34} {r['rows']:>7} {r['cold_wall_s']:>7.1f} {r['first_result_s']:>7.1f} "
                     f"{r['warm_wall_s']:>7.1f} "
                     f"{r['trace_s']:>8.1f} {r['lower_s']:>8.1f} {r['xla_s']:>7.1f} {r['xla_max_s']:>8.1f} "
                     f"{r['programs']:>5} {r['warm_programs']:>10}  {'; '.join(goals) or 'met'}")
    lines.append(f"goals: longest XLA compile <= {LONGEST_GOAL_S:g} s; cold first result <= {FIRST_RESULT_GOAL_S:g} s; "
                 "a warm run compiles no program")
    emit(dict(rows=rows), "\n".join(lines), args.json)


if __name__ == "__main__":
    main()
