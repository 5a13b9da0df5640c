"""Articulated-object rollouts per second: native MuJoCo (one host callback per batch) against MJX (compiled).

Builds the articulated experiment's parts for one object kind (``configs``-style
settings: 50 Hz control, 10 physics steps per control step, a seeded population
of ``--batch`` objects, the controller ``--controller``, the true arm Jacobian)
once per backend, and times ``jit(vmap(sim.rollout))`` over the population for
``--steps`` control steps: compile + first call, then the median of ``--reps``
calls. Prints rollouts per second, simulated seconds per wall second (all
rollouts together), the MJX / native ratio, and the largest difference of the
handle trajectories between the backends on the same rows (friction loss from
``--frictionloss``; the experiment's population draws 0.5-3 N).

    python benchmarks/articulated.py [--kind prismatic] [--batch 8] [--steps 100] [--skip-mjx] [--json out.json]

On a GPU, ``--batch 200 --steps 2000`` is the paper-scale population of one kind.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np
from emit import emit
from timing import time_call

import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)
from selfid_jax.articulated import sim
from selfid_jax.runner.execute import precision


def _part(backend: str, kind: str, batch: int, steps: int, controller: str, frictionloss, seed: int):
    from selfid_jax.experiments.articulated import ArticulatedConfig, build

    dt = 0.02
    cfg = ArticulatedConfig(backend=backend, objects={kind: batch}, controllers=[controller], arms=["true"],
                            control_dt=dt, substeps=10, max_time=steps * dt, trace_points=min(steps, 100),
                            population={"frictionloss": tuple(frictionloss)}, seed=seed)
    (part,) = build(cfg)
    return part, cfg


def measure(backend: str, kind: str, batch: int, steps: int, controller: str, frictionloss, reps: int,
            seed: int = 0) -> dict:
    """Compile + first call and the median steady call of one backend; returns timings and the result."""
    with precision(True):
        part, cfg = _part(backend, kind, batch, steps, controller, frictionloss, seed)
        st = part.static.sim
        fn = jax.jit(jax.vmap(lambda p: sim.rollout(st, p)))
        params = jax.tree.map(np.asarray, part.params.rollout)
        res, first, run, _ = time_call(fn, params, reps=reps)
    sim_s = batch * steps * cfg.control_dt
    return {"backend": backend, "first_call_s": first, "run_s": run, "rollouts_per_s": batch / run,
            "sim_s_per_wall_s": sim_s / run, "progress_mean": float(np.mean(np.asarray(res.progress))),
            "handle_trace": np.asarray(res.handle_trace)}


def run(kind="prismatic", batch=8, steps=100, controller="turbo_u0", frictionloss=(0.5, 3.0), reps=3,
        skip_mjx=False) -> dict:
    rows = {"native": measure("native", kind, batch, steps, controller, frictionloss, reps)}
    if not skip_mjx:
        rows["mjx"] = measure("mjx", kind, batch, steps, controller, frictionloss, reps)
    out = {"kind": kind, "batch": batch, "steps": steps, "controller": controller,
           "frictionloss": list(frictionloss), "device": jax.devices()[0].platform, "rows": {}}
    for name, r in rows.items():
        out["rows"][name] = {k: v for k, v in r.items() if k != "handle_trace"}
    if "mjx" in rows:
        diff = np.abs(rows["mjx"]["handle_trace"] - rows["native"]["handle_trace"])
        out["max_handle_diff_m"] = float(diff.max())
        out["mjx_vs_native"] = rows["mjx"]["rollouts_per_s"] / rows["native"]["rollouts_per_s"]
    return out


def report(res: dict) -> str:
    lines = [f"articulated rollouts: {res['batch']} {res['kind']} objects x {res['steps']} control steps "
             f"(x 10 physics steps), {res['controller']}, friction loss {res['frictionloss']} N, {res['device']}",
             f"{'backend':8s} {'1st call':>9s} {'per call':>9s} {'rollouts/s':>11s} {'sim s/wall s':>13s} "
             f"{'progress':>9s}"]
    for name, r in res["rows"].items():
        lines.append(f"{name:8s} {r['first_call_s']:8.1f}s {r['run_s']:8.2f}s {r['rollouts_per_s']:11.2f} "
                     f"{r['sim_s_per_wall_s']:13.1f} {r['progress_mean']:9.3f}")
    if "mjx_vs_native" in res:
        lines.append(f"MJX / native: {res['mjx_vs_native']:.2f}x rollouts/s; largest handle-position difference "
                     f"{1e3 * res['max_handle_diff_m']:.3g} mm")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", default="prismatic", choices=("prismatic", "revolute", "helical", "bezier"))
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--controller", default="turbo_u0")
    ap.add_argument("--frictionloss", type=float, nargs=2, default=(0.5, 3.0), metavar=("LO", "HI"))
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--skip-mjx", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    res = run(args.kind, args.batch, args.steps, args.controller, args.frictionloss, args.reps, args.skip_mjx)
    emit(res, report(res), args.json)


if __name__ == "__main__":
    main()
