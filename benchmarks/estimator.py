"""Throughput of one full self-ID step for many vmapped estimators, against RLS in the same run.

A step is what Algorithm 1 does per sample: ``update`` (Eq. 6-12 and the
statistics ``S_vv``, ``S_tv``), ``initial_guess`` (Eq. 13), the closed-form
refinement (Eq. 14, :func:`selfid_jax.identify.refine.statistics_closed_form`) and the
convergence ``record`` (Sec. IV-D). The harness is a ``lax.scan`` over
``--steps`` samples whose body is ``vmap(step)`` over ``--batch`` estimators
(n = 6, m = 3, float32): one sample per robot per control tick, as a 1 kHz
loop over a fleet would run. Data: random well-conditioned linear systems
``V = A dtheta + noise`` (singular values of ``A`` in [1, 3], noise 1e-4).

Rows (medians of ``--reps`` timings after a warm-up, interleaved in rounds so
that load from other processes hits all alike; compile time separate):

* ``rls``: :func:`selfid_jax.baselines.rls` ``update`` + ``estimate``, the reference;
* ``ours``: the full step above as :func:`selfid_jax.identify.step.sample_step`
  runs it (``method="closed_form"``), no sample buffer (``capacity=0``): one
  native CPU kernel for the whole step where the kernels are built
  (:mod:`selfid_jax.math.native`);
* ``ours, pure JAX``: the same step with the kernels off, XLA code only;
* ``ours, composed``: the step written by a caller from the public functions
  (``update``, ``initial_guess``, ``statistics_closed_form``, ``record``):
  three native kernels and the guess in XLA between them;
* ``ours, least squares only``: ``update`` + ``S_tv S_vv^+`` without the
  initial guess and the record (the probe of the issue);
* ``ours, 64-sample buffer (before)``: the pre-statistics step, Eq. 14
  re-solved on a 64-sample ring buffer every step (``closed_form`` on the
  buffer, SVD pseudo-inverse), timed on ``--steps-before`` samples;
* ``..., full state out``: ``rls``, ``ours``, ``ours, pure JAX`` and ``ours, composed`` with the
  whole final state returned instead of the estimate alone (so XLA drops none
  of the step as dead code), their ratios against ``plain RLS, full state
  out``: five lines written here (``P v``, the gain, ``J += e k^T``,
  ``P -= k (P v)^T``; ``P_0 = 1e4 I``, no screen), ``J`` and ``P`` returned.

Also prints the relative error of the final float32 estimate against a float64
least-squares solution of the same samples. Goals: ``ours`` at >= 1,000
steps/s for 10,000 estimators on 2 CPU cores, >= 0.5x RLS, within 1e-4 (issue
14); with the full state out, >= 0.5x RLS and >= 2,000 steps/s on 2 cores
(issue 57).

    python benchmarks/estimator.py [--batch 10000] [--steps 50] [--reps 5] [--json out.json]
    XLA_FLAGS=--xla_force_host_platform_device_count=2 python benchmarks/estimator.py --shard   # both CPU cores
"""

from __future__ import annotations

import argparse
import statistics
import sys

import jax
import jax.numpy as jnp
import numpy as np
from emit import emit
from timing import first_call, interleaved, usable_cpus

import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)
from selfid_jax import baselines
from selfid_jax.identify import estimator as E
from selfid_jax.identify.step import sample_step
from selfid_jax.math import native

RF = sys.modules["selfid_jax.identify.refine"]
N, M = 6, 3
F32 = jnp.float32


def make_data(batch: int, steps: int, seed: int = 0):
    """``dtheta (steps, batch, n)``, ``V (steps, batch, m)`` float32 and the float64 least-squares solutions."""
    rng = np.random.default_rng(seed)
    U = np.linalg.qr(rng.normal(size=(batch, M, M)))[0]
    W = np.linalg.qr(rng.normal(size=(batch, N, N)))[0][:, :M]
    A = np.einsum("bij,j,bjk->bik", U, np.geomspace(1.0, 3.0, M), W)  # (batch, m, n), cond 3
    d = rng.uniform(-0.03, 0.03, (steps, batch, N))
    V = np.einsum("bmn,tbn->tbm", A, d) + 1e-4 * rng.normal(size=(steps, batch, M))
    return jnp.asarray(d, F32), jnp.asarray(V, F32), (d, V)


def lstsq_reference(d, V, count: int = 200):
    """float64 least squares ``(count, n, m)`` for the first ``count`` estimators of the float64 data."""
    return np.stack([np.linalg.lstsq(V[:, b], d[:, b], rcond=None)[0].T for b in range(count)])


