"""``selfid-jax online CONFIG``: self-ID a connected robot live (Algorithm 1), then optionally follow a path.

    selfid-jax online CONFIG [--resume] [--out DIR] [--set key.sub=value ...] [--quiet]
                             [--estimate FILE [--accept-flagged-estimate]]

CONFIG (YAML, strict: unknown keys, wrong types and out-of-range values are
refused with the dotted key, before connecting): its schema, with an
example, is :mod:`selfid_jax.sessions.online_config`.

:func:`selfid_jax.sessions.online_run.run_session` does the session
(:func:`selfid_jax.robot.live.run_online`) under the run directory's lock;
the session log ``session.jsonl`` is appended as it happens, and at the end
it writes, each whole (:mod:`selfid_jax.runner.files`): ``online_config.json``
(the resolved config), ``summary.json`` (status, counts, step latency) and
``inverse_jacobian.npz`` / ``.json`` (the estimate, as ``selfid-jax fit``
writes it) and the figures ``figures/convergence`` and, after following,
``figures/path`` (.png/.pdf; :mod:`selfid_jax.sessions.online_figures`, from
the log: ``selfid-jax plot RUN`` redraws them). This command parses the
arguments, calls it and prints the report. ``--resume`` continues a
stopped session from its log. ``--estimate FILE`` follows the path with the
inverse Jacobian of ``selfid-jax fit`` or of an earlier session instead of
self-identifying (no random move; logged as an ``estimate`` record, so
``--resume`` continues with it); its trust figures are printed first and
one whose file is flagged (trust warnings, or not converged) is refused
(exit 2) unless ``--accept-flagged-estimate``; a file written before
estimate files carried trust figures is followed with a line saying so.
While the session runs, a progress line per
self-ID sample and following move goes to stdout (in place on a terminal;
none with ``--quiet``).

Exit codes: 0 converged (or path completed); 1 a stop of the session's own
(max_samples, max_steps, stale, box, limits, divergence, moved: the summary says
which); 2 bad input (config, run directory, a log that disagrees), before any
motion; 3 the robot or its driver failed (connection, robot_error, and
driver_error for any exception a driver raises that is not a RobotError);
4 the runner itself failed (error; the log keeps the traceback); 130
interrupted. Every one of these is a stop record in the log, a closed robot
and a ``summary.json``; only a converged session writes
``inverse_jacobian.npz`` / ``.json``. A first SIGTERM or Ctrl-C stops the
session cleanly after the move in flight (the robot is closed, the log ends
with the stop); a second one ends the process at once, like a crash, after
appending a ``killed`` stop record: the log then lacks at most the line in
flight and ``--resume`` continues.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from selfid_jax.robot.live import OnlineResult

__all__ = ["add_arguments", "command", "exit_code", "run"]

DESCRIPTION = (
    "Self-identify a connected robot's inverse Jacobian live (Algorithm 1: random actuations within m_a and the "
    "limits, the estimator after each sample, the Sec. IV-D convergence test; no random move after convergence), "
    "then follow a path with the estimate if the config has one. A safety envelope (actuator limits, a task-space "
    "box, a step cap, a stale-tracker watchdog, a divergence stop) holds throughout. Every observation, command "
    "and sample is appended to RUN/session.jsonl as it happens; --resume continues a stopped session from it."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``online`` subcommand's arguments."""
    p.add_argument("config", type=Path,
                   help="YAML config, or a shipped one by name (online_ur5e, online_trossen_sim, ...)")
    p.add_argument("--resume", action="store_true", help="continue the session logged in the run directory")
    p.add_argument("--out", type=Path, default=None, help="run directory (default: the config's out, else "
                   "runs/online_<config stem>)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set selfid.m_a=0.02 (repeatable)")
    p.add_argument("--estimate", type=Path, default=None, metavar="FILE",
                   help="follow the config's path with this estimate instead of self-identifying (no random move): "
                   "the inverse_jacobian.npz of selfid-jax fit or of an earlier online session; refused unless its "
                   "task axes are the config's and its shape (actuators, task axes) the robot's. Its trust figures "
                   "are shown first; one flagged (trust warnings, or not converged) is refused unless "
                   "--accept-flagged-estimate")
    p.add_argument("--accept-flagged-estimate", action="store_true",
                   help="follow with an --estimate whose file carries trust warnings (or did not converge) instead "
                   "of refusing it")
    p.add_argument("--quiet", action="store_true", help="no progress line (one per self-ID sample and following "
                   "move, updated in place on a terminal); the final report is still printed")


