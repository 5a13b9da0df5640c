"""``selfid-jax fit LOG``: self-ID from a recorded log into a run directory (estimates, inverse Jacobian, figure).

Usage::

    selfid-jax fit LOG [--task x,y,z | --task-dim 3] [--eps E] [--eps-rel R] [--refine METHOD]
                       [--start S] [--stop S] [--max-gap S] [--out DIR]
    selfid-jax fit --example

Runs :func:`selfid_jax.robot.offline.fit` (float64) and writes, each file whole
(:mod:`selfid_jax.runner.files`), under the run directory's lock:

* ``estimates.npz``: ``estimates (T, n, m)`` after every sample, ``deltas (T,)``
  (``||J_t - J_{t-1}||_F``), ``thresholds (T,)``, ``accepted (T,)``, ``t (T,)``
  and ``row (T,)`` (the log row of each sample);
* ``inverse_jacobian.npz`` / ``.json``: the final refined estimate with
  ``n``, ``m``, the task axes, the convergence iteration and sample counts;
* ``summary.json``: options, counts, rejected rows by reason;
* ``figures/convergence.png`` / ``.pdf``.

The heavy imports (JAX, pandas, matplotlib) happen inside :func:`run`, so the
console script stays fast to start.
"""

from __future__ import annotations

import argparse
import io
import math
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from selfid_jax.robot.offline import FitResult

__all__ = ["EXAMPLE_LOG", "add_arguments", "command", "draw", "draw_convergence", "example_log", "redraw", "run",
           "summary", "write_run"]

EXAMPLE_LOG = "ur5e_example_log.csv"
ESTIMATES_FILE = "estimates.npz"
JINV_NPZ = "inverse_jacobian.npz"
JINV_JSON = "inverse_jacobian.json"
SUMMARY_FILE = "summary.json"
FIGURE = "convergence"

DESCRIPTION = (
    "Run the self-ID estimator (Eq. 6-14) over a recorded log, offline, with the convergence test of Sec. IV-D. "
    "LOG is a CSV, Parquet or NPZ file of sample pairs (dtheta_0.., V_0..) or of a raw time series (t, q_0.., "
    "p_x, p_y, p_z and, for rotation axes, q_w, q_x, q_y, q_z or r_x, r_y, r_z). Bad rows (non-finite, duplicated "
    "or non-monotonic time, gaps) are dropped and counted. Writes estimates.npz, inverse_jacobian.npz/.json, "
    "summary.json and figures/convergence.png/.pdf into the run directory."
)


def example_log() -> Path:
    """Path of the shipped example: a UR5e time series with a few bad rows (``scripts/make_example_log.py``)."""
    return Path(str(resources.files("selfid_jax.robot") / "data" / EXAMPLE_LOG))


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if math.isnan(value):
        raise argparse.ArgumentTypeError("expected a number of seconds, got nan")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``fit`` subcommand's arguments."""
    p.add_argument("log", type=Path, nargs="?", help="CSV, Parquet or NPZ log (see the description)")
    p.add_argument("--example", action="store_true", help=f"fit the shipped UR5e example log ({EXAMPLE_LOG})")
    t = p.add_mutually_exclusive_group()
    t.add_argument("--task", metavar="AXES", help="task axes out of x,y,z,rx,ry,rz, e.g. x,y,z or z,rx,ry")
    t.add_argument("--task-dim", type=int, metavar="M", choices=(2, 3, 6),
                   help="task dimension: 2 (x,y), 3 (x,y,z: default for a time series) or 6 (position + rotation)")
    p.add_argument("--eps", type=float, default=0.0,
                   help="absolute Sec. IV-D threshold on ||J_t - J_{t-1}||_F, inverse-Jacobian units (default 0)")
    p.add_argument("--eps-rel", type=float, default=0.05,
                   help="relative threshold, times ||J_t||_F (default 0.05); converged when the change is at most "
                   "eps + eps_rel ||J_t||_F twice in a row")
    p.add_argument("--refine", default="closed_form", metavar="METHOD",
                   help="Eq. 14 refinement: closed_form (default), optax or slsqp (final estimate only)")
    p.add_argument("--start", type=_seconds, metavar="S", help="ignore rows before this time (s)")
    p.add_argument("--stop", type=_seconds, metavar="S", help="ignore rows after this time (s)")
    p.add_argument("--max-gap", type=_seconds, metavar="S",
                   help="time series: drop pairs of rows more than S seconds apart (default: 3 median time steps; "
                   "inf: never)")
    p.add_argument("--out", type=Path, default=None, help="run directory (default: runs/fit_<log stem>)")


