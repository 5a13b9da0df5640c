"""The README's main job: self-identify the UR5e, then follow a star with the estimated inverse Jacobian.

From a few start configurations at once (one vmapped, compiled call), the
arm runs Algorithm 1 (random actuations of ``m_a`` rad, signed x magnitude
initial guess, closed-form refinement, convergence test of Sec. IV-D), then
follows a 5 cm star with the final estimate and, for comparison, with the true
inverse Jacobian. Writes ``demo.png`` (estimated vs true inverse Jacobian, the
traced paths, the convergence curves) and ``summary.json`` to the output
directory and prints a short summary.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax import control, paths, selfid
from selfid_jax.systems import ur5e

N_CONFIGS = 4
ITERS = 30
EPS = 0.5  # ||J_t - J_{t-1}||_F threshold (rad/m); the UR5e position inverse Jacobian has norm ~4-5
CTRL = dict(steps=400, max_step=0.0025, tol=0.0005)


def main(out_dir: Path | str = "runs/demo") -> dict:
    """Run the demo, write its figure and summary into ``out_dir``; return the summary."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    system = ur5e(task_dim=3)
    star = paths.star(size=0.05, dim=3)
    q0 = control.feasible_starts(system, star, jax.random.key(0), N_CONFIGS, **CTRL)
    keys = jax.random.split(jax.random.key(1), N_CONFIGS)

    def one(key, q):
        sid = selfid.run(system, key, q, iters=ITERS, eps=EPS)
        q_start = sid.env  # follow from where self-ID left the arm
        est = control.follow(system, control.fixed(sid.estimate), star, q_start, return_trajectory=True, **CTRL)
        true = control.follow(system, control.true_inverse(system), star, q_start, return_trajectory=True, **CTRL)
        return sid, est, true, system.true_inverse_jacobian(q_start)

    sid, est, true, truth = jax.block_until_ready(jax.jit(jax.vmap(one))(keys, q0))
    seconds = time.perf_counter() - t0

    rel_err = np.linalg.norm(sid.estimate - truth, axis=(1, 2)) / np.linalg.norm(truth, axis=(1, 2))
    summary = {
        "system": "ur5e (position task, 3-D)",
        "self_id": {"iterations": ITERS, "m_a_rad": float(system.m_a), "eps": EPS},
        "controller": dict(CTRL, path="star, outer radius 0.05 m"),
        "start_configs_rad": np.asarray(q0).tolist(),
        "converged_at": np.asarray(sid.converged_at).tolist(),
        "relative_error_vs_true_inverse": rel_err.tolist(),
        "completion_estimated": np.asarray(est.completion).tolist(),
        "completion_true": np.asarray(true.completion).tolist(),
        "mean_tracking_error_estimated_m": np.asarray(est.mean_error).tolist(),
        "mean_tracking_error_true_m": np.asarray(true.mean_error).tolist(),
        "seconds_including_compile": seconds,
    }
    print(f"UR5e self-ID from {N_CONFIGS} start configurations, then a 5 cm star ({seconds:.1f} s incl. compilation)")
    print(f"{'config':>6s} {'converged at':>12s} {'rel. error':>10s} {'completion est/true':>20s} "
          f"{'tracking error est/true [mm]':>29s}")
    for b in range(N_CONFIGS):
        print(f"{b:6d} {int(sid.converged_at[b]):12d} {rel_err[b]:10.3f} "
              f"{float(est.completion[b]):9.0%} / {float(true.completion[b]):4.0%} "
              f"{1e3 * float(est.mean_error[b]):16.3f} / {1e3 * float(true.mean_error[b]):.3f}")
    print("estimated inverse Jacobian (config 0, rad/m):\n", np.array2string(np.asarray(sid.estimate[0]), precision=2))
    print("true inverse Jacobian (config 0, rad/m):\n", np.array2string(np.asarray(truth[0]), precision=2))
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    _figure(sid, est, true, truth, out_dir / "demo.png")
    print(f"wrote {out_dir / 'demo.png'} and {out_dir / 'summary.json'}")
    return summary


def _figure(sid, est, true, truth, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 4))
    vmax = float(np.abs(truth[0]).max())
    for ax, mat, title in ((axes[0], sid.estimate[0], "estimated"), (axes[1], truth[0], "true")):
        im = ax.imshow(np.asarray(mat), cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        ax.set_title(f"{title} $J^+$, config 0")
        ax.set_xticks(range(3), ["x", "y", "z"])
        ax.set_yticks(range(6), [f"q{i + 1}" for i in range(6)])
        for (i, j), v in np.ndenumerate(np.asarray(mat)):
            ax.text(j, i, f"{v:.1f}", ha="center", va="center", fontsize=7)
    fig.colorbar(im, ax=axes[:2], shrink=0.8, label="rad/m")
    ax = axes[2]
    for b in range(est.positions.shape[0]):
        p_true = np.asarray(true.positions[b]) - np.asarray(true.positions[b][0])
        p_est = np.asarray(est.positions[b]) - np.asarray(est.positions[b][0])
        ax.plot(1e3 * p_true[:, 0], 1e3 * p_true[:, 1], color="0.6", lw=3, label="true inverse" if b == 0 else None)
        ax.plot(1e3 * p_est[:, 0], 1e3 * p_est[:, 1], lw=1, label=f"estimate, config {b}")
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_title("star traced by the end effector")
    ax.legend(fontsize=7)
    ax = axes[3]
    for b in range(sid.deltas.shape[0]):
        d = np.asarray(sid.deltas[b])
        ax.semilogy(np.arange(1, len(d) + 1)[d > 0], d[d > 0], marker=".", label=f"config {b}")
    ax.axhline(EPS, color="k", ls=":", label="eps")
    ax.set_xlabel("self-ID iteration")
    ax.set_ylabel(r"$\|J_t - J_{t-1}\|_F$")
    ax.set_title("convergence (Sec. IV-D)")
    ax.legend(fontsize=7)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    main()