def ours_step(state, dtheta, V):
    return sample_step(state, dtheta, V, 1e-3, 0.0, method="closed_form")[0]


def composed_step(state, dtheta, V):
    state = E.update(state, dtheta, V)
    J = RF.statistics_closed_form(state.S_vv, state.S_tv, E.initial_guess(state))
    return E.record(state, J, 1e-3)


def least_squares_step(state, dtheta, V):
    state = E.update(state, dtheta, V)
    return state._replace(estimate=RF.statistics_closed_form(state.S_vv, state.S_tv, jnp.zeros((N, M), F32)))


def buffered_step(state, dtheta, V):
    state = E.update(state, dtheta, V)
    theta, Vb, mask = E.samples(state)
    w = mask.astype(F32)[:, None]
    J = RF.closed_form(theta * w, Vb * w, E.initial_guess(state))
    return E.record(state, J, 1e-3)


RLS = baselines.rls(delta=1e-4)


def plain_rls_step(s, dtheta, V):
    """Five-line RLS on ``(J (n, m), P (m, m))``, no screen, no forgetting: the floor the full-state rows are timed
    against."""
    J, P = s
    Pv = P @ V
    k = Pv / (1.0 + V @ Pv)
    return J + (dtheta - J @ V)[:, None] * k[None, :], P - k[:, None] * Pv[None, :]


def rls_step(state, dtheta, V):
    state = RLS.update(state, dtheta, V)
    return state._replace(J=RLS.estimate(state, jnp.zeros((N, M), F32)))


def pure_jax(step):
    """``step`` traced with the native kernels off (:mod:`selfid_jax.math.native`): XLA code only."""

    def traced(*args):
        old = native.set_enabled(False)
        try:
            return step(*args)
        finally:
            native.set_enabled(old)

    return traced


def variants(batch):
    return {
        "rls": (lambda: RLS.init(N, M, dtype=F32), rls_step, lambda s: s.J),
        "ours": (lambda: E.init(N, M, capacity=0, dtype=F32), ours_step, lambda s: s.estimate),
        "ours, pure JAX": (lambda: E.init(N, M, capacity=0, dtype=F32), pure_jax(ours_step), lambda s: s.estimate),
        "ours, composed": (lambda: E.init(N, M, capacity=0, dtype=F32), composed_step, lambda s: s.estimate),
        "ours, least squares only": (lambda: E.init(N, M, capacity=0, dtype=F32), least_squares_step,
                                     lambda s: s.estimate),
        "ours, 64-sample buffer (before)": (lambda: E.init(N, M, capacity=64, dtype=F32), buffered_step,
                                            lambda s: s.estimate),
        # the whole final state out: nothing of the step is dead code for XLA to drop (the record's fields, the
        # counts); ratios against the five-line plain RLS with its whole state (J and P) out
        "plain RLS" + FULL: (lambda: (jnp.zeros((N, M), F32), 1e4 * jnp.eye(M, dtype=F32)), plain_rls_step,
                             lambda s: s),
        "rls" + FULL: (lambda: RLS.init(N, M, dtype=F32), rls_step, lambda s: s),
        "ours" + FULL: (lambda: E.init(N, M, capacity=0, dtype=F32), ours_step, lambda s: s),
        "ours, pure JAX" + FULL: (lambda: E.init(N, M, capacity=0, dtype=F32), pure_jax(ours_step), lambda s: s),
        "ours, composed" + FULL: (lambda: E.init(N, M, capacity=0, dtype=F32), composed_step, lambda s: s),
    }


FULL = ", full state out"