def _npz(**arrays) -> bytes:
    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def summary(result: FitResult, *, log: Path | str) -> dict[str, Any]:
    """``summary.json`` of a fit: options, sample counts, rejected rows, convergence, the samples' held-out error."""
    import numpy as np

    from selfid_jax.robot.quality import held_out

    s = result.samples
    n, m = result.estimate.shape
    T = int(result.deltas.shape[0])
    ok = np.asarray(result.accepted, bool)
    quality = held_out(s.dtheta[ok], s.V[ok], float(np.max(np.abs(s.dtheta[ok]), initial=0.0)))
    return {
        "command": "fit",
        "log": str(log),
        "layout": s.layout,
        "rotation": s.rotation,
        "n": n,
        "m": m,
        "task_axes": list(s.axis_names),
        "eps": result.eps,
        "eps_rel": result.eps_rel,
        "refine": result.method,
        "rows": s.rows,
        "rows_used": s.used_rows,
        "rows_outside_window": s.outside_window,
        "max_gap_s": s.max_gap,
        "samples": T,
        "samples_accepted": int(result.accepted.sum()),
        "rejected": [{"reason": r.reason, "count": r.count, "first": r.first} for r in s.rejected],
        "converged_at": result.converged_at,
        "converged": result.converged,
        "converged_time_s": result.converged_time,
        "converged_row": int(s.row[result.converged_at - 1]) if result.converged else None,
        "final_delta": float(result.deltas[-1]),
        "final_threshold": float(result.thresholds[-1]),
        # how far to trust the samples (selfid_jax.robot.quality): the forward map's leave-one-out error, and each
        # actuator's task motion for the largest sample step
        "heldout_error": quality.heldout_error,
        "actuator_effect": quality.effect,
    }


def draw(result: FitResult):
    """Figure of ``||J_t - J_{t-1}||_F`` per sample (log scale) with the threshold and the convergence iteration."""
    return draw_convergence(result.deltas, result.thresholds, eps=result.eps, eps_rel=result.eps_rel,
                            converged_at=result.converged_at,
                            title=f"self-ID from {Path(result.samples.source).name}: n={result.estimate.shape[0]}, "
                            f"task {','.join(result.samples.axis_names)}")


def draw_convergence(deltas, thresholds, *, eps: float, eps_rel: float, converged_at: int, title: str):
    """``||J_t - J_{t-1}||_F`` per sample ``deltas (T,)`` (log scale) against the Sec. IV-D threshold
    ``thresholds (T,)``, with the convergence iteration (1-based; < 1: none); ``fit``'s and ``online``'s figure."""
    import numpy as np
    from matplotlib.figure import Figure

    deltas, thresholds = np.asarray(deltas, np.float64), np.asarray(thresholds, np.float64)
    T = deltas.shape[0]
    k = np.arange(1, T + 1)
    fig = Figure(figsize=(6.4, 3.6))
    ax = fig.subplots()
    tiny = np.finfo(np.float64).tiny
    ax.semilogy(k, np.maximum(deltas, tiny), "o-", ms=3, lw=1, label=r"$\|J_t - J_{t-1}\|_F$")
    ax.semilogy(k, np.maximum(thresholds, tiny), "--", color="0.4", lw=1,
                label=rf"$\epsilon + \epsilon_{{rel}} \|J_t\|_F$ ($\epsilon$={eps:g}, "
                rf"$\epsilon_{{rel}}$={eps_rel:g})")
    if converged_at >= 1:
        ax.axvline(converged_at, color="C3", lw=1.2, label=f"converged at sample {converged_at}")
    ax.set_xlabel("sample")
    ax.set_ylabel(r"$\|J_t - J_{t-1}\|_F$")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    return fig


