"""``selfid-jax online CONFIG``: self-ID a connected robot live (Algorithm 1), then optionally follow a path.

    selfid-jax online CONFIG [--resume] [--out DIR] [--set key.sub=value ...] [--quiet] [--estimate FILE]

CONFIG (YAML, strict: unknown keys, wrong types and out-of-range values are
refused with the dotted key, before connecting)::

    robot:                      # either the TCP client of `selfid-jax robot-sim` ...
      host: 127.0.0.1
      port: 50007
      timeout_s: 5.0
    # robot: {driver: "package.module:Class", args: {...}}   # ... or a user's driver, Class(**args)
    selfid: {task: "x,y,z", m_a: 0.03, eps: 0.0, eps_rel: 0.05, max_samples: 200, seed: 0,
             settle_s: 0.2, poll_s: 0.01, method: closed_form, v_tol: 1.0e-9}
    safety: {box_low: [x, y, z], box_high: [x, y, z], max_step: 0.05, stale_s: 1.0, diverge_dist: 0.05,
             limits_lower: [...], limits_upper: [...]}
    path: {kind: star, size: 0.02, plane: xy, gain: 0.5, tol: 0.002, max_task_step: 0.005, steps: 500}
    # path: {kind: waypoints, waypoints: [[0.01, 0, 0], [0.01, 0.01, 0]]}  # offsets, m (rad for rx, ry, rz)
    # path: {kind: csv, file: square.csv}     # header the task axes (x,y,z), one waypoint offset per row
    out: runs/online_ur5e       # default runs/online_<config stem>; --out wins

:func:`selfid_jax.robot.live.run_online` does the session under the run
directory's lock; the session log ``session.jsonl`` is appended as it
happens, and at the end this writes, each whole
(:mod:`selfid_jax.runner.files`): ``online_config.json`` (the resolved
config), ``summary.json`` (status, counts, step latency) and
``inverse_jacobian.npz`` / ``.json`` (the estimate, as ``selfid-jax fit``
writes it) and the figures ``figures/convergence`` and, after following,
``figures/path`` (.png/.pdf; :mod:`selfid_jax.commands.online_figures`, from
the log: ``selfid-jax plot RUN`` redraws them). ``--resume`` continues a
stopped session from its log. ``--estimate FILE`` follows the path with the
inverse Jacobian of ``selfid-jax fit`` or of an earlier session instead of
self-identifying (no random move; logged as an ``estimate`` record, so
``--resume`` continues with it). While the session runs, a progress line per
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

Size: about 600 lines, one command: its strict config schema (every key documented for the config reference),
its run, the progress line, the summary and the files of a run; the figures are in
:mod:`selfid_jax.commands.online_figures`.
"""

from __future__ import annotations

import argparse
import importlib
import io
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax.robot.options import FollowOptions, OnlineOptions
from selfid_jax.runner.config import STRICT

if TYPE_CHECKING:
    from selfid_jax.robot.live import OnlineResult

__all__ = ["OnlineConfig", "ProgressLine", "add_arguments", "command", "connect", "options", "run", "summary"]

SUMMARY_FILE = "summary.json"
CONFIG_JSON = "online_config.json"
JINV_NPZ = "inverse_jacobian.npz"
JINV_JSON = "inverse_jacobian.json"

DESCRIPTION = (
    "Self-identify a connected robot's inverse Jacobian live (Algorithm 1: random actuations within m_a and the "
    "limits, the estimator after each sample, the Sec. IV-D convergence test; no random move after convergence), "
    "then follow a path with the estimate if the config has one. A safety envelope (actuator limits, a task-space "
    "box, a step cap, a stale-tracker watchdog, a divergence stop) holds throughout. Every observation, command "
    "and sample is appended to RUN/session.jsonl as it happens; --resume continues a stopped session from it."
)

