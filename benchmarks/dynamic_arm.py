"""Dynamic UR5e control steps/s: MJX (``DynamicArm``, compiled, batched) against native MuJoCo; its step response.

Speed: for each batch size, ``--batch`` arms start at random configurations of
the UR5e's sampling box and follow step-and-hold targets (a new random target
within +-0.05 rad every 25 control steps) for ``--steps`` control steps of
``--substeps`` physics steps (0.02 s at the default 10). MJX:
``jit(vmap(arm.rollout))`` in float64, each step returning ``q`` and the
flange pose (the control loop's ``step_fn``); compile + first call, then the
median of ``--reps`` calls. Native, in the same process on the same rows:
``mujoco.rollout`` with ``--nthread`` threads (states only, no site pose) and,
at batch 1, a plain Python ``mj_step`` loop with ``mj_kinematics`` per control
step (what a host-side loop would do). Prints control steps/s, the MJX /
native ratios and the largest ``|q_mjx - q_native|``.

Step response (MJX, gravity compensated, 1 physics step per control step so
times resolve to 2 ms): a 0.05 rad step on one joint at a time from
``UR5E_HOME`` at rest, shipped gains (kp 500, kv 50) and kv 10: 10-90 % rise
time, overshoot, 2 % settling time, the fraction of the step covered after one
0.02 s control period (the kinematic backend covers all of it), and the
gravity sag of the shipped model held at home without compensation.

    python benchmarks/dynamic_arm.py [--batches 1 64 256] [--steps 50] [--nthread 1] [--json out.json]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from emit import emit
from mujoco import rollout as mj_rollout
from timing import time_call

import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)
from selfid_jax.systems.dynamic import dynamic_ur5e
from selfid_jax.systems.ur5e import _SAMPLE_HIGH, _SAMPLE_LOW, UR5E_HOME, UR5E_XML

HOLD = 25  # control steps per target


def _rows(batch: int, steps: int, seed: int):
    """``q0 (B, 6)``, ``targets (B, steps, 6)``: random starts and step-and-hold targets around them."""
    rng = np.random.default_rng(seed)
    q0 = rng.uniform(_SAMPLE_LOW, _SAMPLE_HIGH, (batch, 6))
    n_hold = -(-steps // HOLD)
    jumps = rng.uniform(-0.05, 0.05, (batch, n_hold, 6))
    targets = q0[:, None, :] + np.repeat(jumps, HOLD, axis=1)[:, :steps]
    return q0, targets


def native_rollout(m, q0, targets, substeps: int, nthread: int, pool):
    """``mujoco.rollout`` of every row: ``q (B, steps, 6)`` after each control step."""
    B, steps, _ = targets.shape
    datas = [mujoco.MjData(m) for _ in range(nthread)]
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    s0 = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, datas[0], s0, spec)
    state0 = np.tile(s0, (B, 1))
    state0[:, 1:1 + m.nq] = q0  # FULLPHYSICS = time, qpos, qvel, ...
    control = np.repeat(targets, substeps, axis=1)  # (B, steps * substeps, nu)
    st, _ = pool.rollout(m, datas, state0, control)
    return st[:, substeps - 1::substeps, 1:1 + m.nq]


def native_loop(m, q0, targets, substeps: int):
    """Plain ``mj_step`` loop, one row, with ``mj_kinematics`` per control step (site pose read)."""
    d = mujoco.MjData(m)
    d.qpos[:] = q0
    qs = np.empty((targets.shape[0], m.nq))
    for k, u in enumerate(targets):
        d.ctrl[:] = u
        for _ in range(substeps):
            mujoco.mj_step(m, d)
        mujoco.mj_kinematics(m, d)
        qs[k] = d.qpos
    return qs


def speed(batches, steps: int, substeps: int, nthread: int, reps: int, seed: int) -> list[dict]:
    arm = dynamic_ur5e(gravcomp=1.0)
    m = mujoco.MjModel.from_xml_path(UR5E_XML)
    m.body_gravcomp[1:] = 1.0
    m.flg_gravcomp = 1

    def roll(q0, u):
        _, tr = arm.rollout(arm.init(q0), u, substeps=substeps)
        return tr.q, tr.p, tr.R

    fn = jax.jit(jax.vmap(roll))
    rows = []
    with mj_rollout.Rollout(nthread=nthread) as pool:
        for B in batches:
            q0, targets = _rows(B, steps, seed)
            q0_j, u_j = jnp.asarray(q0), jnp.asarray(targets)
            (q_mjx, _, _), first, run, _ = time_call(fn, q0_j, u_j, reps=reps)
            q_nat, _, run_nat, _ = time_call(native_rollout, m, q0, targets, substeps, nthread, pool, reps=reps)
            row = {"batch": B, "mjx_first_call_s": first, "mjx_run_s": run, "mjx_steps_per_s": B * steps / run,
                   "native_rollout_steps_per_s": B * steps / run_nat,
                   "max_q_diff_rad": float(np.abs(np.asarray(q_mjx) - q_nat).max())}
            row["mjx_vs_rollout"] = row["mjx_steps_per_s"] / row["native_rollout_steps_per_s"]
            if B == 1:
                run_loop = time_call(native_loop, m, q0[0], targets[0], substeps, reps=reps).run_s
                row["native_loop_steps_per_s"] = steps / run_loop
                row["mjx_vs_loop"] = row["mjx_steps_per_s"] / row["native_loop_steps_per_s"]
            rows.append(row)
    return rows


def step_response(step: float = 0.05, duration: float = 1.0) -> dict:
    """Per joint and damping, the response to a ``step`` rad command from home (gravity compensated), by MJX."""
    arm = dynamic_ur5e(gravcomp=1.0)
    q0 = np.asarray(UR5E_HOME)
    T = int(round(duration / arm.timestep))
    kvs = (50.0, 10.0)
    jumps = np.repeat(np.eye(6)[None] * step, len(kvs), axis=0).reshape(-1, 6)  # (len(kvs) * 6, 6)
    kv = np.repeat(kvs, 6)

    def one(kv_i, jump):
        a = arm.with_servo(kv=kv_i)
        _, tr = a.rollout(a.init(jnp.asarray(q0)), jnp.tile(jnp.asarray(q0) + jump, (T, 1)), substeps=1)
        return tr.q

    q = np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(kv), jnp.asarray(jumps)))  # (rows, T, 6)
    t = np.arange(1, T + 1) * arm.timestep
    per_period = int(round(0.02 / arm.timestep))
    out: dict = {"step_rad": step, "period_s": 0.02, "rows": []}
    for r in range(len(kv)):
        j = r % 6
        frac = (q[r, :, j] - q0[j]) / step
        final = frac[-1]
        rise = t[np.argmax(frac >= 0.9 * final)] - t[np.argmax(frac >= 0.1 * final)]
        outside = np.nonzero(np.abs(frac - final) > 0.02 * abs(final))[0]
        settle = t[outside[-1] + 1] if outside.size and outside[-1] + 1 < T else (0.0 if not outside.size else np.inf)
        out["rows"].append({"kv": float(kv[r]), "joint": j + 1, "final": float(final), "rise_10_90_s": float(rise),
                            "overshoot_pct": float(100 * max(frac.max() / final - 1, 0.0)),
                            "settle_2pct_s": float(settle), "after_one_period": float(frac[per_period - 1])})
    # the shipped model's sag, held at home without gravity compensation (native, settled 10 s)
    m = mujoco.MjModel.from_xml_path(UR5E_XML)
    d = mujoco.MjData(m)
    d.qpos[:] = d.ctrl[:] = q0
    for _ in range(5000):
        mujoco.mj_step(m, d)
    sag = d.qpos - q0
    mujoco.mj_kinematics(m, d)
    p_sag = d.site_xpos[0].copy()
    d.qpos[:] = q0
    mujoco.mj_kinematics(m, d)
    out["sag_rad"] = sag.tolist()
    out["sag_flange_m"] = float(np.linalg.norm(p_sag - d.site_xpos[0]))
    return out


def report(res: dict) -> str:
    lines = [f"dynamic UR5e (MJX DynamicArm, float64, gravity compensated): {res['steps']} control steps x "
             f"{res['substeps']} physics steps, native mujoco.rollout nthread={res['nthread']}, {res['device']}",
             f"{'batch':>6s} {'MJX 1st':>8s} {'MJX steps/s':>12s} {'rollout/s':>10s} {'MJX/rollout':>12s} "
             f"{'loop/s':>8s} {'MJX/loop':>9s} {'max|dq|':>9s}"]
    for r in res["speed"]:
        loop = f"{r['native_loop_steps_per_s']:8.0f} {r['mjx_vs_loop']:9.3f}" if "native_loop_steps_per_s" in r else \
            f"{'':8s} {'':9s}"
        lines.append(f"{r['batch']:6d} {r['mjx_first_call_s']:7.1f}s {r['mjx_steps_per_s']:12.0f} "
                     f"{r['native_rollout_steps_per_s']:10.0f} {r['mjx_vs_rollout']:12.3f} {loop} "
                     f"{r['max_q_diff_rad']:9.1e}")
    if "step_response" in res:
        sr = res["step_response"]
        lines.append(f"step response, {sr['step_rad']} rad on one joint from home (gravity compensated, MJX): "
                     "rise 10-90 %, overshoot, settling to 2 %, fraction covered after one 0.02 s period")
        for r in sr["rows"]:
            lines.append(f"  kv {r['kv']:4.0f} joint {r['joint']}: rise {1e3 * r['rise_10_90_s']:5.0f} ms, "
                         f"overshoot {r['overshoot_pct']:5.1f} %, settle {1e3 * r['settle_2pct_s']:5.0f} ms, "
                         f"after one period {r['after_one_period']:.3f}")
        lines.append("sag of the shipped model held at home without compensation: "
                     + ", ".join(f"{s:+.4f}" for s in sr["sag_rad"]) + f" rad, {1e2 * sr['sag_flange_m']:.1f} cm "
                     "at the flange")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 256])
    ap.add_argument("--steps", type=int, default=50, help="control steps per rollout")
    ap.add_argument("--substeps", type=int, default=10, help="physics steps per control step")
    ap.add_argument("--nthread", type=int, default=1, help="threads of native mujoco.rollout")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-step-response", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)  # MuJoCo parity
    res = {"steps": args.steps, "substeps": args.substeps, "nthread": args.nthread,
           "device": jax.devices()[0].platform,
           "speed": speed(args.batches, args.steps, args.substeps, args.nthread, args.reps, args.seed)}
    if not args.skip_step_response:
        res["step_response"] = step_response()
    emit(res, report(res), args.json)


if __name__ == "__main__":
    main()
