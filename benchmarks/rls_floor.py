"""The self-ID step against the RLS floor: a plain five-line RLS, baselines.rls, the old full step, the new one.

All in one process, on the data of ``benchmarks/estimator.py`` (random
well-conditioned linear systems, n = 6, m = 3, float32, ``--batch``
estimators, ``--steps`` samples from an empty estimator), timed in
interleaved rounds (medians; compile separate):

* ``plain RLS``: five lines written here (``P v``, the gain, ``J += e k^T``,
  ``P -= k (P v)^T``) in a ``lax.scan`` under ``vmap``, ``P_0 = 1e4 I``;
* ``baselines.rls``: :func:`selfid_jax.baselines.rls` ``update`` + ``estimate``;
* ``old full step``: ``update``, ``initial_guess``, the batch closed form
  (Eq. 14) and ``record`` every sample (what ``self_identify`` ran before);
* ``new step, per sample``: :func:`selfid_jax.identify.recursive.step` in the
  same harness (one branch choice per vmapped batch per sample);
* ``new step, block``: :func:`selfid_jax.identify.recursive.run` over the
  ``--steps`` samples under ``vmap`` (batch form for the first m + 5, rank-one
  steps after, one branch per block; ``history=False``: like the per-sample
  rows, no per-sample record is written): the fleet form, and what
  ``self_identify`` runs;
* ``new step, block, steady``: the same on ``--steps`` further samples of
  estimators that have already seen ``--steps`` (``warmup=0``): the rate of
  a fleet past its start;
* ``... steady, full state out``: the same program returning the whole
  state (what a fleet keeps). The rows above return only the estimates, which
  lets XLA drop the statistics the rank-one steps do not read (sign weights,
  magnitudes, ``S_tv``) from the rank-one loop: they flatter the step.

Then the float32 error of the new step against float64 least squares (the
timed data, and ``--long`` samples for ``--long-batch`` estimators, with and
without a periodic re-solve), and the live-loop latency at batch 1 (jitted,
``--calls`` calls after a warm-up, p50 and p99 per sample): the old full step,
the new step, the new step with donated buffers, the packed state
(:func:`~selfid_jax.identify.recursive.pack`; also donated), and the block of
``--block`` samples per call, for n = 6, m = 3 and n = 3, m = 3; then the same
in a fresh process with synchronous CPU dispatch (``, sync`` rows:
``jax_cpu_enable_async_dispatch=False``, each call run on the calling thread,
the live loop's setting).
Goals (issue 27): new >= 0.5x plain RLS, >= 1x baselines.rls, >= 2,000 steps/s at
10,000 estimators; batch-1 p99 <= 0.1 ms.

On a 2-core CPU, XLA splits each large loop of a program over both cores; what that split costs differs
between processes (plain RLS at 0.31-0.37 or 0.67-0.71 ms per sample at 10,000 estimators, the same code), so
a single process's ratios can be off by up to 1.4x. ``--one-core`` pins the process to one CPU before JAX
starts: every row then runs without the split (docs/benchmarks.md).

    python benchmarks/rls_floor.py [--batch 10000] [--steps 50] [--reps 3] [--rounds 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
from emit import emit
from timing import first_call, interleaved, pin_one_core, usable_cpus

import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)
from selfid_jax import baselines
from selfid_jax.identify import estimator as E
from selfid_jax.identify import recursive as R
from selfid_jax.identify.refine import statistics_closed_form

F32 = jnp.float32
EPS = 1e-3


def make_data(batch: int, steps: int, n: int = 6, m: int = 3, seed: int = 0):
    """``dtheta (steps, batch, n)``, ``V (steps, batch, m)`` (float64 numpy): ``V = A dtheta + 1e-4 noise``,
    singular values of ``A (m, n)`` in [1, 3]."""
    rng = np.random.default_rng(seed)
    U = np.linalg.qr(rng.normal(size=(batch, m, m)))[0]
    W = np.linalg.qr(rng.normal(size=(batch, n, n)))[0][:, :m]
    A = np.einsum("bij,j,bjk->bik", U, np.geomspace(1.0, 3.0, m), W)
    d = rng.uniform(-0.03, 0.03, (steps, batch, n))
    V = np.einsum("bmn,tbn->tbm", A, d) + 1e-4 * rng.normal(size=(steps, batch, m))
    return d, V


def plain_rls_step(s, dtheta, V):
    J, P = s
    Pv = P @ V
    k = Pv / (1.0 + V @ Pv)
    J = J + (dtheta - J @ V)[:, None] * k[None, :]
    P = P - k[:, None] * Pv[None, :]
    return J, P


RLS = baselines.rls(delta=1e-4)


def rls_step(state, dtheta, V):
    state = RLS.update(state, dtheta, V)
    return state._replace(J=RLS.estimate(state, jnp.zeros_like(state.J)))


def old_step(state, dtheta, V):
    state = E.update(state, dtheta, V)
    J = statistics_closed_form(state.S_vv, state.S_tv, E.initial_guess(state))
    return E.record(state, J, EPS)


def new_step(carry, dtheta, V):
    return R.step(*carry, dtheta, V, EPS)


def scan_rows(n: int, m: int) -> dict:
    """``name: (init, step, read)`` for the per-sample harness."""
    return {
        "plain RLS": (lambda: (jnp.zeros((n, m), F32), 1e4 * jnp.eye(m, dtype=F32)), plain_rls_step, lambda s: s[0]),
        "baselines.rls": (lambda: RLS.init(n, m, dtype=F32), rls_step, lambda s: s.J),
        "old full step": (lambda: E.init(n, m, capacity=0, dtype=F32), old_step, lambda s: s.estimate),
        "new step, per sample": (lambda: (E.init(n, m, capacity=0, dtype=F32), R.init(m, F32)), new_step,
                                 lambda s: s[0].estimate),
    }


def scan_fn(batch, init, step, read):
    vstep = jax.vmap(step)

    def run(d, V):
        s0 = jax.vmap(lambda _: init())(jnp.arange(batch))
        s, _ = jax.lax.scan(lambda s, x: (vstep(s, *x), None), s0, (d, V))
        return read(s)

    return jax.jit(run)


def block_fn(batch, n, m, resolve_every: int = 0):
    def one(d, V):
        s, _, _, _ = R.run(E.init(n, m, capacity=0, dtype=F32), R.init(m, F32), d, V, EPS, warmup=m + 5,
                           resolve_every=resolve_every, history=False)
        return s.estimate

    return jax.jit(jax.vmap(one, in_axes=(1, 1)))


def steady_program(n, m, d0, V0, *, full_state: bool = False):
    """``(fn, s0, r0)``: the block step jitted and vmapped, ``fn(s0, r0, d, V)``, from the state ``(s0, r0)`` after
    ``d0 (T, batch, n)``, ``V0``.

    ``full_state=True``: ``fn`` returns the whole ``(state, rec)``, as a fleet that keeps its estimators
    must; else only the estimates, which lets XLA drop the updates of the statistics that the rank-one
    steps do not read (sign weights, magnitudes, ``S_tv``) from the rank-one loop.
    """
    def first(d, V):
        return R.run(E.init(n, m, capacity=0, dtype=F32), R.init(m, F32), d, V, EPS, warmup=m + 5, history=False)[:2]

    s0, r0 = jax.block_until_ready(jax.jit(jax.vmap(first, in_axes=(1, 1)))(d0, V0))

    def more(s, r, d, V):
        out = R.run(s, r, d, V, EPS, warmup=0, history=False)[:2]
        return out if full_state else out[0].estimate

    return jax.jit(jax.vmap(more, in_axes=(0, 0, 1, 1))), s0, r0


def steady_fn(n, m, d0, V0, *, full_state: bool = False):
    """The block step from the state after ``d0 (T, batch, n)``, ``V0`` (:func:`steady_program`):
    ``fn(d, V) -> estimates``; with ``full_state`` the whole state is computed and the estimate read."""
    fn, s0, r0 = steady_program(n, m, d0, V0, full_state=full_state)
    if not full_state:
        return lambda d, V: fn(s0, r0, d, V)
    return lambda d, V: fn(s0, r0, d, V)[0].estimate


def lstsq(d, V, count):
    return np.stack([np.linalg.lstsq(V[:, b], d[:, b], rcond=None)[0].T for b in range(count)])


def rel_err(J, ref):
    J = np.asarray(J[: len(ref)], np.float64)
    return float(np.max(np.linalg.norm(J - ref, axis=(1, 2)) / np.linalg.norm(ref, axis=(1, 2))))


def throughput(batch, steps, reps, rounds, n=6, m=3):
    d64, V64 = make_data(batch, 2 * steps, n, m)
    d, V = jnp.asarray(d64[:steps], F32), jnp.asarray(V64[:steps], F32)
    ref = lstsq(d64[:steps], V64[:steps], min(200, batch))
    fns = {name: scan_fn(batch, *row) for name, row in scan_rows(n, m).items()}
    fns["new step, block"] = block_fn(batch, n, m)
    fns["new step, block, steady"] = steady_fn(n, m, d, V)
    fns["... steady, full state out"] = steady_fn(n, m, d, V, full_state=True)
    d2, V2 = jnp.asarray(d64[steps:], F32), jnp.asarray(V64[steps:], F32)
    ref2 = lstsq(d64, V64, min(200, batch))
    first, errs = {}, {}
    data = {name: ((d2, V2, ref2) if "steady" in name else (d, V, ref)) for name in fns}
    for name, fn in fns.items():
        out, first[name] = first_call(fn, *data[name][:2])
        errs[name] = rel_err(out, data[name][2])
    times = interleaved({name: (lambda fn=fn, name=name: fn(*data[name][:2]), steps) for name, fn in fns.items()},
                        reps, rounds)
    plain = statistics.median(times["plain RLS"])
    rls = statistics.median(times["baselines.rls"])
    rows = {}
    for name, ts in times.items():
        t = statistics.median(ts)
        rows[name] = {"ms_per_step": 1e3 * t, "steps_per_s": 1.0 / t, "x_plain_rls": plain / t,
                      "x_baselines_rls": rls / t, "first_call_s": first[name], "rel_err_vs_float64_lstsq": errs[name]}
    return rows


def long_error(batch, samples):
    """float32 error of the block step over ``samples`` samples against float64 least squares, per re-solve period."""
    d64, V64 = make_data(batch, samples, seed=1)
    d, V = jnp.asarray(d64, F32), jnp.asarray(V64, F32)
    ref = lstsq(d64, V64, batch)
    out = {}
    for every in (0, 1000):
        J = block_fn(batch, 6, 3, resolve_every=every)(d, V)
        out[f"resolve_every={every}"] = rel_err(J, ref)
    return out


def latency(n, m, calls, block):
    """Per-sample wall time (ms) at batch 1, jitted: p50 and p99 of ``calls`` calls after a warm-up."""
    d64, V64 = make_data(1, calls + 200, n, m, seed=2)
    d, V = np.asarray(d64[:, 0], np.float32), np.asarray(V64[:, 0], np.float32)
    old = jax.jit(old_step)
    new = jax.jit(lambda s, r, x, v: R.step(s, r, x, v, EPS))
    new_donated = jax.jit(lambda s, r, x, v: R.step(s, r, x, v, EPS), donate_argnums=(0, 1))
    run = jax.jit(lambda s, r, x, v: R.run(s, r, x, v, EPS, warmup=0, history=False)[:2])
    packed = jax.jit(lambda f, i, x, v: R.packed_step(f, i, x, v, EPS, n=n, m=m))
    packed_donated = jax.jit(lambda f, i, x, v: R.packed_step(f, i, x, v, EPS, n=n, m=m), donate_argnums=(0, 1))
    res = {}

    def timed(name, call, state, per):
        for t in range(100):  # warm-up, past the rank-deficient start
            state = call(state, t)
        jax.block_until_ready(state)
        ts = []
        for t in range(100, 100 + calls // per):
            t0 = time.perf_counter()
            state = jax.block_until_ready(call(state, t))
            ts.append((time.perf_counter() - t0) / per)
        res[name] = {"p50_ms": 1e3 * float(np.percentile(ts, 50)), "p99_ms": 1e3 * float(np.percentile(ts, 99)),
                     "samples_per_call": per}

    s0 = E.init(n, m, capacity=0, dtype=F32)
    r0 = R.init(m, F32)
    timed("old full step", lambda s, t: old(s, d[t], V[t]), s0, 1)
    timed("new step", lambda c, t: new(*c, d[t], V[t]), (s0, r0), 1)
    own = jax.tree.map(lambda x: jnp.array(x, copy=True), (s0, r0))  # init shares one zeros buffer among fields
    timed("new step, donated", lambda c, t: new_donated(*c, d[t], V[t]), own, 1)
    timed("new step, packed state", lambda c, t: packed(*c, d[t], V[t]), R.pack(s0, r0), 1)
    timed("new step, packed, donated", lambda c, t: packed_donated(*c, d[t], V[t]), R.pack(s0, r0), 1)
    db = d[: (len(d) // block) * block].reshape(-1, block, n)
    Vb = V[: (len(V) // block) * block].reshape(-1, block, m)
    timed(f"new step, {block} per call", lambda c, t: run(*c, db[t % len(db)], Vb[t % len(Vb)]), (s0, r0), block)
    return res


def latencies(calls, block) -> dict:
    return {"n=6,m=3": latency(6, 3, calls, block), "n=3,m=3": latency(3, 3, calls, block)}


def latencies_sync(calls, block) -> dict:
    """:func:`latencies` in a fresh process whose CPU client runs each call on the calling thread
    (``jax_cpu_enable_async_dispatch=False``, fixed when JAX starts its CPU backend): the live loop's setting,
    which blocks on every result anyway, and no hand-off to the client's thread per call."""
    import json
    import os
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "latency.json")
        subprocess.run([sys.executable, os.path.abspath(__file__), "--latency-only", "--sync-dispatch", "--calls",
                        str(calls), "--block", str(block), "--json", out], check=True, stdout=subprocess.DEVNULL)
        with open(out) as f:
            return json.load(f)


