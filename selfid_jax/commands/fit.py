"""``selfid-jax fit LOG``: self-ID from a recorded log into a run directory (estimates, inverse Jacobian, figure).

Usage::

    selfid-jax fit LOG [--task x,y,z | --task-dim 3] [--eps E] [--eps-rel R] [--refine METHOD]
                       [--start S] [--stop S] [--max-gap S] [--out DIR]
                       [--columns MAP] [--joint-names A,B,..] [--length mm] [--time ns] [--angle deg]
                       [--mode auto|stream|moves] [--latency auto|S|none] [--strict]
    selfid-jax fit BAG --joints /joint_states --tracker /mocap/pose [--child-frame F] ...
    selfid-jax fit --example

Runs :func:`selfid_jax.robot.offline.fit` (float64) and writes, each file whole
(:mod:`selfid_jax.runner.files`), under the run directory's lock:

* ``estimates.npz``: ``estimates (T, n, m)`` after every sample, ``deltas (T,)``
  (``||J_t - J_{t-1}||_F``), ``thresholds (T,)``, ``accepted (T,)``, ``t (T,)``
  and ``row (T,)`` (the log row of each sample);
* ``inverse_jacobian.npz`` / ``.json`` (a converged fit only): the final
  refined estimate with ``n``, ``m``, the task axes, the convergence
  iteration, sample counts and units;
* ``summary.json``: options, counts, rejected rows by reason, the trust
  figures (:func:`selfid_jax.robot.quality.trust`), units, notes on how the
  log was read;
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
    "p_x, p_y, p_z and, for rotation axes, q_w, q_x, q_y, q_z or r_x, r_y, r_z; other names through --columns and "
    "--joint-names, other units through --length/--time/--angle or a units row), or a ROS 1/ROS 2 bag or MCAP "
    "file (--joints, --tracker). A time series logged continuously is reduced to one settled row per move. Bad "
    "rows (non-finite, duplicated or non-monotonic time, gaps) are dropped and counted. Writes estimates.npz, "
    "summary.json (with how far to trust the fit), figures/convergence.png/.pdf and, when it converged, "
    "inverse_jacobian.npz/.json into the run directory; exits 1 when it did not (or, with --strict, when a trust "
    "figure is out of bounds)."
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
    b = p.add_argument_group("a ROS 1 / ROS 2 bag or an MCAP file (pip install \"selfid-jax[ros]\")")
    b.add_argument("--joints", metavar="TOPIC", help="the sensor_msgs/JointState topic (joints: --joint-names, "
                   "default the messages' order)")
    b.add_argument("--tracker", metavar="TOPIC", help="the tracker's geometry_msgs/PoseStamped or TransformStamped "
                   "topic, or /tf with --child-frame")
    b.add_argument("--child-frame", metavar="FRAME", help="on a tf topic, the tracked frame (child_frame_id)")
    g = p.add_argument_group("the log's layout and units")
    g.add_argument("--columns", metavar="MAP", help="rename the log's columns to the fit's: 'joint_a=q_0,"
                   "tx=p_x,...' or a YAML/JSON file of that mapping")
    g.add_argument("--joint-names", metavar="NAMES", help="these columns, in this order, are the actuators q_0.. "
                   "(e.g. ROS names shoulder_pan_joint,shoulder_lift_joint,...); in a bag, the JointState names")
    g.add_argument("--length", default="m", choices=("m", "cm", "mm"), help="unit of the tracked positions "
                   "(default m); converted to m")
    g.add_argument("--time", default="s", choices=("s", "ms", "us", "ns"), help="unit of t (default s); converted "
                   "to s, and --start/--stop/--max-gap are in s")
    g.add_argument("--angle", default="rad", choices=("rad", "deg"), help="unit of the actuator positions and "
                   "rotation vectors (default rad); converted to rad")
    g.add_argument("--mode", default="auto", choices=("auto", "stream", "moves"), help="a time series logged "
                   "continuously (a stream) is reduced to one settled row per move; auto (default) detects it, "
                   "stream/moves force either reading")
    g.add_argument("--latency", default="auto", metavar="S|auto|none", help="a stream's tracker latency behind the "
                   "encoders (s): auto (default) estimates it by cross-correlating their speeds; none: no shift")
    g.add_argument("--settle-speed", type=float, default=None, metavar="V", help="a stream: joint speed below "
                   "which the arm is at rest (actuator units/s; default from the stream)")
    g.add_argument("--settle-time", type=_seconds, default=None, metavar="S", help="a stream: shortest rest that "
                   "counts as settled (s; default from the stream)")
    g.add_argument("--strict", action="store_true", help="exit 1 when a trust figure (held-out error, condition "
                   "number, actuator effect, refused fraction) is outside its bound")


def _npz(**arrays) -> bytes:
    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


UNITS = {"actuator": "rad (or m for a prismatic actuator)", "length": "m", "time": "s", "rotation": "rad"}
"""The units of a fit's outputs: every input is converted to these (--length, --time, --angle, a units row)."""


