"""Ablation cost: wall time of the paper-protocol ablation and estimator updates per second per method.

Part 1 runs ``experiments.ablation.study`` on ``configs/ablation_ur5e.yaml``
(all methods, 9 configurations x 10 trials x noise levels) twice with JAX's
persistent compilation cache on (cold: with compile; warm: cached). Part 2
times ``baselines.run_stream`` for each method alone, vmapped over 256
streams of 100 UR5e-sized samples (n=6, m=3), and prints updates per second
relative to the paper's estimator ("ours") in the same process.

    python benchmarks/ablation.py [--config configs/ablation_ur5e.yaml] [--skip-study]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import selfid_jax  # noqa: F401
import jax
import jax.numpy as jnp

from selfid_jax import baselines
from selfid_jax.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def study_times(path):
    from experiments.ablation import study

    cfg = load_config(path)
    times = []
    for _ in range(2):
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            df = study(cfg, out, fresh=True)
            times.append(time.perf_counter() - t0)
    return cfg, df, times


def update_rates(cfg, batch=256, T=100, n=6, m=3):
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
        jax.block_until_ready(fn(keys, d, V))
        t0 = time.perf_counter()
        jax.block_until_ready(fn(keys, d, V))
        rows.append((spec.name, batch * T / (time.perf_counter() - t0)))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs/ablation_ur5e.yaml"))
    ap.add_argument("--skip-study", action="store_true")
    args = ap.parse_args()
    cache = tempfile.mkdtemp(prefix="selfid_jax_cc_")
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    cfg = load_config(args.config)
    if not args.skip_study:
        cfg, df, (cold, warm) = study_times(args.config)
        streams = len(df.drop_duplicates(["noise_level", "m_a", "config_id", "trial"]))
        print(f"paper-protocol ablation ({Path(args.config).name}): {len(cfg.methods)} methods, {streams} self-ID "
              f"streams, {len(df)} rollouts")
        print(f"  cold (incl. compile) {cold:.1f} s, warm {warm:.1f} s, compile ~{cold - warm:.1f} s, "
              f"{len(df) / warm:.0f} rollouts/s")
    rows = update_rates(cfg)
    ref = dict(rows).get("ours", rows[0][1])
    print("estimator updates per second (estimate read after every update, vmap over 256 streams, n=6, m=3):")
    for name, rate in rows:
        print(f"  {name:28s} {rate:12.0f} /s   {rate / ref:6.2f}x ours")


if __name__ == "__main__":
    main()
