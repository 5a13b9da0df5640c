"""SOGP update throughput: 1,000 vmapped estimators at capacity M = 10, 30, 100, in one run.

Each estimator is a Csato-Opper SOGP (selfid_jax.baselines.sogp) of the E-KM's
incremental 2-link input (4-D ``[q, da]``, 2-D output) folding a stream of T
random samples inside ``lax.scan``; one ``jit(vmap(scan))`` per M, timed after
its compile (reported separately). Baselines in the same process: the RLS
estimator (selfid_jax.baselines.rls, 2x2) under the same jit(vmap(scan)), and
one SOGP update called from a Python loop (jitted, one estimator per call).
float64 throughout (the SOGP needs it).

    python benchmarks/sogp.py [--batch 1000] [--steps 50] [--capacities 10 30 100]
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
from timing import time_call  # noqa: E402

from selfid_jax import baselines  # noqa: E402
from selfid_jax.baselines import sogp  # noqa: E402

D, P = 4, 2


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=50, help="samples per estimator (scan length)")
    ap.add_argument("--capacities", type=int, nargs="+", default=[10, 30, 100])
    ap.add_argument("--loop", type=int, default=200, help="Python-loop calls timed")
    args = ap.parse_args()
    B, T = args.batch, args.steps
    key = jax.random.key(0)
    X = jax.random.uniform(key, (B, T, D), minval=-1.0, maxval=1.0)
    Y = jnp.stack([jnp.sin(X[..., 0] + X[..., 2]), jnp.cos(X[..., 1]) * X[..., 3]], axis=-1)
    print(f"{jax.devices()[0].platform}: {B} estimators x {T} updates, input {D}-D, output {P}-D, float64")
    ups = {}
    for M in args.capacities:
        def run(X, Y, M=M):
            state = sogp.init(D, P, capacity=M, kernel=sogp.RBF(0.5, 1.0), noise=1e-2, novelty_tol=1e-4)
            return jax.lax.scan(lambda s, xy: (sogp.update(s, *xy), None), state, (X, Y))[0]

        state, first, best, _ = time_call(jax.jit(jax.vmap(run)), X, Y, reps=3, stat=min)
        ups[M] = B * T / best
        print(f"SOGP M={M:4d}: {ups[M]:12,.0f} updates/s ({1e6 / ups[M]:.2f} us per estimator-update; "
              f"compile+first {first:.1f} s); basis size mean {float(jnp.mean(sogp.size(state))):.1f}, "
              f"unstable {int(jnp.sum(state.unstable))}")

    d = X[..., :2] * 0.05
    V = jnp.einsum("ij,btj->bti", jnp.array([[1.0, 0.3], [-0.2, 0.8]]), d)
    rls = baselines.rls(lam=0.99)

    def run_rls(d, V):
        return baselines.scan(rls, rls.init(2, 2), d, V, jnp.zeros((2, 2)))[0]

    _, first, best, _ = time_call(jax.jit(jax.vmap(run_rls)), d, V, reps=3, stat=min)
    rls_ups = B * T / best
    print(f"RLS (2x2)  : {rls_ups:12,.0f} updates/s ({1e6 / rls_ups:.2f} us per estimator-update)")

    one = jax.jit(sogp.update)
    st = sogp.init(D, P, capacity=30, kernel=sogp.RBF(0.5, 1.0), noise=1e-2)
    st = jax.block_until_ready(one(st, X[0, 0], Y[0, 0]))
    t0 = time.perf_counter()
    for i in range(args.loop):
        st = one(st, X[0, i % T], Y[0, i % T])
    jax.block_until_ready(st)
    loop_us = 1e6 * (time.perf_counter() - t0) / args.loop
    print(f"SOGP M=30 one jitted update per Python call: {loop_us:.0f} us per update")
    for M, u in ups.items():
        print(f"ratio M={M:4d}: {u / rls_ups:.3f} x RLS throughput; {loop_us * u / 1e6:,.0f} x the Python loop")


if __name__ == "__main__":
    main()