def trust(result: FitResult) -> tuple[dict[str, Any], list[str]]:
    """The figures that say how far to trust a fit (:func:`selfid_jax.robot.quality.trust`) and its warnings."""
    import numpy as np

    from selfid_jax.robot.quality import held_out
    from selfid_jax.robot.quality import trust as figures

    s = result.samples
    ok = np.asarray(result.accepted, bool)
    quality = held_out(s.dtheta[ok], s.V[ok], float(np.max(np.abs(s.dtheta[ok]), initial=0.0)))
    refused = sum(r.count for r in s.rejected) + int((~ok).sum())
    return figures(quality, result.estimate, refused, s.rows)


def estimate_units(axis_names) -> list[str]:
    """The unit of each column of the estimate: ``rad/m`` for a position axis, ``rad/rad`` for a rotation axis."""
    return [f"rad/{'rad' if a.startswith('r') else 'm'}" for a in axis_names]


def summary(result: FitResult, *, log: Path | str, units: dict[str, str] | None = None,
            notes: list[str] | None = None, trusted: tuple[dict[str, Any], list[str]] | None = None
            ) -> dict[str, Any]:
    """``summary.json`` of a fit: options, sample counts, rejected rows, convergence, the trust figures and units
    (``trusted``: :func:`trust` of ``result`` where the caller has it)."""
    s = result.samples
    n, m = result.estimate.shape
    T = int(result.deltas.shape[0])
    figures, warnings = trust(result) if trusted is None else trusted
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
        # how far to trust the fit (selfid_jax.robot.quality.trust): the forward map's leave-one-out error, the
        # estimate's condition number, each actuator's task motion for the largest sample step, the fraction of
        # rows and samples refused, and a warning per figure outside its bound
        **figures,
        "warnings": warnings,
        "units": UNITS,
        "estimate_units": estimate_units(s.axis_names),
        "converted_from": units or {},  # column -> the unit it was read in (converted to UNITS)
        "notes": notes or [],  # how the log's layout was read (renamed columns, ISO times, a continuous stream)
    }


def draw(result: FitResult):
    """Figure of ``||J_t - J_{t-1}||_F`` per sample (log scale) with the threshold and the convergence iteration."""
    return draw_convergence(result.deltas, result.thresholds, eps=result.eps, eps_rel=result.eps_rel,
                            converged_at=result.converged_at, accepted=result.accepted,
                            title=f"self-ID from {Path(result.samples.source).name}: n={result.estimate.shape[0]}, "
                            f"task {','.join(result.samples.axis_names)}")


def draw_convergence(deltas, thresholds, *, eps: float, eps_rel: float, converged_at: int, title: str,
                     accepted=None):
    """``||J_t - J_{t-1}||_F`` per sample ``deltas (T,)`` (log scale) against the Sec. IV-D threshold
    ``thresholds (T,)``, with the convergence iteration (1-based; < 1: none); ``fit``'s and ``online``'s figure.

    Samples the estimator refused (``accepted (T,)`` False) and zero or
    non-finite changes are not drawn as values but marked along the bottom;
    the axis spans the drawn values and the threshold, so neither a refused
    sample nor a zero change stretches it, and the threshold is always in view."""
    import numpy as np
    from matplotlib.figure import Figure

    deltas, thresholds = np.asarray(deltas, np.float64), np.asarray(thresholds, np.float64)
    T = deltas.shape[0]
    k = np.arange(1, T + 1)
    ok = np.ones(T, bool) if accepted is None else np.asarray(accepted, bool)
    shown = ok & np.isfinite(deltas) & (deltas > 0)
    thr = np.isfinite(thresholds) & (thresholds > 0)
    fig = Figure(figsize=(6.4, 3.6))
    ax = fig.subplots()
    ax.set_yscale("log")
    ax.plot(k[shown], deltas[shown], "o-", ms=3, lw=1, label=r"$\|J_t - J_{t-1}\|_F$")
    ax.plot(k[thr], thresholds[thr], "--", color="0.4", lw=1, gid="threshold",
            label=rf"$\epsilon + \epsilon_{{rel}} \|J_t\|_F$ ($\epsilon$={eps:g}, "
            rf"$\epsilon_{{rel}}$={eps_rel:g})")
    values = np.concatenate([deltas[shown], thresholds[thr]])
    lo, hi = (float(values.min()), float(values.max())) if values.size else (1e-3, 1.0)
    lo, hi = lo / 3.0, max(hi * 3.0, lo * 10.0)
    ax.set_ylim(lo, hi)
    marked = ~shown
    if marked.any():
        ax.plot(k[marked], np.full(int(marked.sum()), lo * 1.3), "x", color="C3", ms=4, gid="refused",
                label=f"refused or zero change ({int(marked.sum())})")
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
                deltas, thresholds, accepted = z["deltas"], z["thresholds"], z["accepted"]
        except (OSError, ValueError, KeyError) as err:
            raise RunDirError(f"{run_dir / ESTIMATES_FILE}: cannot be read ({err}); run selfid-jax fit again"
                              ) from None
        fig = draw_convergence(deltas, thresholds, eps=float(info["eps"]), eps_rel=float(info["eps_rel"]),
                               converged_at=int(info["converged_at"]), accepted=accepted,
                               title=f"self-ID from {Path(str(info.get('log', '?'))).name}: n={info.get('n')}, "
                               f"task {','.join(info.get('task_axes', []))}")
        return save_figure(fig, run_dir / FIGURES_DIR, FIGURE)