def redraw(run_dir: Path) -> list[Path] | None:
    """Redraw ``figures/convergence`` of a ``fit`` run directory from its ``estimates.npz`` and ``summary.json``
    (``selfid-jax plot RUN``); None when ``run_dir`` is not one (no ``fit`` summary)."""
    import json

    import numpy as np

    from selfid_jax.runner.errors import RunDirError
    from selfid_jax.runner.figures import save_figure
    from selfid_jax.runner.layout import FIGURES_DIR
    from selfid_jax.runner.lock import hold

    run_dir = Path(run_dir)
    try:
        info = json.loads((run_dir / SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(info, dict) or info.get("command") != "fit":
        return None
    with hold(run_dir):  # not while a fit writes it
        try:
            with np.load(run_dir / ESTIMATES_FILE) as z:
                deltas, thresholds = z["deltas"], z["thresholds"]
        except (OSError, ValueError, KeyError) as err:
            raise RunDirError(f"{run_dir / ESTIMATES_FILE}: cannot be read ({err}); run selfid-jax fit again"
                              ) from None
        fig = draw_convergence(deltas, thresholds, eps=float(info["eps"]), eps_rel=float(info["eps_rel"]),
                               converged_at=int(info["converged_at"]),
                               title=f"self-ID from {Path(str(info.get('log', '?'))).name}: n={info.get('n')}, "
                               f"task {','.join(info.get('task_axes', []))}")
        return save_figure(fig, run_dir / FIGURES_DIR, FIGURE)


def write_run(result: FitResult, out: Path, *, log: Path | str) -> dict[str, Path]:
    """Write every output file of a fit into ``out`` (each atomically); returns name -> path."""
    import numpy as np

    from selfid_jax.runner.figures import save_figure
    from selfid_jax.runner.files import atomic_write_bytes, write_json
    from selfid_jax.runner.layout import FIGURES_DIR

    s = result.samples
    info = summary(result, log=log)
    paths = {name: out / name for name in (ESTIMATES_FILE, JINV_NPZ, JINV_JSON, SUMMARY_FILE)}
    atomic_write_bytes(paths[ESTIMATES_FILE], _npz(
        estimates=result.estimates, deltas=result.deltas, thresholds=result.thresholds, accepted=result.accepted,
        t=s.t, row=s.row, converged_at=np.int64(result.converged_at)))
    meta = {k: info[k] for k in ("n", "m", "task_axes", "converged_at", "converged", "samples", "samples_accepted",
                                 "rows", "rows_used", "refine", "eps", "eps_rel")}
    atomic_write_bytes(paths[JINV_NPZ], _npz(
        inverse_jacobian=result.estimate, initial_guess=result.initial_guess, task_axes=np.array(info["task_axes"]),
        **{k: np.asarray(v) for k, v in meta.items() if k != "task_axes"}))
    write_json(paths[JINV_JSON], {"inverse_jacobian": result.estimate, "initial_guess": result.initial_guess,
                                  **meta, "log": str(log)})
    write_json(paths[SUMMARY_FILE], info)
    fig_paths = save_figure(draw(result), out / FIGURES_DIR, FIGURE)
    return {**{p.name: p for p in paths.values()}, **{f"figures/{p.name}": p for p in fig_paths}}


def run(args: argparse.Namespace) -> int:
    """Body of ``selfid-jax fit``: validate, fit, write, print; bad input raises ``ConfigError`` (exit 2)."""
    from selfid_jax.runner.errors import ConfigError, RunDirError

    if args.example == (args.log is not None):
        raise ConfigError("give a LOG file or --example (not both)" if args.example else
                          "no log given: selfid-jax fit LOG (or --example for the shipped UR5e log)")
    log = example_log() if args.example else args.log
    out = args.out if args.out is not None else Path("runs") / f"fit_{Path(log).stem}"
    if (out / "config.yaml").exists():
        raise RunDirError(f"{out}: holds a sweep's run directory (config.yaml); choose another --out")
    if args.start is not None and args.stop is not None and args.stop < args.start:
        raise ConfigError(f"--stop {args.stop:g} is before --start {args.start:g}")
    if args.max_gap is not None and not args.max_gap > 0:
        raise ConfigError(f"--max-gap must be positive seconds, got {args.max_gap:g}")

    import jax

    jax.config.update("jax_enable_x64", True)  # an offline fit is small: float64 everywhere
    from selfid_jax.robot.offline import fit
    from selfid_jax.runner import signals
    from selfid_jax.runner.lock import hold

    signals.phase("fit")
    try:
        result = fit(log, task=args.task, task_dim=args.task_dim, eps=args.eps, eps_rel=args.eps_rel,
                     method=args.refine, start=args.start, stop=args.stop,
                     max_gap="auto" if args.max_gap is None else args.max_gap)
    except ValueError as err:  # LogError included: one line naming file, column, row
        raise ConfigError(" ".join(str(err).split())) from None
    s = result.samples
    n, m = result.estimate.shape
    print(f"{s.source}: {s.rows} rows, {s.layout.replace('_', ' ')}; {result.deltas.shape[0]} samples "
          f"(n={n}, task {','.join(s.axis_names)})")
    for r in s.rejected:
        print(f"  {r.line()}")
    if s.outside_window:
        print(f"  {s.outside_window} rows outside --start/--stop (ignored)")
    refused = int((~result.accepted).sum())
    if refused:
        print(f"  {refused} samples refused by the estimator (all-zero dtheta or V)")
    with hold(out):
        signals.phase("write")
        files = write_run(result, out, log=log)
    if result.converged:
        when = f", t = {result.converged_time:.3f} s" if result.converged_time is not None else ""
        print(f"converged at sample {result.converged_at} of {result.deltas.shape[0]}{when} "
              f"(eps={result.eps:g}, eps_rel={result.eps_rel:g})")
    else:
        print(f"not converged in {result.deltas.shape[0]} samples (eps={result.eps:g}, eps_rel={result.eps_rel:g}; "
              f"last change {result.deltas[-1]:.3g} > {result.thresholds[-1]:.3g}); the estimate uses every sample")
    print(f"inverse Jacobian ({n}x{m}): {files[JINV_NPZ]} (and {JINV_JSON})")
    print(f"results: {out}")
    return 0


def command():
    """The ``fit`` subcommand for :func:`selfid_jax.runner.command_line.main`."""
    from selfid_jax.runner.command_line import Command

    return Command(help="self-ID from a recorded log (CSV, Parquet, NPZ) into a run directory",
                   description=DESCRIPTION, add_arguments=add_arguments, run=run, plot=redraw)
