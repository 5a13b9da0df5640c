"""Latency of the online runner's per-sample estimator step, against a numpy RLS update in the same process.

The step is what :func:`selfid_jax.robot.live.run_online` runs after each
accepted sample: :func:`selfid_jax.robot.steps.host_step`, i.e. the jitted
:func:`selfid_jax.identify.step.sample_step` (``update`` Eq. 6-12, ``initial_guess``
Eq. 13, the closed-form refinement Eq. 14, ``record`` Sec. IV-D) and the
host read of the step's info and ``converged_at`` the loop needs to decide
whether to move again: one sample at a time, batch 1, as a robot feeds it.
Timed per sample with ``time.perf_counter``; p50 and p99 over ``--samples``
samples (after ``--warmup`` untimed ones), for n = 6, m = 3 and n = 3, m = 3
in float64 and float32. The compile time of the first call is reported once
per configuration.

The baseline is the simplest faithful recursive least squares in numpy, per
sample: ``k = P V / (1 + V^T P V)``, ``Jinv += (dtheta - Jinv V) k^T``,
``P -= k (P V)^T`` (Sherman-Morrison; ``P_0 = 1e3 I``), in the same dtype.
Rows alternate ours / numpy in ``--rounds`` rounds, so load from other
processes on a shared machine hits both alike. Data: a random
well-conditioned linear system ``V = A dtheta + noise``, ``dtheta ~
U(-0.03, 0.03)``.

    python benchmarks/online_step.py [--samples 4000] [--rounds 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax

import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)

jax.config.update("jax_enable_x64", True)  # float64 rows; float32 rows pass float32 states

import numpy as np  # noqa: E402
from emit import emit  # noqa: E402
from timing import first_call  # noqa: E402

from selfid_jax.robot import steps  # noqa: E402

CONFIGS = ((6, 3), (3, 3))
DTYPES = ("float64", "float32")


def make_data(n: int, m: int, T: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``dtheta (T, n)``, ``V (T, m)`` float64 of a random linear system with singular values in [1, 3]."""
    rng = np.random.default_rng(seed)
    U = np.linalg.qr(rng.normal(size=(m, m)))[0]
    W = np.linalg.qr(rng.normal(size=(n, n)))[0][:, :m]
    A = U @ np.diag(np.geomspace(1.0, 3.0, m)) @ W.T  # (m, n)
    d = rng.uniform(-0.03, 0.03, (T, n))
    return d, d @ A.T + 1e-4 * rng.normal(size=(T, m))


def time_ours(state, d, V, dtype) -> np.ndarray:
    """Per-sample seconds of the online step (jitted step + the host reads the loop does)."""
    out = np.empty(d.shape[0])
    for i in range(d.shape[0]):
        t0 = time.perf_counter()
        state, _, _ = steps.host_step(state, d[i], V[i], 0.0, 0.05)
        out[i] = time.perf_counter() - t0
    return out


def time_rls(d, V, dtype) -> np.ndarray:
    """Per-sample seconds of a numpy RLS update of ``Jinv (n, m)`` (Sherman-Morrison on ``P (m, m)``)."""
    n, m = d.shape[1], V.shape[1]
    d, V = d.astype(dtype), V.astype(dtype)
    J = np.zeros((n, m), dtype)
    P = np.eye(m, dtype=dtype) * dtype(1e3)
    out = np.empty(d.shape[0])
    for i in range(d.shape[0]):
        t0 = time.perf_counter()
        v = V[i]
        Pv = P @ v
        k = Pv / (1 + v @ Pv)
        J += np.outer(d[i] - J @ v, k)
        P -= np.outer(k, Pv)
        out[i] = time.perf_counter() - t0
    return out


def run(samples: int = 4000, warmup: int = 200, rounds: int = 2) -> dict:
    rows = []
    for n, m in CONFIGS:
        for name in DTYPES:
            dtype = np.dtype(name)
            d, V = make_data(n, m, warmup + samples * rounds)
            state = steps.init_state(n, m, dtype=dtype)
            (state, info), compile_s = first_call(steps.sample_step, state, d[0], V[0], 0.0, 0.05)
            time_ours(state, d[:warmup], V[:warmup], dtype)
            time_rls(d[:warmup], V[:warmup], dtype.type)
            ours, rls = [], []
            for r in range(rounds):
                sl = slice(warmup + r * samples, warmup + (r + 1) * samples)
                ours.append(time_ours(state, d[sl], V[sl], dtype))
                rls.append(time_rls(d[sl], V[sl], dtype.type))
            o, b = np.concatenate(ours) * 1e3, np.concatenate(rls) * 1e3
            rows.append({"n": n, "m": m, "dtype": name, "samples": int(o.size), "compile_s": compile_s,
                         "ours_p50_ms": float(np.percentile(o, 50)), "ours_p99_ms": float(np.percentile(o, 99)),
                         "rls_p50_ms": float(np.percentile(b, 50)), "rls_p99_ms": float(np.percentile(b, 99))})
    return {"benchmark": "online_step", "rows": rows, "cpu_count": os.cpu_count(), "machine": platform.machine(),
            "jax": jax.__version__, "numpy": np.__version__, "backend": jax.default_backend()}


def report(res: dict) -> str:
    lines = [f"online per-sample step, batch 1, {res['backend']} ({res['cpu_count']} CPUs), jax {res['jax']}; "
             "ours = jitted identify.step.sample_step + host reads; rls = numpy Sherman-Morrison",
             f"{'n':>2} {'m':>2} {'dtype':>8} {'samples':>7} {'compile s':>9} {'ours p50 ms':>11} "
             f"{'ours p99 ms':>11} {'rls p50 ms':>10} {'rls p99 ms':>10} {'p50 ratio':>9} {'p99 ratio':>9}"]
    for r in res["rows"]:
        lines.append(f"{r['n']:>2} {r['m']:>2} {r['dtype']:>8} {r['samples']:>7} {r['compile_s']:>9.3f} "
                     f"{r['ours_p50_ms']:>11.4f} {r['ours_p99_ms']:>11.4f} {r['rls_p50_ms']:>10.4f} "
                     f"{r['rls_p99_ms']:>10.4f} {r['ours_p50_ms'] / r['rls_p50_ms']:>8.1f}x "
                     f"{r['ours_p99_ms'] / r['rls_p99_ms']:>8.1f}x")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=4000, help="timed samples per round")
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--json", default=None, help="write the results here")
    args = ap.parse_args()
    res = run(args.samples, args.warmup, args.rounds)
    emit(res, report(res), args.json)


if __name__ == "__main__":
    main()
