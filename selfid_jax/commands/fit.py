"""``selfid-jax fit LOG``: self-ID from a recorded log into a run directory (estimates, inverse Jacobian, figure).

Usage::

    selfid-jax fit LOG [--task x,y,z | --task-dim 3] [--eps E] [--eps-rel R] [--refine METHOD]
                       [--start S] [--stop S] [--max-gap S|auto|inf] [--out DIR]
                       [--columns MAP] [--joint-names A,B,..] [--length mm] [--time ns] [--angle deg]
                       [--mode auto|stream|windows|moves] [--latency auto|S|none] [--strict]
    selfid-jax fit BAG --joints /joint_states --tracker /mocap/pose [--child-frame F] ...
    selfid-jax fit BAG --joints /joint_states --camera /camera/image_raw --tag tag36h11:ID:EDGE_M [--camera-info F]
    selfid-jax fit JOINTS.csv --video FRAMES --frame-times TIMES.csv --camera-info CAMERA.yaml --tag tag36h11:ID:EDGE_M
    selfid-jax fit --example

Parses the flags, calls :func:`selfid_jax.sessions.fit_run.fit_to_run` (which
runs ``sj.fit`` with the same keywords, flag ``--x-y`` = keyword ``x_y``, and
writes the run directory) and prints what it did. The flags' defaults are the
library's (:class:`selfid_jax.robot.fit_options.ReadOptions`, ``FitOptions``).
JAX, pandas and matplotlib are imported inside :func:`run`, so the console
script stays fast to start.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from selfid_jax.robot.fit_options import LATENCY_CHOICES, MODES, FitOptions, ReadOptions
from selfid_jax.robot.read import EXAMPLE_LOG, example_log
from selfid_jax.sessions.fit_run import JINV_JSON, JINV_NPZ, SUMMARY_FILE, draw_convergence, estimate_units, redraw

__all__ = ["EXAMPLE_LOG", "add_arguments", "command", "draw_convergence", "example_log", "options", "redraw", "run"]

_READ, _FIT = ReadOptions(), FitOptions()

DESCRIPTION = (
    "Run the self-ID estimator (Eq. 6-14) over a recorded log, offline, with the convergence test of Sec. IV-D "
    "(sj.fit from Python, with the same options). "
    "LOG is a CSV, Parquet or NPZ file of sample pairs (dtheta_0.., V_0..) or of a raw time series (t, q_0.., "
    "p_x, p_y, p_z and, for rotation axes, q_w, q_x, q_y, q_z or r_x, r_y, r_z; other names through --columns and "
    "--joint-names, other units through --length/--time/--angle or a units row), or a ROS 1/ROS 2 bag or MCAP "
    "file (--joints, --tracker). The tracker may be a camera and an AprilTag (--tag): a bag's image topic "
    "(--camera) or, beside a joint log, a video or a folder of images (--video, --frame-times, --camera-info). "
    "A time series logged continuously is reduced to one settled row per move. Bad "
    "rows (non-finite, duplicated or non-monotonic time, gaps) are dropped and counted. Writes estimates.npz, "
    "summary.json (with how far to trust the fit), figures/convergence.png/.pdf and, when it converged, "
    "inverse_jacobian.npz/.json (with the trust figures and warnings, which selfid-jax online --estimate checks) "
    "into the run directory; exits 1 when it did not (or, with --strict, when a trust figure is out of bounds, "
    "and then writes no inverse_jacobian)."
)


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if math.isnan(value):
        raise argparse.ArgumentTypeError("expected a number of seconds, got nan")
    return value


def _gap(text: str) -> float | str:
    return "auto" if text.strip().lower() == "auto" else _seconds(text)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``fit`` subcommand's arguments (defaults: :class:`~selfid_jax.robot.fit_options.ReadOptions`,
    :class:`~selfid_jax.robot.fit_options.FitOptions`; the library checks the values)."""
    p.add_argument("log", type=Path, nargs="?",
                   help="CSV, Parquet or NPZ log, ROS bag or MCAP file (see the description)")
    p.add_argument("--example", action="store_true", help=f"fit the shipped UR5e example log ({EXAMPLE_LOG})")
    t = p.add_mutually_exclusive_group()
    t.add_argument("--task", default=_READ.task, metavar="AXES",
                   help="task axes out of x,y,z,rx,ry,rz, e.g. x,y,z or z,rx,ry")
    t.add_argument("--task-dim", type=int, default=_READ.task_dim, metavar="M", choices=(2, 3, 6),
                   help="task dimension: 2 (x,y), 3 (x,y,z: default for a time series) or 6 (position + rotation)")
    p.add_argument("--eps", type=float, default=_FIT.eps,
                   help="absolute Sec. IV-D threshold on ||J_t - J_{t-1}||_F, inverse-Jacobian units (default "
                   f"{_FIT.eps:g})")
    p.add_argument("--eps-rel", type=float, default=_FIT.eps_rel,
                   help=f"relative threshold, times ||J_t||_F (default {_FIT.eps_rel:g}); converged when the change is "
                   "at most eps + eps_rel ||J_t||_F twice in a row")
    p.add_argument("--refine", default=_FIT.method, metavar="METHOD",
                   help=f"Eq. 14 refinement: closed_form, optax or slsqp (final estimate only); default {_FIT.method}")
    p.add_argument("--start", type=_seconds, default=_READ.start, metavar="S", help="ignore rows before this time (s)")
    p.add_argument("--stop", type=_seconds, default=_READ.stop, metavar="S", help="ignore rows after this time (s)")
    p.add_argument("--max-gap", type=_gap, default=_READ.max_gap, metavar="S",
                   help="time series: drop pairs of rows more than S seconds apart (default auto: 3 median time "
                   "steps; inf: never)")
    p.add_argument("--out", type=Path, default=None, help="run directory (default: runs/fit_<log stem>)")
    b = p.add_argument_group("a ROS 1 / ROS 2 bag or an MCAP file (pip install \"selfid-jax[ros]\")")
    b.add_argument("--joints", default=_READ.joints, metavar="TOPIC",
                   help="the sensor_msgs/JointState topic (joints: --joint-names, default the messages' order)")
    b.add_argument("--tracker", default=_READ.tracker, metavar="TOPIC",
                   help="the tracker's geometry_msgs/PoseStamped or TransformStamped topic, or /tf with --child-frame")
    b.add_argument("--child-frame", default=_READ.child_frame, metavar="FRAME",
                   help="on a tf topic, the tracked frame (child_frame_id)")
    c = p.add_argument_group("a camera and an AprilTag as the tracker (pip install \"selfid-jax[camera]\")")
    c.add_argument("--tag", default=_READ.tag, metavar="FAMILY:ID:EDGE_M",
                   help="the tracked tag, e.g. tag36h11:7:0.05: its family, id and the edge of its black square in "
                   "metres (every position, and so the estimate, scales with the edge)")
    c.add_argument("--camera", default=_READ.camera, metavar="TOPIC",
                   help="a bag's sensor_msgs/Image or CompressedImage topic (with --joints), instead of --tracker; "
                   "intrinsics from the camera_info topic beside it, or --camera-info")
    c.add_argument("--video", type=Path, default=_READ.video, metavar="FRAMES",
                   help="beside a joint log (t, q_0..): a video file or a folder of images (sorted by file name)")
    c.add_argument("--frame-times", type=Path, default=_READ.frame_times, metavar="CSV",
                   help="with --video: a CSV with a t column, one row per frame, on the joint log's clock (its "
                   "--time unit)")
    c.add_argument("--camera-info", type=Path, default=_READ.camera_info, metavar="FILE",
                   help="the camera's intrinsics: OpenCV's or ROS's calibration YAML (selfid-jax calibrate writes "
                   "one)")
    g = p.add_argument_group("the log's layout and units")
    g.add_argument("--columns", default=_READ.columns, metavar="MAP",
                   help="rename the log's columns to the fit's: 'joint_a=q_0,tx=p_x,...' or a YAML/JSON file of "
                   "that mapping")
    g.add_argument("--joint-names", default=_READ.joint_names, metavar="NAMES",
                   help="these columns, in this order, are the actuators q_0.. (e.g. ROS names shoulder_pan_joint,"
                   "shoulder_lift_joint,...); in a bag, the JointState names")
    g.add_argument("--length", default=_READ.length, metavar="UNIT",
                   help=f"unit of the tracked positions: m, cm or mm (default {_READ.length}); converted to m")
    g.add_argument("--time", default=_READ.time, metavar="UNIT",
                   help=f"unit of t: s, ms, us or ns (default {_READ.time}); converted to s, and --start/--stop/"
                   "--max-gap are in s")
    g.add_argument("--angle", default=_READ.angle, metavar="UNIT",
                   help=f"unit of the actuator positions and rotation vectors: rad or deg (default {_READ.angle}: rad, "
                   "a joint beyond two turns refused as looking like degrees; state rad for a multi-turn joint); "
                   "converted to rad")
    g.add_argument("--mode", default=_READ.mode, metavar="|".join(MODES),
                   help="a time series logged continuously (a stream) is reduced to one settled row per move, or, "
                   "without rests, to short windows each moving the joints about m_a; auto detects a stream; stream "
                   "(rests, else windows), windows and moves (every row a move) force a reading "
                   f"(default {_READ.mode})")
    g.add_argument("--latency", default=str(_READ.latency), metavar="|".join(("S", *LATENCY_CHOICES)),
                   help="a stream's tracker latency behind the encoders (s): auto estimates it from the log (their "
                   "speeds cross-correlated for a stream with rests, a least-squares lag fit of tracker on joint "
                   f"velocity for windows); none: no shift (default {_READ.latency})")
    g.add_argument("--settle-speed", type=float, default=_READ.settle_speed, metavar="V",
                   help="a stream: joint speed below which the arm is at rest (actuator units/s; default from the "
                   "stream)")
    g.add_argument("--settle-time", type=_seconds, default=_READ.settle_time, metavar="S",
                   help="a stream: shortest rest that counts as settled (s; default from the stream)")
    g.add_argument("--strict", action="store_true", help="exit 1, and write no inverse_jacobian.npz/.json, when a "
                   "trust figure (held-out error, condition number, an actuator that did not move or barely acts, "
                   "refused fraction, a unit that looks swapped) is outside its bound")


