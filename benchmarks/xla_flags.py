"""Effect of the CPU XLA flags that ``import selfid_jax`` sets.

Runs the same batched workloads in fresh subprocesses, with the package's
default flags and with ``SELFID_JAX_NO_XLA_FLAGS=1`` (JAX's own defaults), and
prints compile and run times and their ratio. Workloads: ``self_identify`` on
a planar 3-link arm (nonlinear forward kinematics inside ``lax.scan``), 200
iterations, vmapped over a batch of keys; 200-step UR5e star rollouts
(``control.follow`` with the true inverse Jacobian) at the same batch; and one
batched UR5e pose through ``mjx.kinematics``.

    python benchmarks/xla_flags.py [--batch 1000] [--iters 200]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, sys
import selfid_jax as sj
import jax, jax.numpy as jnp

batch, iters = int(sys.argv[1]), int(sys.argv[2])

def fk(q):
    a = jnp.cumsum(q)
    return jnp.stack([jnp.sum(jnp.cos(a)), jnp.sum(jnp.sin(a))])

def observe(q, key, d):
    q_new = q + d
    return q_new, fk(q_new) - fk(q)

def one(key):
    return sj.self_identify(observe, key, 0.05, 1e-4, n_act=3, task_dim=2, iters=iters,
                            env=jnp.array([0.3, 0.9, -0.6]), capacity=20, stop_at_convergence=False).estimate

if sys.argv[3] == "ur5e":
    from selfid_jax import control
    from selfid_jax.control import paths
    arm = sj.ur5e(task_dim=3)
    star = paths.star(size=0.05)
    fn = jax.jit(jax.vmap(lambda q: control.follow(arm, control.true_inverse(arm), star, q,
                                                   control.ControllerParams(max_step=0.0025, tol=0.0005),
                                                   steps=iters).completion))
    keys = arm.sample_configs(jax.random.key(0), batch)
elif sys.argv[3] == "mjx":
    arm = sj.ur5e(task_dim=3, fk="mjx")
    fn = jax.jit(jax.vmap(lambda q: arm.pose(q)[0]))
    keys = arm.sample_configs(jax.random.key(0), batch)
else:
    fn = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.key(0), batch)
sys.path.insert(0, sys.argv[4])
from timing import time_call
t = time_call(fn, keys, reps=3, stat=min)
print(json.dumps({"compile_and_first": t.first_s, "run": t.run_s}))
"""


def measure(batch: int, iters: int, flags_on: bool, workload: str) -> dict:
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    if not flags_on:
        env["SELFID_JAX_NO_XLA_FLAGS"] = "1"
    out = subprocess.run([sys.executable, "-c", CHILD, str(batch), str(iters), workload,
                          str(Path(__file__).resolve().parent)], env=env, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--iters", type=int, default=200)
    args = ap.parse_args()
    print(f"batch {args.batch} x {args.iters} steps; compile+first run and steady run per workload")
    print(f"{'workload':34s} {'XLA flags':20s} {'compile+first':>14s} {'run':>10s}")
    workloads = (("selfid", "self_identify, 3-link arm"), ("ur5e", "UR5e star rollouts"),
                 ("mjx", "UR5e mjx.kinematics pose (1 step)"))
    for workload, label in workloads:
        on = measure(args.batch, args.iters, True, workload)
        off = measure(args.batch, args.iters, False, workload)
        print(f"{label:34s} {'selfid_jax defaults':20s} {on['compile_and_first']:13.2f}s {on['run']:9.3f}s")
        print(f"{'':34s} {'jax defaults':20s} {off['compile_and_first']:13.2f}s {off['run']:9.3f}s")
        print(f"{'':34s} run speed-up from the flags: {off['run'] / on['run']:.2f}x, compile+first: "
              f"{off['compile_and_first'] / on['compile_and_first']:.2f}x")


if __name__ == "__main__":
    main()