Positive = Annotated[float, Field(gt=0)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class RobotSection(BaseModel):
    """How to reach the robot: ``host``/``port`` (the TCP client) or ``driver``/``args`` (a user's class)."""

    model_config = STRICT

    host: str | None = Field(None, description="robot server's host (selfid-jax robot-sim or a bridge)")
    port: int | None = Field(None, ge=1, le=65535)
    timeout_s: float = Field(5.0, gt=0, description="s, the TCP client's timeout per request")
    driver: str | None = Field(None, description="'package.module:Class' of a driver implementing Robot")
    args: dict[str, Any] = Field(default_factory=dict, description="keyword arguments of the driver class")

    @model_validator(mode="after")
    def _one_form(self):
        tcp, drv = self.host is not None or self.port is not None, self.driver is not None
        if tcp == drv:
            raise ValueError("give either host and port (the TCP client) or driver (a user's driver class), "
                             "not both" if tcp else "give host and port, or driver")
        if tcp and (self.host is None or self.port is None):
            raise ValueError("the TCP client needs both host and port")
        if self.args and not drv:
            raise ValueError("args are for a driver class")
        if drv and ":" not in str(self.driver):
            raise ValueError(f"driver must be 'package.module:Class', got {self.driver!r}")
        return self


_SELFID = OnlineOptions._field_defaults  # the one place each online default is written (selfid_jax.robot.options)
_PATH = FollowOptions._field_defaults


class SelfIDSection(BaseModel):
    """Algorithm 1's settings (:class:`~selfid_jax.robot.options.OnlineOptions`, whose defaults these are)."""

    model_config = STRICT

    task: str = Field(_SELFID["task"], description="task axes out of x,y,z,rx,ry,rz")
    m_a: Positive | list[Positive] = Field(_SELFID["m_a"], description="self-ID magnitude, actuator units, scalar or "
                                           "per actuator")
    eps: float = Field(_SELFID["eps"], ge=0, description="absolute Sec. IV-D threshold")
    eps_rel: float = Field(_SELFID["eps_rel"], ge=0, description="relative Sec. IV-D threshold")
    max_samples: int = Field(_SELFID["max_samples"], ge=1, le=10**7, description="most random moves")
    min_samples: int | None = Field(_SELFID["min_samples"], ge=0, le=10**7, description="accepted samples before "
                                    "Sec. IV-D may declare convergence (null: 5 per task axis)")
    seed: int = Field(_SELFID["seed"], ge=0, le=2**32 - 1)
    wander: float | None = Field(_SELFID["wander"], ge=0.5, description="self-ID keeps each actuator within wander "
                                 "m_a of where it started (multiples of m_a; null: an unbounded random walk)")
    settle_s: float = Field(_SELFID["settle_s"], ge=0, description="s after each move before reading")
    poll_s: float = Field(_SELFID["poll_s"], gt=0, description="s between reads while waiting for a fresh pose")
    method: Literal["closed_form", "optax"] = _SELFID["method"]
    v_tol: float = Field(_SELFID["v_tol"], ge=0)

    @field_validator("task")
    @classmethod
    def _task(cls, v: str) -> str:
        from selfid_jax.robot.log import parse_task

        parse_task(v)
        return v


class SafetySection(BaseModel):
    """The safety envelope (:class:`selfid_jax.robot.safety.Envelope`; defaults from
    :class:`~selfid_jax.robot.options.OnlineOptions`)."""

    model_config = STRICT

    box_low: Vec3 | None = Field(_SELFID["box_low"], description="m, lowest tracked x, y, z")
    box_high: Vec3 | None = Field(_SELFID["box_high"], description="m, highest tracked x, y, z")
    max_step: Positive | list[Positive] | None = Field(_SELFID["max_step"], description="actuator units per move; "
                                                       "default the driver's")
    stale_s: float = Field(_SELFID["stale_s"], gt=0, description="s, tracker watchdog")
    diverge_dist: float = Field(_SELFID["diverge_dist"], gt=0, description="m, distance from the path (its position "
                                "axes) that stops following")
    limits_lower: list[float] | None = Field(_SELFID["lower"], description="actuator units, narrows the driver's "
                                             "limits")
    limits_upper: list[float] | None = _SELFID["upper"]
    seen_min: float = Field(_SELFID["seen_min"], gt=0, description="m, a tracked position change below this is "
                            "not seen (motion versus sight)")
    seen_min_rad: float = Field(_SELFID["seen_min_rad"], gt=0, description="rad, an orientation change below this "
                                "is not seen")
    frozen_motion: Positive | None = Field(_SELFID["frozen_motion"], description="actuator units moved with no "
                                           "change seen that stop (tracker_frozen); default 3 max(m_a)")
    frozen_dist: float = Field(_SELFID["frozen_dist"], gt=0, description="m of motion the estimate predicts, while "
                               "following, with no change seen that stop (tracker_frozen)")
    follow_min_ratio: float = Field(_SELFID["follow_min_ratio"], gt=0, le=1, description="an actuator that moves "
                                    "less than this fraction of its commands stops the session (actuator)")
    follow_min_moves: int = Field(_SELFID["follow_min_moves"], ge=1, description="moves before the command-"
                                  "following and held-out checks apply")
    follow_max_residual: float = Field(_SELFID["follow_max_residual"], gt=0, description="while following, the "
                                       "estimate's prediction error of the tracked motion, relative, that stops "
                                       "(estimate)")
    max_heldout_error: float = Field(_SELFID["max_heldout_error"], gt=0, description="at convergence, the "
                                     "samples' leave-one-out error of the tracked motion, relative, that stops "
                                     "before following (estimate)")


class PathSection(BaseModel):
    """The path followed after convergence and the follow law's settings
    (:class:`~selfid_jax.robot.options.FollowOptions`, whose defaults these are)."""

    model_config = STRICT

    kind: Literal["star", "waypoints", "csv"] = Field(_PATH["kind"], description="the shipped star, the rows of "
                                                      "waypoints, or the rows of the CSV file")
    size: float = Field(_PATH["size"], gt=0, description="m, the star's outer radius (kind star)")
    plane: Literal["xy", "xz", "yz"] = Field(_PATH["plane"], description="the star's plane (kind star)")
    waypoints: list[list[float]] | None = Field(_PATH["waypoints"], description="kind waypoints: one row per "
                                                "waypoint, its offset from where following starts, one value per "
                                                "task axis (m for x, y, z; rad for rx, ry, rz)")
    file: str | None = Field(_PATH["file"], description="kind csv: a CSV file, its header the task axes (e.g. "
                             "x,y,z), one waypoint offset per row in the units of waypoints; a relative path is "
                             "looked up beside the config, then in the current directory")
    gain: float = Field(_PATH["gain"], gt=0, le=1)
    tol: float = Field(_PATH["tol"], gt=0, description="m, position error at which a waypoint counts as reached")
    max_task_step: float = Field(_PATH["max_task_step"], gt=0, description="m, cap on the twist's position part "
                                 "per move")
    steps: int = Field(_PATH["steps"], ge=1, le=10**7)
    rot_tol: float = Field(_PATH["rot_tol"], gt=0, description="rad, rotation error at which a waypoint counts as "
                           "reached (tasks with rotation axes)")
    max_rot_step: float = Field(_PATH["max_rot_step"], gt=0, description="rad, cap on the twist's rotation part "
                                "per move")


class OnlineConfig(BaseModel):
    """The ``selfid-jax online`` config."""

    model_config = STRICT

    robot: RobotSection
    selfid: SelfIDSection = Field(default_factory=SelfIDSection)
    safety: SafetySection = Field(default_factory=SafetySection)
    path: PathSection | None = None
    out: str | None = None


def options(cfg: OnlineConfig, config_dir: Path | None = None, estimate: str | Path | None = None) -> OnlineOptions:
    """The config as :class:`~selfid_jax.robot.options.OnlineOptions` (the same names, one level flatter).

    A relative ``path.file`` is taken from ``config_dir`` (the config's
    folder) where it is there, else as given (the current directory).
    ``estimate``: ``--estimate FILE`` (OnlineOptions.estimate).
    """
    s, f = cfg.selfid, cfg.safety
    path = None if cfg.path is None else FollowOptions(**cfg.path.model_dump())
    if path is not None and path.file is not None and config_dir is not None and not Path(path.file).is_absolute() \
            and (config_dir / path.file).is_file():
        path = path._replace(file=str(config_dir / path.file))
    return OnlineOptions(task=s.task, m_a=s.m_a, eps=s.eps, eps_rel=s.eps_rel, max_samples=s.max_samples, seed=s.seed,
                         wander=s.wander, min_samples=s.min_samples,
                         settle_s=s.settle_s, poll_s=s.poll_s, method=s.method, v_tol=s.v_tol, lower=f.limits_lower,
                         upper=f.limits_upper, max_step=f.max_step, box_low=f.box_low, box_high=f.box_high,
                         stale_s=f.stale_s, diverge_dist=f.diverge_dist, seen_min=f.seen_min,
                         seen_min_rad=f.seen_min_rad, frozen_motion=f.frozen_motion, frozen_dist=f.frozen_dist,
                         follow_min_ratio=f.follow_min_ratio, follow_min_moves=f.follow_min_moves,
                         follow_max_residual=f.follow_max_residual, max_heldout_error=f.max_heldout_error,
                         path=path, estimate=None if estimate is None else str(estimate))


def import_driver(spec: str, config_dir: Path | None = None):
    """The factory named by ``'package.module:Class'``, its module imported as Python would, else from the
    config's folder, else from the current directory (a driver file beside the config needs no install)."""
    import sys

    module, _, name = spec.partition(":")
    extra = [str(p) for p in (config_dir, Path.cwd()) if p is not None and str(p) not in sys.path]
    try:
        return getattr(importlib.import_module(module), name)
    except ModuleNotFoundError as err:
        if err.name != module.split(".")[0] or not extra:
            raise
    sys.path[:0] = extra
    try:
        return getattr(importlib.import_module(module), name)
    finally:
        for p in extra:
            sys.path.remove(p)


def connect(section: RobotSection, config_dir: Path | None = None):
    """A connected :class:`~selfid_jax.robot.protocol.Robot` from the config's ``robot`` section.

    A ``driver`` module is found as Python finds it, else in ``config_dir``
    (the config's folder), else in the current directory. Raises ConfigError
    naming ``robot.driver`` / ``robot.host`` when the driver cannot be
    imported, is not a Robot, or the connection fails.
    """
    from selfid_jax.robot.protocol import Robot, RobotError
    from selfid_jax.runner.errors import ConfigError

    if section.driver is not None:
        key = "robot.driver"
        try:
            factory = import_driver(section.driver, config_dir)
        except (ImportError, AttributeError) as err:
            raise ConfigError(f"{key}: cannot import {section.driver!r} (looked on the Python path, in the "
                              f"config's folder and in the current directory): {err}") from None
        try:
            robot = factory(**section.args)
        except (RobotError, OSError) as err:
            raise ConfigError(f"{key}: cannot connect with {section.driver}: {err}") from None
    else:
        key = "robot.host"
        from selfid_jax.robot.transport import RemoteRobot

        try:
            robot = RemoteRobot(str(section.host), int(section.port or 0), timeout_s=section.timeout_s)
        except (RobotError, OSError) as err:
            raise ConfigError(f"{key}: cannot connect to {section.host}:{section.port}: {err}") from None
    if not isinstance(robot, Robot):
        raise ConfigError(f"{key}: {type(robot).__name__} does not implement the Robot protocol "
                          "(limits, read, move, close)")
    return robot


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``online`` subcommand's arguments."""
    p.add_argument("config", type=Path, help="YAML config (see the description and configs/robot/online_ur5e.yaml)")
    p.add_argument("--resume", action="store_true", help="continue the session logged in the run directory")
    p.add_argument("--out", type=Path, default=None, help="run directory (default: the config's out, else "
                   "runs/online_<config stem>)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set selfid.m_a=0.02 (repeatable)")
    p.add_argument("--estimate", type=Path, default=None, metavar="FILE",
                   help="follow the config's path with this estimate instead of self-identifying (no random move): "
                   "the inverse_jacobian.npz of selfid-jax fit or of an earlier online session; refused unless its "
                   "task axes are the config's and its shape (actuators, task axes) the robot's")
    p.add_argument("--quiet", action="store_true", help="no progress line (one per self-ID sample and following "
                   "move, updated in place on a terminal); the final report is still printed")


class ProgressLine:
    """The live progress of ``selfid-jax online``: one line per session event
    (:func:`selfid_jax.robot.live.run_online`'s ``progress``) on ``stream``, or on a terminal one line rewritten in
    place (carriage return) per phase."""

    def __init__(self, stream=None, tty: bool | None = None):
        import sys

        self.stream = sys.stdout if stream is None else stream
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)()) if tty is None else tty
        self.width = 0  # length of the line shown in place (tty)
        self.phase: str | None = None

    @staticmethod
    def line(event: dict[str, Any]) -> str:
        """The text of one event."""
        phase = event["phase"]
        if phase == "selfid":
            head = f"self-ID  move {event['move']:4d}  sample {event['sample']:4d}"
            if not event["accepted"]:
                return f"{head}  rejected ({event['reason']})"
            conv = event.get("converged_at", -1)
            ok = "converged" if conv > 0 else ("below" if event["delta"] <= event["threshold"] else "above")
            return (f"{head}  |J_t - J_t-1| {event['delta']:.3e}  threshold {event['threshold']:.3e}  {ok}"
                    + ("" if event.get("estimator_accepted", True) else "  (refused by the estimator)"))
        if phase == "follow":
            return (f"follow   move {event['step']:4d}  waypoint {event['waypoint']}/{event['waypoints']}  "
                    f"path distance {1e3 * event['distance']:.3f} mm")
        return f"stop: {event['status']}: {event['detail']}"

    def __call__(self, event: dict[str, Any]) -> None:
        text = self.line(event)
        if not self.tty:
            print(text, file=self.stream, flush=True)
            return
        if self.width and (event["phase"] != self.phase or event["phase"] == "stop"):
            self.stream.write("\n")  # keep the last line of the phase before
            self.width = 0
        self.phase = event["phase"]
        if event["phase"] == "stop":
            self.stream.write(text + "\n")
        else:
            self.stream.write("\r" + text.ljust(self.width))
            self.width = len(text)
        self.stream.flush()


