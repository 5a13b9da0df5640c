"""Settled poses per second of the closed-chain hands, per backend and batch size (float64, CPU).

For each hand (the Stewart Hand; the Model O too when
``selfid_jax.systems.hands.model_o_hand`` exists) and backend (``kinematic``:
Newton solve; ``mjx``: MJX settling; ``native``: ``mujoco.rollout`` through
``jax.pure_callback``, one batched call), times ``jit(vmap(system.pose))`` on
random commands from the hand's sampling box at batch 1, 100, 1000 (and
100,000 for kinematic), compile time separate, and prints poses/s with the
ratio against native at the same batch and the fraction of NaN (failed) poses.

    python benchmarks/hands.py            # full: mjx up to batch 1000 (several minutes on 2 cores)
    python benchmarks/hands.py --quick    # mjx at batch 1 and 100 only, kinematic up to 10,000
"""

from __future__ import annotations

import argparse
import importlib
import time

import jax
import numpy as np

import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)
from selfid_jax.systems.hands.stewart import stewart_hand


def _hands():
    """``{name: factory(backend=...) -> System}``: the Stewart Hand and, if present, the Model O."""
    hands = {"stewart_hand": stewart_hand}
    try:
        mod = importlib.import_module("selfid_jax.systems.hands.model_o_hand")
    except ImportError:
        return hands
    factory = getattr(mod, "model_o", None)
    if callable(factory):
        hands["model_o"] = factory
    return hands


def _time(fn, q, min_time):
    """``(seconds per call, compile seconds, NaN fraction)`` of ``fn(q)``."""
    t0 = time.perf_counter()
    p, _ = fn(q)
    jax.block_until_ready(p)
    compile_s = time.perf_counter() - t0
    n, t0 = 0, time.perf_counter()
    while True:
        p, _ = fn(q)
        jax.block_until_ready(p)
        n += 1
        if time.perf_counter() - t0 >= min_time or n >= 20:
            break
    return (time.perf_counter() - t0) / n, compile_s, float(np.mean(np.isnan(np.asarray(p)[:, 0])))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller batches for mjx and kinematic")
    ap.add_argument("--min-time", type=float, default=0.5, help="seconds of timed calls per entry")
    args = ap.parse_args()
    batches = {
        "kinematic": (1, 100, 1000, 10_000) if args.quick else (1, 100, 1000, 100_000),
        "mjx": (1, 100) if args.quick else (1, 100, 1000),
        "native": (1, 100, 1000),
    }
    print(f"devices: {jax.devices()}  (float64)")
    print(f"{'hand':14s} {'backend':10s} {'batch':>7s} {'poses/s':>11s} {'x native':>9s} {'compile s':>10s} "
          f"{'NaN':>5s}")
    with jax.enable_x64(True):
        for hname, factory in _hands().items():
            rates = {}
            for backend in ("native", "kinematic", "mjx"):
                try:
                    system = factory(backend=backend)
                except (ValueError, TypeError) as e:
                    print(f"{hname:14s} {backend:10s} skipped: {e}")
                    continue
                fn = jax.jit(jax.vmap(system.pose))
                low, high = np.asarray(system.sample_low), np.asarray(system.sample_high)
                for B in batches[backend]:
                    q = np.random.default_rng(B).uniform(low, high, (B, system.n_act))
                    sec, comp, nan = _time(fn, jax.numpy.asarray(q), args.min_time)
                    rate = B / sec
                    rates[(backend, B)] = rate
                    ref = rates.get(("native", B))
                    ratio = f"{rate / ref:9.2f}" if ref else f"{'-':>9s}"
                    print(f"{hname:14s} {backend:10s} {B:7d} {rate:11.1f} {ratio} {comp:10.1f} {nan:5.2f}", flush=True)


if __name__ == "__main__":
    main()
