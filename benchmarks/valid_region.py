"""Whole-process time and peak memory of the valid-region maps: the paper-protocol UR5e map and its ``_full`` variant.

Each config runs as a whole process through ``benchmarks/whole_process.py``,
twice: cold (empty persistent compilation cache) then warm (the same cache);
prints the wall time (interpreter start to exit), its import / build / run
split, rollouts per second and the peak RSS. Configs named ``*_full`` run only
their first ``--full-chunks`` chunks (fewer configurations; default 2) and the
full map's time is projected from the rows per second of the run phase.

    python benchmarks/valid_region.py [--configs configs/valid_region/valid_region_ur5e.yaml
                                                 configs/valid_region/valid_region_ur5e_full.yaml]
                                      [--full-chunks 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from whole_process import measure

ROOT = Path(__file__).resolve().parents[1]
GOAL_COLD_S = 8.0
GOAL_RSS_MIB = 4096.0


def _overrides(path: Path, full_chunks: int):
    """``(overrides, full_rows)``: for a ``_full`` config, ``n_configs`` covering ``full_chunks`` chunks."""
    import selfid_jax  # noqa: F401
    from selfid_jax.runner.registry import load as load_config

    cfg = load_config(path)
    per_config = len(cfg.eps_limits.values()) * cfg.n_trials * len(cfg.systems)
    n_full = cfg.n_configs * per_config
    if not path.stem.endswith("_full"):
        return [], n_full
    keep = max(1, min(cfg.n_configs, full_chunks * cfg.chunk_size // per_config))
    return [f"n_configs={keep}"], n_full


def run(configs=(ROOT / "configs/valid_region/valid_region_ur5e.yaml",
                 ROOT / "configs/valid_region/valid_region_ur5e_full.yaml"),
        full_chunks: int = 2, warm: bool = True, warm_full: bool = True) -> dict:
    """Cold (and ``warm``) whole-process runs of each config; ``_full`` configs cut to ``full_chunks`` chunks (a
    number above their chunk count runs them whole) and run warm only if ``warm_full``."""
    res = {}
    for path in map(Path, configs):
        overrides, n_full = _overrides(path, full_chunks)
        with tempfile.TemporaryDirectory() as cache:
            entry = {"cold": measure(path, cache, overrides)}
            if warm and (warm_full or not path.stem.endswith("_full")):
                entry["warm"] = measure(path, cache, overrides)
        entry["rows_full"] = n_full
        if overrides:
            entry["projected_full_run_s"] = entry["cold"]["run_s"] * n_full / entry["cold"]["rows"]
        res[path.name] = entry
    return res


def report(res: dict) -> str:
    lines = [f"{'config':34s} {'rows':>8s} {'cold':>7s} {'warm':>7s} {'import':>7s} {'build':>6s} {'run':>6s} "
             f"{'rows/s':>8s} {'peak RSS':>9s}"]
    for name, e in res.items():
        c = e["cold"]
        warm = f"{e['warm']['wall_s']:6.1f}s" if "warm" in e else f"{'-':>7s}"
        label = name + (f" ({c['rows']} of {e['rows_full']})" if "projected_full_run_s" in e else "")
        lines.append(f"{label:34s} {c['rows']:8d} {c['wall_s']:6.1f}s {warm} {c['import_s']:6.1f}s "
                     f"{c['build_s']:5.1f}s {c['run_s']:5.1f}s {c['rows'] / c['run_s']:8.0f} "
                     f"{c['peak_rss_mib']:7.0f}MiB")
        if "projected_full_run_s" in e:
            lines.append(f"{'':34s} projected full map: {e['projected_full_run_s']:.0f} s of run")
    first = next(iter(res.values()))["cold"]
    lines.append(f"goal: paper-protocol UR5e map <= {GOAL_COLD_S:.0f} s whole process, cold compile cache "
                 f"({'met' if first['wall_s'] <= GOAL_COLD_S else 'not met'}); peak RSS < {GOAL_RSS_MIB:.0f} MiB")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=[str(ROOT / "configs/valid_region/valid_region_ur5e.yaml"),
                                                     str(ROOT / "configs/valid_region/valid_region_ur5e_full.yaml")])
    ap.add_argument("--full-chunks", type=int, default=2,
                    help="run only this many chunks of configs named *_full (projects the total); more than the "
                         "config has: the whole config")
    ap.add_argument("--no-warm-full", action="store_true", help="run *_full configs cold only")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    res = run(args.configs, args.full_chunks, warm_full=not args.no_warm_full)
    print(report(res))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2, default=str))


if __name__ == "__main__":
    main()
