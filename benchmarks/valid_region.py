"""Wall time of the valid-region maps: the paper-protocol UR5e map and its ``_full`` variant.

For each config, runs the ``valid_region`` experiment (``selfid_jax.experiment.run``) twice into fresh
directories with JAX's persistent compilation cache on: the first run compiles
(cold), the second loads the compiled function from the cache (warm). Prints
the cold wall time (including compile), the warm one, their difference (the
compile time) and rollouts per second. ``--full-chunks K`` runs only the first
K chunks of the ``_full`` map and reports its projected total.

    python benchmarks/valid_region.py [--configs configs/valid_region_ur5e.yaml configs/valid_region_ur5e_full.yaml]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import selfid_jax  # noqa: F401
import jax

from selfid_jax import experiment
from selfid_jax.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def timed_study(cfg, out):
    t0 = time.perf_counter()
    df, _ = experiment.run(experiment.get("valid_region"), cfg, out, fresh=True)
    return df, time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=[str(ROOT / "configs/valid_region_ur5e.yaml"),
                                                     str(ROOT / "configs/valid_region_ur5e_full.yaml")])
    ap.add_argument("--full-chunks", type=int, default=None,
                    help="run only this many chunks of configs named *_full (projects the total)")
    args = ap.parse_args()

    cache = tempfile.mkdtemp(prefix="selfid_jax_cc_")
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)

    print(f"valid-region maps on {jax.device_count()} {jax.devices()[0].platform} device(s)")
    print(f"{'config':34s} {'rollouts':>9s} {'cold (incl. compile)':>21s} {'warm':>9s} {'compile':>8s} "
          f"{'rollouts/s':>11s}")
    for path in args.configs:
        cfg = load_config(path)
        overrides = {}
        if args.full_chunks and Path(path).stem.endswith("_full"):
            n_full = len(cfg.eps_limits.values()) * cfg.n_configs * cfg.n_trials * len(cfg.systems)
            keep = max(1, args.full_chunks * cfg.chunk_size // (cfg.n_trials * len(cfg.eps_limits.values())))
            overrides["n_configs"] = min(cfg.n_configs, keep)
            cfg = cfg.model_copy(update=overrides)
        with tempfile.TemporaryDirectory() as a, tempfile.TemporaryDirectory() as b:
            df, cold = timed_study(cfg, a)
            _, warm = timed_study(cfg, b)
        n = len(df)
        label = Path(path).name + (f" ({n} of {n_full} rows)" if overrides else "")
        print(f"{label:34s} {n:9d} {cold:20.2f}s {warm:8.2f}s {cold - warm:7.2f}s {n / warm:11.0f}")
        if overrides:
            print(f"{'':34s} projected full map: {n_full / (n / warm):.0f} s + compile")
    print("goal: paper-protocol UR5e map under 10 s including compile on a 2-core CPU")


if __name__ == "__main__":
    main()