def summary(result: OnlineResult, cfg: OnlineConfig) -> dict[str, Any]:
    """``summary.json`` of a session: its stop, counts, convergence and the estimator step's latency."""
    import numpy as np

    from selfid_jax.robot.quality import condition
    from selfid_jax.systems.validation import AXIS_NAMES

    ms = result.step_ms
    n, m = result.estimate.shape
    return {
        "command": "online",
        "status": result.status.value,
        "detail": result.detail,
        "n": n,
        "m": m,
        "task_axes": [AXIS_NAMES[a] for a in result.axes],
        "converged": result.converged,
        "converged_at": result.converged_at,
        "samples": result.samples,
        "rejected": result.rejected,
        "moves": result.moves,
        "follow_steps": result.follow_steps,
        "follow_rejected": result.follow_rejected,
        "heldout_error": None if result.quality is None else result.quality.heldout_error,
        # ||J Ĵ - I||_F against the driver's model Jacobian where self-ID started (a driver with jacobian())
        "reference_error": result.reference_error,
        "actuator_effect": None if result.quality is None else result.quality.effect,
        # the estimate's condition number s_max / s_min (selfid_jax.robot.quality.condition), as selfid-jax fit reports
        "condition": condition(result.estimate) if result.converged else None,
        "waypoints": result.waypoints,
        "waypoints_total": result.waypoints_total,
        "replayed": result.replayed,
        "estimate_source": result.estimate_source,  # --estimate: the file followed with (no self-ID); else None
        "truncated_log_lines": result.truncated,
        # while following, the tracked point's distance from the path after each move [m] (every session of the log)
        "track_mean_m": float(np.nanmean(result.track)) if result.track.size else None,
        "track_max_m": float(np.nanmax(result.track)) if result.track.size else None,
        "selfid_s": result.selfid_s,  # wall time of self-ID [s]: moves, settling, reads, the estimator
        "follow_s": result.follow_s,  # wall time following the path [s]
        "step_ms_p50": float(np.percentile(ms, 50)) if ms.size else None,
        "step_ms_p99": float(np.percentile(ms, 99)) if ms.size else None,
        "eps": cfg.selfid.eps,
        "eps_rel": cfg.selfid.eps_rel,
        "log": str(result.log),
    }