def write_run(result: FitResult, out: Path, *, log: Path | str, units: dict[str, str] | None = None,
              notes: list[str] | None = None, trusted: tuple[dict[str, Any], list[str]] | None = None
              ) -> dict[str, Path]:
    """Write every output file of a fit into ``out`` (each atomically); returns name -> path.

    Only a converged fit writes ``inverse_jacobian.npz`` / ``.json`` (and one
    that did not removes those of an earlier fit there, so no file can be
    taken for its result); ``summary.json`` then holds ``estimate_so_far``."""
    import numpy as np

    from selfid_jax.runner.figures import save_figure
    from selfid_jax.runner.files import atomic_write_bytes, write_json
    from selfid_jax.runner.layout import FIGURES_DIR

    s = result.samples
    info = summary(result, log=log, units=units, notes=notes, trusted=trusted)
    paths = {name: out / name for name in (ESTIMATES_FILE, SUMMARY_FILE)}
    atomic_write_bytes(paths[ESTIMATES_FILE], _npz(
        estimates=result.estimates, deltas=result.deltas, thresholds=result.thresholds, accepted=result.accepted,
        t=s.t, row=s.row, converged_at=np.int64(result.converged_at)))
    if result.converged:
        paths.update({name: out / name for name in (JINV_NPZ, JINV_JSON)})
        meta = {k: info[k] for k in ("n", "m", "task_axes", "converged_at", "converged", "samples",
                                     "samples_accepted", "rows", "rows_used", "refine", "eps", "eps_rel")}
        atomic_write_bytes(paths[JINV_NPZ], _npz(
            inverse_jacobian=result.estimate, initial_guess=result.initial_guess,
            task_axes=np.array(info["task_axes"]), estimate_units=np.array(info["estimate_units"]),
            **{k: np.asarray(v) for k, v in meta.items() if k != "task_axes"}))
        write_json(paths[JINV_JSON], {"inverse_jacobian": result.estimate, "initial_guess": result.initial_guess,
                                      **meta, "units": UNITS, "estimate_units": info["estimate_units"],
                                      "log": str(log)})
    else:
        for name in (JINV_NPZ, JINV_JSON):
            (out / name).unlink(missing_ok=True)
        info["estimate_so_far"] = result.estimate
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
        samples, notes, units = read_samples(log, args)
        result = fit(samples, eps=args.eps, eps_rel=args.eps_rel, method=args.refine)
    except ValueError as err:  # LogError included: one line naming file, column, row
        raise ConfigError(" ".join(str(err).split())) from None
    s = result.samples
    n, m = result.estimate.shape
    print(f"{s.source}: {s.rows} rows, {s.layout.replace('_', ' ')}; {result.deltas.shape[0]} samples "
          f"(n={n}, task {','.join(s.axis_names)})")
    for note in notes:
        print(f"  {note}")
    for r in s.rejected:
        print(f"  {r.line()}")
    if s.outside_window:
        print(f"  {s.outside_window} rows outside --start/--stop (ignored)")
    refused = int((~result.accepted).sum())
    if refused:
        print(f"  {refused} samples refused by the estimator (all-zero dtheta or V)")
    with hold(out):
        signals.phase("write")
        figures, warnings = trusted = trust(result)
        files = write_run(result, out, log=log, units=units, notes=notes, trusted=trusted)
    effect = figures["actuator_effect"]
    print(f"trust: held-out error {figures['heldout_error']:.3g}, condition number {figures['condition']:.3g}, "
          f"{100 * figures['refused_fraction']:.0f}% refused, actuator effect "
          f"{min(effect, default=float('nan')):.3g}..{max(effect, default=float('nan')):.3g}")
    for w in warnings:
        print(f"  warning: {w}")
    if result.converged:
        when = f", t = {result.converged_time:.3f} s" if result.converged_time is not None else ""
        print(f"converged at sample {result.converged_at} of {result.deltas.shape[0]}{when} "
              f"(eps={result.eps:g}, eps_rel={result.eps_rel:g})")
        print(f"inverse Jacobian ({n}x{m}, {', '.join(sorted(set(estimate_units(s.axis_names))))}): "
              f"{files[JINV_NPZ]} (and {JINV_JSON})")
    else:
        print(f"not converged in {result.deltas.shape[0]} samples (eps={result.eps:g}, eps_rel={result.eps_rel:g}; "
              f"last change {result.deltas[-1]:.3g} > {result.thresholds[-1]:.3g}): no inverse Jacobian written "
              f"(the estimate so far is in {out / SUMMARY_FILE})")
    print(f"results: {out}")
    if not result.converged:
        return 1
    return 1 if args.strict and warnings else 0


