"""Ablation cost: whole-process time of the paper-protocol ablation, peak memory, and updates per second per method.

Part 1 runs the ablation of ``configs/ablation/ablation_ur5e.yaml`` (14 methods, 9
configurations x 10 trials x 4 noise levels = 360 self-ID streams, 13
checkpoints: 61,200 rollouts of 435 steps) as a whole process twice, through
``benchmarks/whole_process.py``: cold (empty persistent compilation cache)
then warm (the same cache), and prints wall time, the import / build / run
split and the peak RSS. ``--full-chunks K`` also runs the first ``K`` chunks
of ``configs/ablation/ablation_ur5e_full.yaml`` (20x the streams) for its peak RSS and
a projected wall time. Part 2 times ``baselines.run_stream`` for each method
alone, vmapped over 256 streams of 100 UR5e-sized samples (n = 6, m = 3), and
prints updates per second against the paper's estimator ("ours") measured in
the same process.

    python benchmarks/ablation.py [--config configs/ablation/ablation_ur5e.yaml] [--skip-study] [--full-chunks 1]
                                  [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOAL_COLD_S = 30.0
GOAL_RSS_MIB = 4096.0


def study_times(config) -> dict:
    """Cold and warm whole-process runs of ``config`` (separate processes sharing one compile cache)."""
    from whole_process import measure

    with tempfile.TemporaryDirectory() as cache:
        cold = measure(config, cache)
        warm = measure(config, cache)
    return {"cold": cold, "warm": warm}


def full_chunks(config, k: int) -> dict:
    """The first ``k`` chunks of a ``_full`` config (fewer configurations): peak RSS and projected wall time."""
    from whole_process import measure

    from selfid_jax.runner.registry import load as load_config

    cfg = load_config(config)
    per_config = len(cfg.pose_noise) * len(cfg.m_a) * cfg.n_trials  # streams per configuration
    n_full = cfg.n_configs * per_config
    keep = max(1, min(cfg.n_configs, k * cfg.chunk_size // per_config))
    with tempfile.TemporaryDirectory() as cache:
        rec = measure(config, cache, overrides=[f"n_configs={keep}"])
    streams = keep * per_config
    rec["streams"], rec["streams_full"] = streams, n_full
    rec["projected_full_run_s"] = rec["run_s"] * n_full / streams
    return rec


def update_rates(cfg, batch=256, T=100, n=6, m=3, reps=3):
    import jax
    import jax.numpy as jnp
    from timing import time_call

    from selfid_jax import baselines

    key = jax.random.key(0)
    kJ, kd, kn = jax.random.split(key, 3)
    J = jax.random.normal(kJ, (batch, m, n))
    d = jax.random.uniform(kd, (batch, T, n), minval=-0.03, maxval=0.03)
    V = jnp.einsum("bmn,btn->btm", J, d) + 1e-4 * jax.random.normal(kn, (batch, T, m))
    truth = jnp.zeros((n, m))
    keys = jax.random.split(key, batch)
    rows = []
    for spec in cfg.methods:
        est = baselines.make(spec.method, **spec.options)
        fn = jax.jit(jax.vmap(lambda k, a, b, est=est: baselines.run_stream(est, k, a, b, truth)[-1]))
        rows.append((spec.name, batch * T / time_call(fn, keys, d, V, reps=reps).run_s))  # median after a warm-up
    return rows


def run(config=ROOT / "configs/ablation/ablation_ur5e.yaml", *, skip_study=False, full=0, rates=True) -> dict:
    import selfid_jax  # noqa: F401
    from selfid_jax.runner.registry import load as load_config

    res: dict = {"config": Path(config).name}
    if not skip_study:
        res.update(study_times(config))
    if full:
        res["full"] = full_chunks(Path(config).with_name(Path(config).stem + "_full.yaml"), full)
    if rates:
        rows = update_rates(load_config(config))
        ref = dict(rows).get("ours", rows[0][1])
        res["updates_per_s"] = {name: {"rate": rate, "vs_ours": rate / ref} for name, rate in rows}
    return res


def report(res: dict) -> str:
    lines = []
    if "cold" in res:
        c, w = res["cold"], res["warm"]
        lines.append(f"paper-protocol ablation ({res['config']}, {c['rows']} table rows, {c['devices']}):")
        for name, r in (("cold", c), ("warm", w)):
            lines.append(f"  {name}: {r['wall_s']:6.1f} s whole process (import {r['import_s']:.1f}, "
                         f"build {r['build_s']:.1f}, run {r['run_s']:.1f}), peak RSS {r['peak_rss_mib']:.0f} MiB")
        lines.append(f"  goal: cold <= {GOAL_COLD_S:.0f} s ({'met' if c['wall_s'] <= GOAL_COLD_S else 'not met'})")
    if "full" in res:
        f = res["full"]
        lines.append(f"  full ({f['config']}): {f['streams']} of {f['streams_full']} streams, peak RSS "
                     f"{f['peak_rss_mib']:.0f} MiB (goal < {GOAL_RSS_MIB:.0f}), run {f['run_s']:.1f} s, "
                     f"projected full run {f['projected_full_run_s']:.0f} s")
    if "updates_per_s" in res:
        lines.append("estimator updates per second (estimate read after every update, vmap over 256 streams, "
                     "n=6, m=3):")
        for name, r in res["updates_per_s"].items():
            lines.append(f"  {name:28s} {r['rate']:12.0f} /s   {r['vs_ours']:6.2f}x ours")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs/ablation/ablation_ur5e.yaml"))
    ap.add_argument("--skip-study", action="store_true")
    ap.add_argument("--skip-rates", action="store_true")
    ap.add_argument("--full-chunks", type=int, default=0, help="also run this many chunks of the _full config")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    res = run(args.config, skip_study=args.skip_study, full=args.full_chunks, rates=not args.skip_rates)
    print(report(res))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2, default=str))


if __name__ == "__main__":
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
