"""The self-ID step against the memory-bandwidth bound of the device it runs on.

The step (``benchmarks/estimator.py``'s ``ours``: ``update``, ``initial_guess``,
``statistics_closed_form``, ``record``; n = 6, m = 3, float32, no sample buffer)
does a few hundred flops per estimator and sample on a state of about 100
values, so a batch of estimators is bound by memory traffic, not arithmetic.
This script states that traffic and measures how close the step comes to it:

* **traffic per estimator and sample**, counted two ways: from the state
  (``2 x`` the bytes of the leaves a step changes, read and written, plus the
  bytes of the leaves it only reads and of the sample ``(dtheta, V)``), and as
  XLA counts it (``cost_analysis()["bytes accessed"]`` of one compiled
  ``vmap(step)``, divided by the batch: every fusion's operands and outputs);
* **copy bandwidth** of the default device: the best of ``--reps`` calls of a
  jitted ``x * a + b`` over ``--copy-mib`` MiB of float32, counted as bytes
  read plus bytes written;
* **the bound**: bandwidth / traffic, estimator-steps per second, and the
  measured rate of ``--steps`` steps of ``vmap(step)`` in one ``lax.scan`` at
  ``--batch`` estimators as a fraction of it.

    python benchmarks/bandwidth.py [--batch 10000] [--steps 50] [--copy-mib 256] [--json out.json]
    JAX_PLATFORMS=cpu taskset -c 0,1 python benchmarks/bandwidth.py   # the 2-core CPU row on a bigger machine

On a GPU run it with ``--batch 1000000 --copy-mib 2048`` (``benchmarks/gpu.sh`` does).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import jax
import jax.numpy as jnp
import numpy as np
from emit import emit
from estimator import F32, E, M, N, make_data, ours_step, scan_fn
from timing import first_call, repeat


def state_traffic(batch: int = 64, steps: int = 8) -> dict:
    """Bytes per estimator and sample the step must move, from which state leaves it changes.

    Runs ``steps`` steps on ``batch`` estimators of random data and marks a leaf
    as written when any of its entries changed in any step.
    """
    d, V, _ = make_data(batch, steps, seed=1)
    state = jax.vmap(lambda _: E.init(N, M, capacity=0, dtype=F32))(jnp.arange(batch))
    step = jax.jit(jax.vmap(ours_step))
    changed = {name: False for name in state._fields}
    for t in range(steps):
        new = step(state, d[t], V[t])
        for name in state._fields:
            a, b = np.asarray(getattr(state, name)), np.asarray(getattr(new, name))
            changed[name] |= bool(a.size) and not np.array_equal(a, b, equal_nan=True)
        state = new
    size = {name: int(np.asarray(getattr(state, name)).nbytes // batch) for name in state._fields}
    written = sum(size[k] for k, c in changed.items() if c)
    read_only = sum(size[k] for k, c in changed.items() if not c)
    sample = (N + M) * np.dtype(np.float32).itemsize
    return {"state_bytes": sum(size.values()), "written_bytes": written, "read_only_bytes": read_only,
            "sample_bytes": sample, "bytes_per_step": 2 * written + read_only + sample,
            "written_leaves": [k for k, c in changed.items() if c],
            "read_only_leaves": [k for k, c in changed.items() if not c and size[k]]}


def xla_traffic(batch: int) -> float | None:
    """XLA's ``bytes accessed`` of one compiled ``vmap(step)`` at ``batch`` estimators, per estimator (None if the
    backend does not say)."""
    d, V, _ = make_data(batch, 1, seed=2)
    state = jax.vmap(lambda _: E.init(N, M, capacity=0, dtype=F32))(jnp.arange(batch))
    cost = jax.jit(jax.vmap(ours_step)).lower(state, d[0], V[0]).compile().cost_analysis()
    if isinstance(cost, list):  # older jax: one dict per program
        cost = cost[0] if cost else None
    if not cost or "bytes accessed" not in cost:
        return None
    return float(cost["bytes accessed"]) / batch


def copy_bandwidth(mib: int = 256, reps: int = 10) -> float:
    """Bytes per second (read + written) of the best of ``reps`` jitted ``x * a + b`` over ``mib`` MiB of float32."""
    n = mib * (1 << 20) // 4
    x = jnp.ones((n,), F32)
    f = jax.jit(lambda x: x * jnp.float32(1.0001) + jnp.float32(1e-7))
    first_call(f, x)
    return 2 * x.nbytes / min(repeat(f, x, reps=reps))


def run(batch: int = 10_000, steps: int = 50, reps: int = 5, copy_mib: int = 256) -> dict:
    traffic = state_traffic()
    xla = xla_traffic(min(batch, 4096))
    bw = copy_bandwidth(copy_mib)
    d, V, _ = make_data(batch, steps)
    fn = scan_fn(batch, lambda: E.init(N, M, capacity=0, dtype=F32), ours_step, lambda s: s.estimate)
    _, compile_s = first_call(fn, d, V)
    per_call = statistics.median(repeat(fn, d, V, reps=reps))
    rate = batch * steps / per_call
    bound = bw / traffic["bytes_per_step"]
    return {"batch": batch, "steps": steps, "n": N, "m": M, "dtype": "float32",
            "device": f"1 {jax.devices()[0].platform} ({jax.devices()[0].device_kind})",
            "cpus_visible": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
            "traffic": traffic, "xla_bytes_per_step": xla, "copy_bandwidth_gb_s": bw / 1e9,
            "bound_estimator_steps_per_s": bound, "estimator_steps_per_s": rate, "steps_per_s": steps / per_call,
            "fraction_of_bound": rate / bound, "first_call_s": compile_s, "effective_gb_s":
                rate * traffic["bytes_per_step"] / 1e9}


def report(r: dict) -> str:
    t = r["traffic"]
    xla = "-" if r["xla_bytes_per_step"] is None else f"{r['xla_bytes_per_step']:.0f} B"
    return "\n".join([
        f"self-ID step against the bandwidth bound, {r['device']}, {r['cpus_visible']} CPUs visible",
        f"traffic per estimator and sample: {t['bytes_per_step']} B = 2 x {t['written_bytes']} B written "
        f"({', '.join(t['written_leaves'])}) + {t['read_only_bytes']} B read only "
        f"({', '.join(t['read_only_leaves'])}) + {t['sample_bytes']} B sample; XLA counts {xla}",
        f"copy bandwidth {r['copy_bandwidth_gb_s']:.1f} GB/s -> bound {r['bound_estimator_steps_per_s']:.3g} "
        f"estimator-steps/s",
        f"measured at batch {r['batch']:,} ({r['steps']} steps in one scan): {r['estimator_steps_per_s']:.3g} "
        f"estimator-steps/s = {r['steps_per_s']:.0f} steps/s, {r['effective_gb_s']:.1f} GB/s effective, "
        f"{100 * r['fraction_of_bound']:.1f} % of the bound (first call {r['first_call_s']:.1f} s)",
    ])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--copy-mib", type=int, default=256, help="MiB of float32 in the copy-bandwidth probe")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    res = run(args.batch, args.steps, args.reps, args.copy_mib)
    emit(res, report(res), args.json)


if __name__ == "__main__":
    main()
