"""Workspace-map throughput: configurations per second of the workspace experiment's compiled compute.

Times ``jit(vmap(compute))`` of :mod:`selfid_jax.experiments.workspace` on batches of configurations of the arm5 (one
kinematics pass for pose and 6x5 Jacobian, three SVDs), float32 and float64, after a warm-up call, and once
through the sweep runner (chunks written to a temporary run directory). Prints configurations/s.

    python benchmarks/workspace.py [--n 1048576] [--chunk 131072]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import jax


def rate(n: int, chunk: int, x64: bool) -> float:
    from selfid_jax.experiments import workspace

    from selfid_jax.runner.execute import precision

    cfg = workspace.WorkspaceConfig(n_configs=n, x64=x64, chunk_size=chunk)
    with precision(x64):
        part = workspace.build(cfg)
        fn = jax.jit(workspace.EXPERIMENT.batched(part.static))
        params = jax.tree.map(lambda a: a[:chunk], part.params)
        jax.block_until_ready(fn(params))  # compile
        t = time.perf_counter()
        for start in range(0, n, chunk):
            params = jax.tree.map(lambda a, s=start: a[s:s + chunk], part.params)
            jax.block_until_ready(fn(params))
        return n / (time.perf_counter() - t)


def runner_rate(n: int, chunk: int) -> tuple[float, dict]:
    from selfid_jax.experiments import workspace

    from selfid_jax import runner as experiment

    cfg = workspace.WorkspaceConfig(n_configs=n, chunk_size=chunk)
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        _, summary = experiment.run(workspace.EXPERIMENT, cfg, d)
        return n / (time.perf_counter() - t), summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2**20)
    ap.add_argument("--chunk", type=int, default=2**17)
    args = ap.parse_args()
    print(f"devices: {jax.devices()}")
    for x64 in (False, True):
        r = rate(args.n, args.chunk, x64)
        print(f"compute only, {'float64' if x64 else 'float32'}: {args.n} configurations at {r:,.0f}/s")
    r, summary = runner_rate(args.n, args.chunk)
    print(f"through the sweep runner (float32, chunks to parquet, summary): {r:,.0f}/s; "
          f"{summary['cells_reached']['rz']} r-z cells of {1e3 * summary['cell_m']:g} mm")


if __name__ == "__main__":
    main()
