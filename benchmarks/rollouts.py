"""Per-rollout time of 200-step star-path rollouts on the UR5e (position task, true inverse Jacobian).

Prints, in one run: the batched JAX controller (``jit(vmap(control.follow))``)
at batch 1,000 and 10,000 (compile time separate), a straightforward numpy
loop of the same controller on DH kinematics (``tests/numpy_reference.py``),
and a loop over MuJoCo's C bindings (``mj_kinematics`` + ``mj_comPos`` +
``mj_jacSite`` each step), with the ratios against the numpy loop.

    python benchmarks/rollouts.py [--batches 1000 10000] [--loops 100]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)
from selfid_jax import control
from selfid_jax.control import paths
from selfid_jax.systems import ur5e
from selfid_jax.systems.ur5e import UR5E_XML

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import numpy_reference as ref
from timing import time_call

STEPS = 200
CTRL = dict(max_step=0.0025, tol=0.0005)


def mujoco_c_loop(q0s, path, system):
    """The same controller with MuJoCo's C kinematics and site Jacobian each step."""
    model = mujoco.MjModel.from_xml_path(UR5E_XML)
    data = mujoco.MjData(model)
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "ee")
    jacp = np.zeros((3, model.nv))

    def position(q):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        return data.site_xpos[site].copy()

    def jinv(q):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        mujoco.mj_jacSite(model, data, jacp, None, site)
        return ref.right_inverse(jacp)

    lim = dict(dq_max=np.asarray(system.dq_max), q_low=np.asarray(system.q_low), q_high=np.asarray(system.q_high))
    return [ref.follow(position, jinv, path, q, steps=STEPS, **CTRL, **lim)[0] for q in q0s]


def numpy_loop(q0s, path, system):
    lim = dict(dq_max=np.asarray(system.dq_max), q_low=np.asarray(system.q_low), q_high=np.asarray(system.q_high))
    jinv = lambda q: ref.right_inverse(ref.ur5e_position_jacobian(q))
    return [ref.follow(ref.ur5e_position, jinv, path, q, steps=STEPS, **CTRL, **lim)[0] for q in q0s]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1000, 10_000])
    ap.add_argument("--loops", type=int, default=100, help="rollouts for the numpy and MuJoCo C loops")
    ap.add_argument("--json", default=None, help="write the rows here")
    args = ap.parse_args()

    system = ur5e(task_dim=3)
    path = paths.star(size=0.05, dim=3)
    fn = jax.jit(jax.vmap(lambda q: control.follow(system, control.true_inverse(system), path, q,
                                                   control.ControllerParams(**CTRL), steps=STEPS).completion))
    rows = []
    for batch in args.batches:
        q0s = system.sample_configs(jax.random.key(batch), batch)
        comp, first, run, _ = time_call(fn, q0s, reps=1)  # one call after the first (same result: deterministic)
        rows.append((f"JAX jit(vmap), batch {batch}", run / batch, first - run, float(jnp.mean(comp))))

    q0s = np.asarray(system.sample_configs(jax.random.key(0), args.loops), float)
    path_np = np.asarray(path, float)
    t0 = time.perf_counter()
    comp = numpy_loop(q0s, path_np, system)
    t_np = (time.perf_counter() - t0) / args.loops
    rows.append((f"numpy loop, {args.loops} rollouts", t_np, 0.0, float(np.mean(comp))))
    t0 = time.perf_counter()
    comp = mujoco_c_loop(q0s, path_np, system)
    t_c = (time.perf_counter() - t0) / args.loops
    rows.append((f"MuJoCo C loop, {args.loops} rollouts", t_c, 0.0, float(np.mean(comp))))

    dtype = jnp.zeros(()).dtype
    print(f"UR5e star-path rollouts, {STEPS} steps, true inverse Jacobian ({dtype}, {jax.devices()[0].platform})")
    print(f"{'implementation':32s} {'per rollout':>13s} {'compile':>9s} {'vs numpy':>9s} {'completion':>11s}")
    for name, per, comp_s, completion in rows:
        compile_txt = f"{comp_s:8.2f}s" if comp_s else f"{'-':>9s}"
        print(f"{name:32s} {per * 1e3:10.4f} ms {compile_txt} {t_np / per:8.1f}x {completion:11.3f}")
    print("goals: batched JAX >= 100x faster per rollout than the numpy loop; <= 0.1 ms per rollout at batch 10k")
    if args.json:
        import json

        out = {name: {"ms_per_rollout": per * 1e3, "compile_s": comp_s, "vs_numpy": t_np / per,
                      "completion": completion} for name, per, comp_s, completion in rows}
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
