"""One experiment run as a whole process, for timing from outside: cold or warm compile cache, peak RSS.

Run as a child process by :func:`measure` (``benchmarks/ablation.py``,
``benchmarks/valid_region.py``, ``benchmarks/run_all.py``): it imports the
package, loads the config (with ``--set`` overrides), runs the experiment into
a temporary directory with JAX's persistent compilation cache in
``--cache-dir`` (empty: a cold start; reused: warm), and prints one JSON line:
rows computed, the seconds spent in import / build / run inside the process and to the first chunk file
on disk (the sweep's first result),
the seconds of each compile stage (JAX's own duration events: ``trace`` to a
jaxpr, ``lower`` to MLIR, ``xla`` backend compile; total, longest single one
and count; a program read back from the cache has no ``xla`` entry), and the
process's peak resident memory. :func:`measure` adds the wall time
seen by the parent, which is the whole-process time (interpreter start to exit).

    python benchmarks/whole_process.py CONFIG --cache-dir DIR [--set key=value ...]
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from timing import run_process

ROOT = Path(__file__).resolve().parents[1]


def measure(config, cache_dir, overrides=(), env=None, timeout=1800) -> dict:
    """Run this script in a child process; returns its JSON record plus ``wall_s`` (whole process)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), str(config), "--cache-dir", str(cache_dir)]
    for o in overrides:
        cmd += ["--set", o]
    out, wall = run_process(cmd, capture_output=True, text=True, cwd=ROOT, env={**os.environ, **(env or {})},
                            timeout=timeout)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr[-3000:]}")
    record = json.loads(out.stdout.strip().splitlines()[-1])
    record["wall_s"] = wall
    return record


def main():
    t0 = time.perf_counter()
    import argparse
    import resource
    import tempfile
    import threading

    ap = argparse.ArgumentParser()
    ap.add_argument("config")
    ap.add_argument("--cache-dir", required=True)
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()

    import jax
    import jax.monitoring

    import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)

    # seconds per compile stage, from JAX's own events: tracing to a jaxpr, lowering to MLIR, XLA's backend compile
    stages = {"/jax/core/compile/jaxpr_trace_duration": "trace", "/jax/core/compile/jaxpr_to_mlir_module_duration":
              "lower", "/jax/core/compile/backend_compile_duration": "xla"}
    compile_s = {name: [] for name in stages.values()}

    def on_duration(event, seconds, **_):
        if event in stages:
            compile_s[stages[event]].append(float(seconds))

    hits = []

    def on_event(event, **_):
        if event == "/jax/compilation_cache/cache_hits":
            hits.append(1)

    jax.monitoring.register_event_duration_secs_listener(on_duration)
    jax.monitoring.register_event_listener(on_event)

    jax.config.update("jax_compilation_cache_dir", args.cache_dir)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    from selfid_jax import runner as experiment
    from selfid_jax.runner.registry import load as load_config

    t_import = time.perf_counter()
    cfg = load_config(args.config, args.set)
    exp = experiment.get(cfg.experiment)
    parts = exp.parts(cfg)
    t_build = time.perf_counter()
    with tempfile.TemporaryDirectory() as out:
        first_chunk: list[float] = []
        done = threading.Event()

        def watch():  # the first chunk file on disk: the sweep's first result
            while not done.wait(0.05):
                if next(Path(out).glob("**/chunks/chunk_*.parquet"), None) is not None:
                    first_chunk.append(time.perf_counter())
                    return

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        df, summary = experiment.run(exp, cfg, out, fresh=True, parts=parts)
        done.set()
        watcher.join()
    t_run = time.perf_counter()
    print(json.dumps({
        "config": Path(args.config).name, "overrides": args.set, "rows": len(df),
        "import_s": t_import - t0, "build_s": t_build - t_import, "run_s": t_run - t_build,
        "first_chunk_s": (first_chunk[0] if first_chunk else t_run) - t0,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "compile": {stage: {"total_s": sum(v), "max_s": max(v, default=0.0), "count": len(v)}
                    for stage, v in compile_s.items()},
        "cache_hits": len(hits),  # programs read back from the persistent cache (their "xla" entry is the read)
        "devices": f"{jax.device_count()} {jax.devices()[0].platform}",
        "summary": summary if cfg.experiment == "valid_region" else None,
    }, default=str))


if __name__ == "__main__":
    main()