def read_samples(log: Path, args: argparse.Namespace):
    """The log's sample pairs for ``fit``: ``(Samples, notes, units)`` (the layout, units and screens of ``args``)."""
    from selfid_jax.robot import streams
    from selfid_jax.robot.log import LogError, prepare_table, read_table_units, samples_from_table
    from selfid_jax.robot.tables import Units

    names = None if args.joint_names is None else [x.strip() for x in args.joint_names.split(",") if x.strip()]
    text = str(args.latency).strip().lower()
    try:
        latency = {"auto": "auto", "none": None}[text] if text in ("auto", "none") else float(text)
    except ValueError:
        raise LogError(f"--latency: expected auto, none or seconds, got {args.latency!r}") from None
    notes: list[str] = []
    if is_bag(log):
        from selfid_jax.robot.bags import read_bag

        if not (args.joints and args.tracker):
            raise LogError(f"{log}: a bag needs --joints TOPIC (sensor_msgs/JointState) and --tracker TOPIC")
        table, info = read_bag(log, joints=args.joints, tracker=args.tracker, joint_names=names,
                               child_frame=args.child_frame)
        notes += [f"bag: {line.strip()}" for line in info.lines()]
        names = None
        row_units: dict[str, str] = {}
    else:
        if args.joints or args.tracker or args.child_frame:
            raise LogError(f"{log}: --joints, --tracker and --child-frame are for a ROS bag or MCAP file")
        table, row_units = read_table_units(log)
    table, more, units = prepare_table(table, columns=args.columns, joint_names=names,
                                       units=Units(args.length, args.time, args.angle), row_units=row_units,
                                       source=str(log))
    notes += more
    converted = {k: v for k, v in units.items() if v not in ("m", "s", "rad")}
    if converted:
        notes.append("converted to m, s, rad: " + ", ".join(f"{k} [{v}]" for k, v in converted.items()))
    q_cols = sorted((c for c in table if c.startswith("q_") and c[2:].isdigit()), key=lambda c: int(c[2:]))
    if q_cols and "t" in table:
        quat = [c for c in ("q_w", "q_x", "q_y", "q_z") if c in table]
        rotvec = [c for c in ("r_x", "r_y", "r_z") if c in table]
        pose = [c for c in ("p_x", "p_y", "p_z") if c in table] + quat + rotvec
        try:
            table, s_info = streams.reduce_stream(table, q_cols, pose, mode=args.mode, latency=latency,
                                                  v_tol=args.settle_speed, min_settle_s=args.settle_time,
                                                  quat_cols=quat or None, rotvec_cols=rotvec or None)
        except ValueError as err:
            raise LogError(f"{log}: {err}") from None
        if s_info.continuous:
            notes.append(s_info.line())
        notes += list(s_info.notes)
    samples = samples_from_table(table, task=args.task, task_dim=args.task_dim, start=args.start, stop=args.stop,
                                 max_gap="auto" if args.max_gap is None else args.max_gap, source=str(log))
    return samples, notes, units


def is_bag(path: Path) -> bool:
    """A ROS 1 bag, a ROS 2 bag folder or an MCAP file (read by :mod:`selfid_jax.robot.bags`)."""
    return path.is_dir() or path.suffix.lower() in (".bag", ".mcap", ".db3")


def command():
    """The ``fit`` subcommand for :func:`selfid_jax.runner.command_line.main`."""
    from selfid_jax.runner.command_line import Command

    return Command(help="self-ID from a recorded log (CSV, Parquet, NPZ) into a run directory",
                   description=DESCRIPTION, add_arguments=add_arguments, run=run, plot=redraw)