def run(batch=10_000, steps=50, reps=3, rounds=3, long=10_000, long_batch=100, calls=2000, block=10) -> dict:
    rows = throughput(batch, steps, reps, rounds)
    lat = latencies(calls, block)
    for where, more in latencies_sync(calls, block).items():
        lat[where].update({f"{name}, sync": r for name, r in more.items()})
    return {"batch": batch, "steps": steps, "n": 6, "m": 3, "dtype": "float32", "reps": reps * rounds,
            "device": f"1 {jax.devices()[0].platform}, {usable_cpus()} CPU core(s) usable",
            "rows": rows,
            "long": {"samples": long, "batch": long_batch, "rel_err": long_error(long_batch, long)},
            "latency": lat}


def report(res: dict) -> str:
    lines = [f"self-ID step against the RLS floor: {res['batch']} vmapped estimators (n=6, m=3, float32), "
             f"{res['steps']} samples from empty, median of {res['reps']}, {res['device']}",
             f"{'variant':27s} {'ms/step':>8s} {'steps/s':>8s} {'x plain':>8s} {'x b.rls':>8s} {'1st call':>9s} "
             f"{'err vs f64':>10s}"]
    for name, r in res["rows"].items():
        lines.append(f"{name:27s} {r['ms_per_step']:8.3f} {r['steps_per_s']:8.0f} {r['x_plain_rls']:8.2f} "
                     f"{r['x_baselines_rls']:8.2f} {r['first_call_s']:8.2f}s {r['rel_err_vs_float64_lstsq']:10.1e}")
    lg = res["long"]
    lines.append(f"float32 over {lg['samples']} samples ({lg['batch']} estimators), max relative error vs float64 "
                 "least squares: " + ", ".join(f"{k} {v:.1e}" for k, v in lg["rel_err"].items()))
    for where, rows in res["latency"].items():
        for name, r in rows.items():
            lines.append(f"batch 1, {where}, {name:31s}: p50 {1e3 * r['p50_ms']:6.1f} us, p99 {1e3 * r['p99_ms']:6.1f} "
                         "us per sample")
    new = res["rows"]["new step, block"]
    steady = res["rows"]["new step, block, steady"]
    full = res["rows"]["... steady, full state out"]
    lat = res["latency"]["n=6,m=3"]
    p99 = lat["new step"]["p99_ms"]
    best = min((k for k, r in lat.items() if r["samples_per_call"] == 1 and "old" not in k),
               key=lambda k: lat[k]["p99_ms"])
    goals = [("new >= 0.5x plain RLS", new["x_plain_rls"] >= 0.5, f"{new['x_plain_rls']:.2f}x"),
             (">= 1x baselines.rls", new["x_baselines_rls"] >= 1.0, f"{new['x_baselines_rls']:.2f}x"),
             (">= 2000 steps/s", new["steps_per_s"] >= 2000, f"{new['steps_per_s']:.0f}"),
             ("steady >= 0.5x plain RLS", steady["x_plain_rls"] >= 0.5, f"{steady['x_plain_rls']:.2f}x"),
             ("steady, full state out >= 0.5x plain RLS", full["x_plain_rls"] >= 0.5, f"{full['x_plain_rls']:.2f}x"),
             ("batch-1 p99 <= 0.1 ms (n=6, m=3), new step", p99 <= 0.1, f"{p99:.3f} ms"),
             ("... best one-sample form", lat[best]["p99_ms"] <= 0.1, f"{best}: {lat[best]['p99_ms']:.3f} ms"),
             ("float32 error <= 1e-4", max(res["long"]["rel_err"].values()) <= 1e-4,
              f"{max(res['long']['rel_err'].values()):.1e}")]
    lines.append("goals: " + "; ".join(f"{g} {'met' if ok else 'NOT met'} ({v})" for g, ok, v in goals))
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--long", type=int, default=10_000, help="samples of the float32 drift check")
    ap.add_argument("--long-batch", type=int, default=100)
    ap.add_argument("--calls", type=int, default=2000, help="timed calls of the batch-1 latency")
    ap.add_argument("--block", type=int, default=10, help="samples per call of the blocked live-loop step")
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--latency-only", action="store_true", help="only the batch-1 latencies (their JSON record)")
    ap.add_argument("--sync-dispatch", action="store_true",
                    help="run each call on the calling thread (jax_cpu_enable_async_dispatch=False)")
    ap.add_argument("--one-core", action="store_true",
                    help="run on one CPU (set before JAX starts its CPU client): every row without XLA's split of "
                         "each loop over the cores, whose cost differs between processes")
    a = ap.parse_args()
    if a.one_core:
        pin_one_core(ap)
    if a.sync_dispatch:
        jax.config.update("jax_cpu_enable_async_dispatch", False)  # before the CPU backend starts
    if a.latency_only:
        lat = latencies(a.calls, a.block)
        emit(lat, "\n".join(f"{w} {k}: p50 {1e3 * r['p50_ms']:.1f} us, p99 {1e3 * r['p99_ms']:.1f} us"
                            for w, rows in lat.items() for k, r in rows.items()), a.json)
        return
    res = run(a.batch, a.steps, a.reps, a.rounds, a.long, a.long_batch, a.calls, a.block)
    emit(res, report(res), a.json)


if __name__ == "__main__":
    main()
