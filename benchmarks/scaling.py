"""How cost grows with the work: throughput and memory of the self-ID step and the UR5e rollout against batch size,
and of the step against the problem size ``n`` x ``m``, in one run.

Rows:

* **estimator step vs batch** (n = 6, m = 3, float32): one full self-ID step per
  estimator (``update``, ``initial_guess``, the closed-form refinement, the
  Sec. IV-D ``record``: what Algorithm 1 does per sample), ``vmap`` over the
  batch inside a ``lax.scan`` over ``--steps`` samples, at batch 1, 10, 100,
  1k, 10k, 100k and 1M;
* **UR5e rollout vs batch**: ``jit(vmap(control.follow))`` of the 5 cm star
  with the true inverse Jacobian (435 steps) at batch 1 ... 100k;
* **estimator step vs n x m** at batch 10k: n in {3, 6, 9, 16}, m in {3, 6}.

Each row prints the run time per call (median of ``--reps`` after a warm-up;
compile time separate), the throughput (estimator-steps or rollouts per
second), the peak memory of the compiled program (XLA's own
``memory_analysis``: arguments + outputs + temporaries, less the outputs
aliased to donated arguments; the estimator's program with its state
donated, as a fleet runs it, so that the new state overwrites the old) per
batch element, and for the estimator the state's own size per estimator (the
bytes of its pytree's leaves), the goal being a peak within 2x of it; and the
same ratio for the rank-one step of :mod:`selfid_jax.identify.recursive`
(per sample and blocked) at batch 10k. "Stops
paying": the smallest batch whose throughput no larger batch beats by 20 % or
more.

    python benchmarks/scaling.py [--quick] [--json out.json] [--figure scaling.png]

``--quick`` stops at batch 10k (CI-sized); the full run takes a few minutes on
2 cores, most of it compiling one program per shape.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from emit import emit
from estimator import ours_step  # the full self-ID step the estimator benchmark times
from timing import time_call

import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)
from selfid_jax import control
from selfid_jax.control import paths
from selfid_jax.identify import estimator as E
from selfid_jax.systems.ur5e import ur5e

F32 = jnp.float32
PAYS = 1.2  # a 10x larger batch must raise the throughput by at least this factor to pay


def _peak_bytes(jitted, *args) -> int | None:
    """Arguments + outputs + temporaries, less the outputs aliased to donated arguments, of the compiled program
    [bytes] (None where XLA reports nothing)."""
    try:
        mem = jitted.lower(*args).compile().memory_analysis()
    except Exception:  # noqa: BLE001  (a backend without the analysis)
        return None
    if mem is None:
        return None
    return int(mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes
               - mem.alias_size_in_bytes)


def estimator_row(batch: int, n: int, m: int, steps: int, reps: int) -> dict:
    """One estimator shape: ``steps`` full self-ID steps for ``batch`` vmapped estimators."""
    rng = np.random.default_rng(batch + 100 * n + m)
    A = jnp.asarray(rng.normal(size=(m, n)), F32)
    d = jnp.asarray(rng.uniform(-0.03, 0.03, (steps, batch, n)), F32)
    V = jnp.einsum("mn,tbn->tbm", A, d) + 1e-4 * jnp.asarray(rng.normal(size=(steps, batch, m)), F32)
    one = E.init(n, m, capacity=0, dtype=F32)  # no sample buffer: the closed form reads the statistics
    state0 = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + jnp.shape(x)), one)
    state_bytes = sum(np.dtype(x.dtype).itemsize * int(np.prod(np.shape(x))) for x in jax.tree.leaves(one))

    def run(state, d, V):
        def body(s, x):
            return jax.vmap(ours_step)(s, *x), None

        return jax.lax.scan(body, state, (d, V))[0]

    jitted = jax.jit(run)
    _, first, t, _ = time_call(jitted, state0, d, V, reps=reps)
    # the memory of the program a fleet runs: its state donated, so that XLA writes the new state over the old
    # (timed without donation, which would consume state0 at the first call; the step is the same)
    peak = _peak_bytes(jax.jit(run, donate_argnums=0), state0, d, V)
    data_bytes = 4 * steps * (n + m)  # per estimator: its samples, an argument of the benchmark, not of the step
    return dict(what="estimator", batch=batch, n=n, m=m, steps=steps, compile_s=first - t, run_s=t,
                per_s=batch * steps / t, state_bytes=state_bytes,
                peak_bytes_per=None if peak is None else peak / batch,
                peak_bytes_per_less_data=None if peak is None else peak / batch - data_bytes)


def recursive_memory(batch: int, steps: int) -> dict:
    """Peak per estimator (less its samples) over the state's size, donated, of ``steps`` samples of the rank-one
    self-ID step (:mod:`selfid_jax.identify.recursive`): ``step`` per sample and the blocked ``run``."""
    from selfid_jax.identify import recursive as R

    n, m = 6, 3
    grow = lambda x: jnp.broadcast_to(x, (batch,) + jnp.shape(x))
    s0 = jax.tree.map(grow, E.init(n, m, capacity=0, dtype=F32))
    r0 = jax.tree.map(grow, R.init(m, F32))
    size = sum(np.dtype(x.dtype).itemsize * int(np.prod(np.shape(x))) for x in jax.tree.leaves((s0, r0))) / batch
    d, V = jnp.zeros((steps, batch, n), F32), jnp.zeros((steps, batch, m), F32)

    def per_sample(s, r, d, V):
        return jax.lax.scan(lambda c, x: (jax.vmap(lambda s, r, a, b: R.step(s, r, a, b, 1e-3))(*c, *x), None),
                            (s, r), (d, V))[0]

    def blocked(s, r, d, V):
        return jax.vmap(lambda s, r, a, b: R.run(s, r, a, b, 1e-3, warmup=0, history=False)[:2],
                        in_axes=(0, 0, 1, 1))(s, r, d, V)

    out = {}
    for name, fn in (("recursive.step", per_sample), ("recursive.run", blocked)):
        peak = _peak_bytes(jax.jit(fn, donate_argnums=(0, 1)), s0, r0, d, V)
        out[name] = None if peak is None else (peak / batch - 4 * steps * (n + m)) / size
    return dict(batch=batch, state_bytes=size, peak_over_state=out)


def rollout_row(batch: int, reps: int) -> dict:
    """``batch`` UR5e star rollouts with the true inverse Jacobian in one compiled call."""
    system = ur5e()
    path = paths.star(size=0.05)
    q0 = system.sample_configs(jax.random.key(batch), batch)

    def run(q0):
        return jax.vmap(lambda q: control.follow(system, control.true_inverse(system), path, q, steps=435))(q0)

    jitted = jax.jit(run)
    _, first, t, _ = time_call(jitted, q0, reps=reps)
    peak = _peak_bytes(jitted, q0)
    return dict(what="rollout", batch=batch, compile_s=first - t, run_s=t, per_s=batch / t,
                peak_bytes_per=None if peak is None else peak / batch)


def stops_paying(rows: list[dict]) -> int | None:
    """The smallest batch whose throughput no larger batch beats by :data:`PAYS` or more (None: the largest batch
    measured still paid), robust to one noisy row."""
    for i, a in enumerate(rows[:-1]):
        if max(b["per_s"] for b in rows[i + 1:]) < PAYS * a["per_s"]:
            return a["batch"]
    return None


def _ratio(r: dict) -> str:
    """The peak per estimator (less its samples) over the state's own size, formatted."""
    peak = r["peak_bytes_per_less_data"]
    return "-" if peak is None else f"{peak / r['state_bytes']:.2f}"


