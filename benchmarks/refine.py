"""Refinement speed and accuracy: scipy SLSQP (the paper's optimizer) vs batched JAX.

Problems: 6 actuators x 6 task dims, K=20 noisy samples of a random linear
system each. Prints per-problem wall time of SLSQP with numeric and with
analytic gradient (a loop of ``scipy.optimize.minimize`` on numpy arrays, no
JAX in the loop), of ``refine(method="optax")`` and
``refine(method="closed_form")`` vmapped over 10,000 problems (compile time
reported separately), the speed ratios, and the worst relative objective
difference against SLSQP. float64 throughout (SLSQP runs in float64).

    python benchmarks/refine.py [--batch 10000] [--slsqp 50]
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from timing import time_call  # noqa: E402

import selfid_jax as sj  # noqa: E402
from selfid_jax.identify import estimator as E  # noqa: E402
from selfid_jax.identify.refine import slsqp_refine  # noqa: E402

N = M = 6
K = 20


def make_problems(key, batch):
    """Batched estimator states, each holding K noisy samples of its own random 6x6 system."""
    kJ, kd, kn = jax.random.split(key, 3)
    J = jax.random.normal(kJ, (batch, M, N))
    d = jax.random.uniform(kd, (batch, K, N), minval=-0.05, maxval=0.05)
    V = jnp.einsum("bmn,bkn->bkm", J, d) + 1e-3 * jax.random.normal(kn, (batch, K, M))

    def fold(d, V):
        def body(s, x):
            return E.update(s, *x), None

        return jax.lax.scan(body, E.init(N, M, capacity=K), (d, V))[0]

    return jax.jit(jax.vmap(fold))(d, V)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=10_000)
    ap.add_argument("--slsqp", type=int, default=50, help="problems solved by SLSQP per gradient mode")
    ap.add_argument("--steps", type=int, default=100, help="optax refinement steps")
    ap.add_argument("--json", default=None, help="write the rows here")
    args = ap.parse_args()
    rows = {}

    states = make_problems(jax.random.key(0), args.batch)
    J0 = jax.jit(jax.vmap(sj.initial_guess))(states)
    theta_np, V_np, J0_np = (np.asarray(x) for x in (states.dtheta_buf, states.v_buf, J0))

    slsqp_time = {}
    slsqp_sol = {}
    for numeric in (True, False):
        sols = []
        t0 = time.perf_counter()
        for i in range(args.slsqp):
            sols.append(slsqp_refine(theta_np[i], V_np[i], J0_np[i], numeric_grad=numeric))
        slsqp_time[numeric] = (time.perf_counter() - t0) / args.slsqp
        slsqp_sol[numeric] = np.stack(sols)

    results = {}
    for method in ("optax", "closed_form"):
        fn = jax.jit(jax.vmap(lambda s, j, method=method: sj.refine(s, j, method=method, steps=args.steps)))
        out, t_first, t_run, _ = time_call(fn, states, J0, reps=1)  # one call after the first
        results[method] = (out, t_run / args.batch, t_first - t_run)

    obj = jax.jit(jax.vmap(E.objective))
    sub = jax.tree.map(lambda x: x[: args.slsqp], states)
    f_ref = np.asarray(obj(sub, jnp.asarray(slsqp_sol[False])))

    print(f"refinement of {N}x{M} inverse Jacobians from K={K} noisy samples (float64, {jax.devices()[0].platform})")
    print(f"{'method':34s} {'per problem':>14s} {'compile':>9s} {'vs SLSQP analytic':>18s} {'worst rel obj diff':>19s}")
    for numeric in (True, False):
        name = "scipy SLSQP, " + ("numeric grad" if numeric else "analytic grad")
        f = np.asarray(obj(sub, jnp.asarray(slsqp_sol[numeric])))
        gap = np.max(np.abs(f - f_ref) / f_ref)
        ratio = slsqp_time[False] / slsqp_time[numeric]
        print(f"{name:34s} {slsqp_time[numeric] * 1e3:11.3f} ms {'-':>9s} {ratio:17.2f}x {gap:19.2e}")
        rows[name] = {"ms_per_problem": slsqp_time[numeric] * 1e3, "vs_slsqp_analytic": ratio, "rel_obj_diff": gap}
    for method, (out, per, compile_s) in results.items():
        f = np.asarray(obj(sub, out[: args.slsqp]))
        gap = np.max(np.abs(f - f_ref) / f_ref)
        label = f"jax {method} (vmap {args.batch})" + (f", {args.steps} steps" if method == "optax" else "")
        print(f"{label:34s} {per * 1e3:11.4f} ms {compile_s:8.2f}s {slsqp_time[False] / per:17.1f}x {gap:19.2e}")
        rows[method] = {"ms_per_problem": per * 1e3, "compile_s": compile_s,
                        "vs_slsqp_analytic": slsqp_time[False] / per, "rel_obj_diff": float(gap)}
    print("goals: optax >= 10x and closed_form >= 100x faster than SLSQP (analytic grad), rel obj diff <= 1e-6")
    if args.json:
        import json

        with open(args.json, "w") as f:
            json.dump({"batch": args.batch, "rows": rows}, f, indent=2, default=float)


if __name__ == "__main__":
    main()