def _npz(**arrays) -> bytes:
    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _check_sizes(cfg: OnlineConfig, n: int, path: Path) -> None:
    """Per-actuator config values against the robot's ``n`` (known once connected; before any motion)."""
    from selfid_jax.runner.errors import ConfigError

    for key, value in (("selfid.m_a", cfg.selfid.m_a), ("safety.max_step", cfg.safety.max_step),
                       ("safety.limits_lower", cfg.safety.limits_lower),
                       ("safety.limits_upper", cfg.safety.limits_upper)):
        if isinstance(value, list) and len(value) != n:
            raise ConfigError(f"{path}: key '{key}': {len(value)} values, but the robot has {n} actuators")


def run(args: argparse.Namespace) -> int:
    """Body of ``selfid-jax online``: validate, connect, run the session, write the summary; the exit code."""
    from selfid_jax.runner.config import read_config, validate
    from selfid_jax.runner.errors import ConfigError, RunDirError

    data, set_keys = read_config(args.config, args.overrides)
    cfg: OnlineConfig = validate(OnlineConfig, data, args.config, set_keys)  # type: ignore[arg-type,assignment]

    import jax

    jax.config.update("jax_enable_x64", True)  # one estimator per process: float64, like `fit`
    from selfid_jax.robot import live
    from selfid_jax.robot.log import parse_task

    estimate = getattr(args, "estimate", None)
    if estimate is not None and cfg.path is None:
        raise ConfigError(f"{args.config}: --estimate {estimate}: following with a given estimate needs a path "
                          "section in the config")
    if estimate is not None and not Path(estimate).is_file():
        raise ConfigError(f"--estimate {estimate}: no such file")
    opts = options(cfg, Path(args.config).resolve().parent, estimate)
    if opts.path is not None:
        try:
            opts.path.offsets(parse_task(opts.task) or ())
        except ValueError as err:
            raise ConfigError(f"{args.config}: {err}") from None
    out = args.out if args.out is not None else Path(cfg.out) if cfg.out else \
        Path("runs") / f"online_{args.config.stem}"
    if (out / "config.yaml").exists():
        raise RunDirError(f"{out}: holds a sweep's run directory (config.yaml); choose another --out")
    log = out / live.LOG_FILE
    if log.exists() and not args.resume:
        raise RunDirError(f"{out}: already holds a session log ({live.LOG_FILE}); continue it with --resume or "
                          "choose another --out")
    if args.resume and not log.exists():
        raise RunDirError(f"{out}: no session log ({live.LOG_FILE}) to resume; run without --resume")

    import threading

    from selfid_jax.runner import signals
    from selfid_jax.runner.config import dump_config
    from selfid_jax.runner.files import write_json
    from selfid_jax.runner.lock import hold

    stop = threading.Event()
    with hold(out):
        signals.phase("connect")
        robot = connect(cfg.robot, Path(args.config).resolve().parent)
        try:  # run_online closes the robot however it ends; close (idempotent) here too if it never starts
            from selfid_jax.robot.protocol import RobotError, check_limits

            try:
                n = check_limits(robot.limits()).lower.shape[0]
            except (RobotError, ValueError) as err:
                raise ConfigError(f"robot: its limits cannot be used: {err}") from None
            _check_sizes(cfg, n, args.config)
            write_json(out / CONFIG_JSON, dump_config(cfg))
            signals.phase("online")
            try:
                with signals.graceful(f"selfid-jax online: interrupted; the session log {log} is intact "
                                      "(continue with --resume)", stop.set, interrupt=True,
                                      last_words=lambda: _log_killed(log)):
                    result = live.run_online(robot, opts, out, resume=args.resume, stop_requested=stop.is_set,
                                             progress=None if getattr(args, "quiet", False) else ProgressLine())
            except ValueError as err:  # bad options, a log that disagrees: all before any motion
                raise ConfigError(f"{args.config}: {' '.join(str(err).split())}") from None
        finally:
            robot.close()
        signals.phase("write")
        files = write_run(result, cfg, out)
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