def options(args: argparse.Namespace) -> dict:
    """``sj.fit``'s keywords from the parsed flags (flag ``--x-y`` is keyword ``x_y``; ``--refine`` is ``method``)."""
    read = {name: getattr(args, name) for name in ReadOptions._fields}
    return {**read, "eps": args.eps, "eps_rel": args.eps_rel, "method": args.refine}


def run(args: argparse.Namespace) -> int:
    """Body of ``selfid-jax fit``: fit and write (:func:`selfid_jax.sessions.fit_run.fit_to_run`), then print; bad
    input raises ``ConfigError`` (exit 2)."""
    from selfid_jax.runner.errors import ConfigError
    from selfid_jax.sessions.fit_run import default_run_dir, fit_to_run

    if args.example == (args.log is not None):
        raise ConfigError("give a LOG file or --example (not both)" if args.example else
                          "no log given: selfid-jax fit LOG (or --example for the shipped UR5e log)")
    log = example_log() if args.example else args.log
    out = args.out if args.out is not None else default_run_dir(log)
    try:
        result, files = fit_to_run(log, out, strict=bool(getattr(args, "strict", False)), **options(args))
    except ConfigError:
        raise
    except ValueError as err:  # LogError included: one line naming file, column, row
        raise ConfigError(" ".join(str(err).split())) from None
    s = result.samples
    n, m = result.estimate.shape
    print(f"{s.source}: {s.rows} rows, {s.layout.replace('_', ' ')}; {result.deltas.shape[0]} samples "
          f"(n={n}, task {','.join(s.axis_names)})")
    for note in result.notes:
        print(f"  {note}")
    for r in s.rejected:
        print(f"  {r.line()}")
    if s.outside_window:
        print(f"  {s.outside_window} rows outside --start/--stop (ignored)")
    refused = int((~result.accepted).sum())
    if refused:
        print(f"  {refused} samples refused by the estimator (all-zero dtheta or V)")
    trust = result.trust
    effect = trust.actuator_effect
    print(f"trust: held-out error {trust.heldout_error:.3g}, condition number {trust.condition:.3g}, "
          f"{100 * trust.refused_fraction:.0f}% refused, actuator effect "
          f"{min(effect, default=float('nan')):.3g}..{max(effect, default=float('nan')):.3g}")
    for w in trust.warnings:
        print(f"  warning: {w}")
    if result.converged:
        when = f", t = {result.converged_time:.3f} s" if result.converged_time is not None else ""
        print(f"converged at sample {result.converged_at} of {result.deltas.shape[0]}{when} "
              f"(eps={result.eps:g}, eps_rel={result.eps_rel:g})")
        if JINV_NPZ in files:
            print(f"inverse Jacobian ({n}x{m}, {', '.join(sorted(set(estimate_units(s.axis_names))))}): "
                  f"{files[JINV_NPZ]} (and {JINV_JSON}; with its trust figures)")
        else:
            print(f"--strict: {len(trust.warnings)} trust warning(s): no inverse Jacobian written (the estimate is "
                  f"in {Path(out) / SUMMARY_FILE}, estimate_so_far)")
    else:
        print(f"not converged in {result.deltas.shape[0]} samples (eps={result.eps:g}, eps_rel={result.eps_rel:g}; "
              f"last change {result.deltas[-1]:.3g} > {result.thresholds[-1]:.3g}): no inverse Jacobian written "
              f"(the estimate so far is in {Path(out) / SUMMARY_FILE})")
    print(f"results: {out}")
    if not result.converged:
        return 1
    return 1 if args.strict and trust.warnings else 0


def command():
    """The ``fit`` subcommand for :func:`selfid_jax.runner.command_line.main`."""
    from selfid_jax.runner.command_line import Command

    return Command(help="self-ID from a recorded log (CSV, Parquet, NPZ, ROS bag, MCAP; a camera and an AprilTag) "
                   "into a run directory",
                   description=DESCRIPTION, add_arguments=add_arguments, run=run, plot=redraw)