def run(args: argparse.Namespace) -> int:
    """Body of ``selfid-jax online``: validate, run the session (:func:`selfid_jax.sessions.online_run.run_session`),
    print the report; the exit code."""
    from selfid_jax.runner.command_line import find_config
    from selfid_jax.sessions.online_config import default_out, load_online_config

    args.config = find_config(args.config, args.config_dirs)  # a path, or a shipped config by name
    cfg = load_online_config(args.config, args.overrides)

    import jax

    jax.config.update("jax_enable_x64", True)  # one estimator per process: float64, like `fit`
    from selfid_jax.sessions.online_progress import ProgressLine
    from selfid_jax.sessions.online_run import run_session

    out = args.out if args.out is not None else default_out(cfg, args.config)
    estimate = getattr(args, "estimate", None)
    accept = bool(getattr(args, "accept_flagged_estimate", False))
    if estimate is not None and cfg.path is not None:  # its trust figures, before anything connects or moves
        from selfid_jax.sessions.online_run import check_estimate

        for line in check_estimate(estimate, cfg.selfid.task, accept_flagged=accept):
            print(line)
    result, files = run_session(cfg, out, config_path=args.config, resume=args.resume, estimate=estimate,
                                progress=None if getattr(args, "quiet", False) else ProgressLine(),
                                accept_flagged_estimate=accept)
    _report(result, files)
    return exit_code(result.status)


def exit_code(status) -> int:
    """The exit code of a session that ended with ``status`` (a :class:`selfid_jax.robot.session.Stop`): 0 converged
    or path completed; 1 a stop of the session's own (max_samples, max_steps, stale, box, limits, divergence, moved);
    3 the robot or its driver failed (connection, robot_error, driver_error); 4 the runner failed (error); 130
    interrupted. Bad input (config, run directory, a log that disagrees) exits 2 before any motion."""
    from selfid_jax.robot.session import Stop

    if status in (Stop.CONVERGED, Stop.COMPLETED):
        return 0
    if status == Stop.INTERRUPTED:
        return 130
    if status in (Stop.CONNECTION, Stop.ROBOT_ERROR, Stop.DRIVER_ERROR):
        return 3
    return 4 if status == Stop.ERROR else 1


def _report(result: OnlineResult, files: dict[str, Path]) -> None:
    """Print what the session did: counts, wall times [s], tracking error [mm], step latency [ms], its stop and
    the files."""
    from selfid_jax.sessions.online_run import JINV_JSON, JINV_NPZ, SUMMARY_FILE

    rejected = ", ".join(f"{v} {k}" for k, v in result.rejected.items()) or "none"
    resumed = f" ({result.replayed} replayed from the log)" if result.replayed else ""
    print(f"self-ID: {result.samples} samples{resumed}, {result.moves} random moves, rejected: {rejected}")
    if result.converged:
        print(f"converged at sample {result.converged_at}")
    elif result.estimate_source is not None and result.given_converged_at is not None:
        print(f"the estimate's own self-ID converged at sample {result.given_converged_at} ({result.estimate_source})")
    if result.trust is not None:
        t = result.trust
        print(f"trust: held-out error {t.heldout_error:.3g}, condition number {t.condition:.3g}")
        for w in t.warnings:
            print(f"  warning: {w}")
    if result.reference_error is not None:
        where = "following started" if result.estimate_source is not None else "self-ID started"
        print(f"against the driver's model Jacobian J where {where}: ||J Ĵ - I||_F {result.reference_error:.3g}")
    print(f"wall time: self-ID {result.selfid_s:.1f} s, following {result.follow_s:.1f} s")
    if result.waypoints_total:
        print(f"follow: {result.waypoints}/{result.waypoints_total} waypoints in {result.follow_steps} moves")
    if result.track.size:
        import numpy as np

        print(f"tracking error: path distance mean {1e3 * np.nanmean(result.track):.3f} mm, "
              f"max {1e3 * np.nanmax(result.track):.3f} mm over {result.track.size} moves")
    if result.step_ms.size:
        import numpy as np

        print(f"estimator step: p50 {np.percentile(result.step_ms, 50):.3f} ms, "
              f"p99 {np.percentile(result.step_ms, 99):.3f} ms per sample")
    print(f"stopped: {result.status.value}: {result.detail}")
    if result.close_error is not None:  # beside the stop, never in its place
        print(f"note: {result.close_error}")
    if result.estimate_source is not None:
        print(f"followed with the estimate from {result.estimate_source} (no self-ID); log: {result.log}")
    elif JINV_NPZ in files:
        print(f"inverse Jacobian: {files[JINV_NPZ]} (and {JINV_JSON}); log: {result.log}")
    else:
        print(f"not converged: no inverse Jacobian written (the estimate so far is in {files[SUMMARY_FILE]}); "
              f"log: {result.log}")
    for name, f in files.items():
        if name.startswith("figures/") and f.suffix == ".png":
            print(f"figure: {f}")


def command():
    """The ``online`` subcommand for :func:`selfid_jax.runner.command_line.main`."""
    from selfid_jax.runner.command_line import Command

    return Command(help="self-ID a connected robot live (Algorithm 1), then follow a path; resumable",
                   description=DESCRIPTION, add_arguments=add_arguments, run=run, plot=_redraw)


def _redraw(run_dir: Path):
    """``selfid-jax plot RUN`` of an online run directory (:func:`selfid_jax.sessions.online_figures.redraw`)."""
    from selfid_jax.sessions.online_figures import redraw

    return redraw(run_dir)