def _log_killed(log: Path) -> None:
    """Append the stop record of a process that a second signal ends at once (called from the signal thread)."""
    from selfid_jax.robot.journal import Journal

    with Journal(log) as journal:
        journal.append({"e": "stop", "reason": "killed", "detail": "a second signal ended the process at once; the "
                        "robot's connection closes with it (continue with --resume)"})


def write_run(result: OnlineResult, cfg: OnlineConfig, out: Path) -> dict[str, Path]:
    """Write ``summary.json`` and, for a converged session only, ``inverse_jacobian.npz``/``.json`` into ``out`` (each
    atomically); a session that did not converge has its estimate so far in the summary (``estimate_so_far``)."""
    import numpy as np

    from selfid_jax.identify import estimator
    from selfid_jax.runner.files import atomic_write_bytes, write_json

    info = summary(result, cfg)
    meta = {k: info[k] for k in ("n", "m", "task_axes", "converged_at", "converged", "samples", "eps", "eps_rel",
                                 "status")}
    guess = np.asarray(estimator.initial_guess(result.state))
    paths = {SUMMARY_FILE: out / SUMMARY_FILE}
    if result.converged:  # a session that never converged writes no file that could be taken for a result
        paths.update({name: out / name for name in (JINV_NPZ, JINV_JSON)})
        atomic_write_bytes(paths[JINV_NPZ], _npz(
            inverse_jacobian=result.estimate, initial_guess=guess, task_axes=np.array(info["task_axes"]),
            **{k: np.asarray(v) for k, v in meta.items() if k != "task_axes"}))
        write_json(paths[JINV_JSON], {"inverse_jacobian": result.estimate, "initial_guess": guess, **meta,
                                      "log": str(result.log)})
    else:
        info["estimate_so_far"] = result.estimate if result.samples else None  # not converged: not a result
    write_json(paths[SUMMARY_FILE], info)
    from selfid_jax.commands.online_figures import write_figures

    for f in write_figures(out):  # from the session log, as `selfid-jax plot RUN` redraws them
        paths[f"figures/{f.name}"] = f
    return paths


def _report(result: OnlineResult, files: dict[str, Path]) -> None:
    rejected = ", ".join(f"{v} {k}" for k, v in result.rejected.items()) or "none"
    resumed = f" ({result.replayed} replayed from the log)" if result.replayed else ""
    print(f"self-ID: {result.samples} samples{resumed}, {result.moves} random moves, rejected: {rejected}")
    if result.converged:
        print(f"converged at sample {result.converged_at}")
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
    """``selfid-jax plot RUN`` of an online run directory (:func:`selfid_jax.commands.online_figures.redraw`)."""
    from selfid_jax.commands.online_figures import redraw

    return redraw(run_dir)
