"""Effect of the CPU XLA flags that ``import selfid_jax`` sets.

Runs the same batched workloads in fresh subprocesses, with the package's
default flags and with ``SELFID_JAX_NO_XLA_FLAGS=1`` (JAX's own defaults), and
prints compile and run times and their ratio. Workloads: ``self_identify`` on
a planar 3-link arm (nonlinear forward kinematics inside ``lax.scan``), 200
iterations, vmapped over a batch of keys; 200-step UR5e star rollouts
(``control.follow`` with the true inverse Jacobian) at the same batch; and one
batched UR5e pose through ``mjx.kinematics``.

The children start without the caller's ``XLA_FLAGS``, so that each arm runs
the flags it names. ``--extra FLAGS`` adds a third arm: the package's default
flags with ``FLAGS`` on top (a flag the user sets wins over the package's, so
``--extra=--xla_cpu_use_fusion_emitters=true`` tries that flag alone);
``--no-jax-defaults`` drops the JAX-defaults arm (its ``mjx.kinematics`` compile
takes minutes).

    python benchmarks/xla_flags.py [--batch 1000] [--iters 200] [--extra FLAGS] [--no-jax-defaults]
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


def measure(batch: int, iters: int, flags_on: bool, workload: str, extra: str = "") -> dict:
    """``{"compile_and_first", "run"}`` (s) of ``workload`` in a fresh process: the package's flags (``flags_on``)
    or JAX's defaults, with ``extra`` as that process's ``XLA_FLAGS``."""
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    if extra:
        env["XLA_FLAGS"] = extra
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
    ap.add_argument("--extra", default="", help="an arm with these XLA flags on top of the package's")
    ap.add_argument("--no-jax-defaults", action="store_true", help="skip the arm with JAX's own defaults")
    args = ap.parse_args()
    if args.batch < 1 or args.iters < 1:
        ap.error("--batch and --iters must be >= 1")
    if args.extra and not all(f.startswith("--xla_") for f in args.extra.split()):
        ap.error(f"--extra must be XLA flags (--xla_...), got {args.extra!r}")
    arms = [("selfid_jax defaults", True, "")]
    if args.extra:
        arms.append((f"+ {args.extra}", True, args.extra))
    if not args.no_jax_defaults:
        arms.append(("jax defaults", False, ""))
    print(f"batch {args.batch} x {args.iters} steps; compile+first run and steady run per workload")
    w = max(20, *(len(name) for name, _, _ in arms))
    print(f"{'workload':34s} {'XLA flags':{w}s} {'compile+first':>14s} {'run':>10s}")
    workloads = (("selfid", "self_identify, 3-link arm"), ("ur5e", "UR5e star rollouts"),
                 ("mjx", "UR5e mjx.kinematics pose (1 step)"))
    for workload, label in workloads:
        res = {name: measure(args.batch, args.iters, on, workload, extra) for name, on, extra in arms}
        base = res["selfid_jax defaults"]
        for i, (name, r) in enumerate(res.items()):
            print(f"{label if i == 0 else '':34s} {name:{w}s} {r['compile_and_first']:13.2f}s {r['run']:9.3f}s")
        for name, r in list(res.items())[1:]:
            print(f"{'':34s} {name}: run time {r['run'] / base['run']:.2f}x, compile+first "
                  f"{r['compile_and_first'] / base['compile_and_first']:.2f}x those of the package's defaults")


if __name__ == "__main__":
    main()