def _fmt_bytes(v) -> str:
    if v is None:
        return "-"
    for unit, scale in (("MB", 1e6), ("kB", 1e3)):
        if abs(v) >= scale:
            return f"{v / scale:.1f} {unit}"
    return f"{v:.0f} B"


def figure(est: list[dict], roll: list[dict], path: str) -> None:
    """Log-log throughput against batch for both programs, the batch where each stops paying marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), layout="constrained")
    for ax, rows, label, unit in ((axes[0], est, "self-ID step (n = 6, m = 3)", "estimator-steps / s"),
                                  (axes[1], roll, "UR5e star rollout (435 steps)", "rollouts / s")):
        b = [r["batch"] for r in rows]
        ax.loglog(b, [r["per_s"] for r in rows], "o-", label="measured")
        ax.loglog(b, [rows[0]["per_s"] * x / b[0] for x in b], ":", color="0.6", label="linear in batch")
        knee = stops_paying(rows)
        if knee is not None:
            ax.axvline(knee, color="C3", ls="--", label=f"stops paying: {knee:,}")
        ax.set(xlabel="batch", ylabel=unit, title=label)
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="batches up to 10k only")
    ap.add_argument("--steps", type=int, default=20, help="samples per estimator timing")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--json", default=None)
    ap.add_argument("--figure", default=None, help="write the log-log figure here (PNG)")
    args = ap.parse_args()
    top = 10_000 if args.quick else 1_000_000
    est = [estimator_row(b, 6, 3, args.steps, args.reps) for b in (1, 10, 100, 1000, 10_000, 100_000, 1_000_000)
           if b <= top]
    roll = [rollout_row(b, args.reps) for b in (1, 10, 100, 1000, 10_000, 100_000) if b <= min(top, 100_000)]
    shapes = [estimator_row(10_000, n, m, args.steps, args.reps) for n in (3, 6, 9, 16) for m in (3, 6)]
    lines = [f"devices: {jax.devices()}", "",
             "estimator step vs batch (n = 6, m = 3, float32)",
             f"{'batch':>9} {'compile s':>10} {'run s':>9} {'steps/s':>12} {'state/est':>10} {'peak/est':>10} "
             f"{'peak/state':>10}"]
    for r in est:
        ratio = _ratio(r)
        lines.append(f"{r['batch']:>9,} {r['compile_s']:>10.2f} {r['run_s']:>9.4f} {r['per_s']:>12,.0f} "
                     f"{_fmt_bytes(r['state_bytes']):>10} {_fmt_bytes(r['peak_bytes_per_less_data']):>10} {ratio:>10}")
    lines.append(f"stops paying after batch {stops_paying(est)}")
    lines += ["", "UR5e rollout vs batch (star 5 cm, true inverse, 435 steps)",
              f"{'batch':>9} {'compile s':>10} {'run s':>9} {'rollouts/s':>12} {'ms/rollout':>11} {'peak/rollout':>12}"]
    for r in roll:
        lines.append(f"{r['batch']:>9,} {r['compile_s']:>10.2f} {r['run_s']:>9.4f} {r['per_s']:>12,.0f} "
                     f"{1e3 / r['per_s']:>11.4f} {_fmt_bytes(r['peak_bytes_per']):>12}")
    lines.append(f"stops paying after batch {stops_paying(roll)}")
    lines += ["", "estimator step vs n x m (batch 10,000, float32)",
              f"{'n':>3} {'m':>3} {'steps/s':>12} {'state/est':>10} {'peak/est':>10} {'peak/state':>10}"]
    for r in shapes:
        ratio = _ratio(r)
        lines.append(f"{r['n']:>3} {r['m']:>3} {r['per_s']:>12,.0f} {_fmt_bytes(r['state_bytes']):>10} "
                     f"{_fmt_bytes(r['peak_bytes_per_less_data']):>10} {ratio:>10}")
    rec = recursive_memory(10_000, args.steps)
    lines.append(f"rank-one step (state + Recursion {rec['state_bytes']:.0f} B), peak/state at batch 10,000: "
                 + ", ".join(f"{k} {v:.2f}" for k, v in rec["peak_over_state"].items() if v is not None))
    lines.append("peak/est: the compiled program's peak per estimator with its state donated (arguments + outputs + "
                 "temporaries, less the outputs aliased to the donated state), less its own samples (an argument "
                 "of the benchmark); goal <= 2x the state")
    if args.figure:
        figure(est, roll, args.figure)
        lines.append(f"figure: {args.figure}")
    paying = dict(estimator=stops_paying(est), rollout=stops_paying(roll))
    emit(dict(estimator=est, rollout=roll, shapes=shapes, recursive_memory=rec, stops_paying=paying),
         "\n".join(lines), args.json)


if __name__ == "__main__":
    main()