def scan_fn(batch, init, step, read, shard: bool = False):
    """``jit(run)``: ``run(d (T, batch, n), V (T, batch, m)) -> read(final state)``; ``shard``: batch split over
    devices."""
    n_dev = jax.device_count() if shard else 1
    vstep = jax.vmap(step)

    def run(d, V):
        s0 = jax.vmap(lambda _: init())(jnp.arange(batch // n_dev))
        s, _ = jax.lax.scan(lambda s, x: (vstep(s, *x), None), s0, (d, V))
        return read(s)

    if n_dev == 1:
        return jax.jit(run)
    from jax.sharding import Mesh
    from jax.sharding import PartitionSpec as P

    mesh = Mesh(np.asarray(jax.devices()), ("b",))
    return jax.jit(jax.shard_map(run, mesh=mesh, in_specs=(P(None, "b"), P(None, "b")), out_specs=P("b"),
                                 check_vma=False))


def run(batch: int = 10_000, steps: int = 50, reps: int = 5, rounds: int = 3, steps_before: int = 5,
        shard: bool = False) -> dict:
    """Time every variant; returns ``{"rows": {name: {...}}, ...}`` with medians in ms per step and steps/s.

    ``shard``: split the batch over ``jax.devices()`` (on CPU, start Python with
    ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` to use both cores).
    """
    d, V, (d64, V64) = make_data(batch, steps)
    ref = lstsq_reference(d64, V64, min(200, batch))
    fns, compile_s, errs = {}, {}, {}
    for name, (init, step, read) in variants(batch).items():
        if shard and "before" in name:
            continue
        T = steps_before if "before" in name else steps
        fn = scan_fn(batch, init, step, read, shard)
        out, compile_s[name] = first_call(fn, d[:T], V[:T])
        fns[name] = (fn, T)
        if T == steps:
            J = out if isinstance(out, jax.Array) else (out[0] if isinstance(out, tuple) and not hasattr(
                out, "_fields") else (out.J if hasattr(out, "J") else out.estimate))
            J = np.asarray(J[: len(ref)], np.float64)
            errs[name] = float(np.max(np.linalg.norm(J - ref, axis=(1, 2)) / np.linalg.norm(ref, axis=(1, 2))))
    times = interleaved({name: (lambda fn=fn, T=T: fn(d[:T], V[:T]), T) for name, (fn, T) in fns.items()},
                        reps, rounds)
    rows = {}
    for name, ts in times.items():
        per_step = statistics.median(ts)
        rls = statistics.median(times["plain RLS" + FULL if name.endswith(FULL) else "rls"])
        rows[name] = {
            "ms_per_step": 1e3 * per_step,
            "steps_per_s": 1.0 / per_step,
            "estimator_steps_per_s": batch / per_step,
            "ratio_to_rls": rls / per_step,
            "first_call_s": compile_s[name],
            "rel_err_vs_float64_lstsq": errs.get(name),
            "timed_steps": fns[name][1],
        }
    return {"batch": batch, "n": N, "m": M, "dtype": "float32", "steps": steps, "reps": reps * rounds,
            "device": f"{jax.device_count() if shard else 1} {jax.devices()[0].platform}", "rows": rows,
            "cpus_usable": usable_cpus(),
            "native": native.status()}


def report(res: dict) -> str:
    lines = [f"self-ID step, {res['batch']} vmapped estimators (n={res['n']}, m={res['m']}, {res['dtype']}), "
             f"median of {res['reps']} timings, {res['device']} device(s) on {res.get('cpus_usable')} usable CPUs, "
             f"native kernels {res['native']}",
             f"{'variant':34s} {'ms/step':>8s} {'steps/s':>8s} {'x RLS':>6s} {'est-steps/s':>12s} "
             f"{'1st call':>9s} {'err vs f64':>10s}"]
    for name, r in res["rows"].items():
        err = "-" if r["rel_err_vs_float64_lstsq"] is None else f"{r['rel_err_vs_float64_lstsq']:.1e}"
        lines.append(f"{name:34s} {r['ms_per_step']:8.3f} {r['steps_per_s']:8.0f} {r['ratio_to_rls']:6.2f} "
                     f"{r['estimator_steps_per_s']:12.3g} {r['first_call_s']:8.2f}s {err:>10s}")
    ours, full = res["rows"]["ours"], res["rows"]["ours" + FULL]

    def met(ok: bool) -> str:
        return "met" if ok else "not met"

    lines.append(f"goal (issue 14): ours >= 1000 steps/s ({met(ours['steps_per_s'] >= 1000)}), "
                 f">= 0.5x RLS ({met(ours['ratio_to_rls'] >= 0.5)}), "
                 f"error <= 1e-4 ({met(ours['rel_err_vs_float64_lstsq'] <= 1e-4)})")
    cpus, batch = res.get("cpus_usable"), res["batch"]
    where = "" if cpus == 2 else f"; this run on {cpus} usable CPUs"
    lines.append(f"goal (issue 57), 10,000 estimators, full state out: >= 0.5x plain RLS "
                 f"({met(full['ratio_to_rls'] >= 0.5 and batch >= 10_000)}), >= 2000 steps/s on 2 cores "
                 f"({met(full['steps_per_s'] >= 2000 and batch >= 10_000)}{where})")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--shard", action="store_true", help="split the batch over all JAX devices")
    ap.add_argument("--json", default=None, help="write the results here")
    args = ap.parse_args()
    res = run(args.batch, args.steps, args.reps, args.rounds, shard=args.shard)
    emit(res, report(res), args.json)


if __name__ == "__main__":
    main()
