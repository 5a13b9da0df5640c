"""The ``selfid-jax online`` config: a strict schema of a live session's robot, self-ID, safety and path sections.

The YAML a lab writes for ``selfid-jax online CONFIG`` (and for
:func:`selfid_jax.sessions.online_run.run_session`)::

    robot:                      # either the TCP client of `selfid-jax robot-sim` ...
      host: 127.0.0.1
      port: 50007
      timeout_s: 5.0
    # robot: {driver: franka, args: {host: 172.16.0.2}}     # ... or a shipped driver (franka, trossen) ...
    # robot: {driver: "package.module:Class", args: {...}}   # ... or a user's driver, Class(**args)
    selfid: {task: "x,y,z", m_a: 0.03, eps: 0.0, eps_rel: 0.05, max_samples: 200, seed: 0,
             settle_s: 0.2, poll_s: 0.01, method: closed_form, v_tol: 1.0e-9}
    safety: {box_low: [x, y, z], box_high: [x, y, z], max_step: 0.05, stale_s: 1.0, diverge_dist: 0.05,
             limits_lower: [...], limits_upper: [...]}
    path: {kind: star, size: 0.02, plane: xy, gain: 0.5, tol: 0.002, max_task_step: 0.005, steps: 500}
    # path: {kind: waypoints, waypoints: [[0.01, 0, 0], [0.01, 0.01, 0]]}  # offsets, m (rad for rx, ry, rz)
    # path: {kind: csv, file: square.csv}     # header the task axes (x,y,z), one waypoint offset per row
    tracker: {camera: 0, tag: "tag36h11:0:0.05", camera_info: camera.yaml, latency_s: 0.05}
    # a camera and an AprilTag as the tracker: the camera's pose of the tag replaces the driver's tracker fields
    out: runs/online_ur5e       # default runs/online_<config stem>; --out wins

Unknown keys, wrong types and out-of-range values are refused with the
dotted key, before connecting (:func:`load_online_config`). Every default is
written once, in :class:`selfid_jax.robot.options.OnlineOptions` /
:class:`~selfid_jax.robot.options.FollowOptions`, and :func:`options` turns
a config into those (the same names, one level flatter); the robot section's
forms are checked by :func:`selfid_jax.robot.drivers.check_robot_args`. The
``tracker`` section (optional) is read by
:func:`selfid_jax.sessions.online_run.run_session`, which opens the camera
(:class:`selfid_jax.robot.camera.live.LiveCamera`) before connecting and
puts it in front of the driver (:class:`~selfid_jax.robot.camera.live.CameraTracked`);
its detector settings left null are :class:`selfid_jax.robot.camera.tracker.TrackerSettings`'
defaults (the camera extra, OpenCV, is imported only where the section is given).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax.robot.drivers.load import check_robot_args
from selfid_jax.robot.options import FollowOptions, OnlineOptions
from selfid_jax.runner.config import STRICT

__all__ = ["OnlineConfig", "PathSection", "RobotSection", "SafetySection", "SelfIDSection", "TrackerSection",
           "default_out", "load_online_config", "options"]

Positive = Annotated[float, Field(gt=0)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class RobotSection(BaseModel):
    """How to reach the robot: ``host``/``port`` (the TCP client of robot-sim or a bridge) or ``driver``/``args``: a
    shipped driver (``franka``: a Franka FR3 or Panda over libfranka; ``trossen``: a Trossen WidowX AI) or a user's
    class. A shipped driver's ``args`` are checked against its class's arguments with the config, a user's class's
    when it is imported, before anything connects."""

    model_config = STRICT

    host: str | None = Field(None, description="robot server's host (selfid-jax robot-sim or a bridge)")
    port: int | None = Field(None, ge=1, le=65535)
    timeout_s: float = Field(5.0, gt=0, description="s, the TCP client's timeout per request")
    driver: str | None = Field(None, description="a shipped driver by name (franka, trossen) or 'package.module:Class' "
                                                 "of a driver implementing Robot")
    args: dict[str, Any] = Field(default_factory=dict, description="keyword arguments of the driver class, checked "
                                 "against its signature before connecting (franka: host, the arm's FCI address; "
                                 "connect_timeout_s, 5 s; realtime; dynamics; settle_band, band_tol; ...: "
                                 "docs/drivers.md)")

    @model_validator(mode="after")
    def _one_form(self):
        check_robot_args(host=self.host, port=self.port, driver=self.driver, args=self.args)
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


class TrackerSection(BaseModel):
    """A live camera and an AprilTag as the tracker (:mod:`selfid_jax.robot.camera.live`): the camera's pose of the
    tag, in the camera frame, replaces the driver's tracker fields; the driver still gives q, limits and moves."""

    model_config = STRICT

    camera: Annotated[int, Field(ge=0)] | str = Field(description="what cv2.VideoCapture opens: a device index (0: "
                                                      "the first webcam) or a URL (an IP camera's stream; robot-sim's "
                                                      "camera at http://HOST:PORT/stream.mjpg)")
    tag: str = Field(description="'FAMILY:ID:EDGE_M', e.g. 'tag36h11:0:0.05': the tag's family, id and the edge of "
                     "its black square [m]")
    camera_info: str = Field(description="the camera's intrinsics at the resolution it sends: OpenCV's calibration "
                             "YAML or ROS's camera_info YAML; a relative path is looked up beside the config, then "
                             "in the current directory")
    latency_s: float = Field(0.0, ge=0, le=10, description="s from exposure to the frame's arrival, subtracted from "
                             "the arrival time (time.monotonic at grab) to stamp each frame")
    open_timeout_s: float = Field(5.0, gt=0, le=600, description="s for the camera to open and send its first frame; "
                                  "else the session stops before connecting to the robot")
    wait_s: float = Field(0.5, ge=0, le=10, description="s a reading after a move waits for a frame exposed after "
                          "the move (else the reading has no pose)")
    max_reprojection: float | None = Field(None, gt=0, description="px, RMS reprojection error above which a "
                                           "detection is a dropout (null: the tracker's default)")
    max_ambiguity: float | None = Field(None, gt=0, le=1, description="best / second IPPE error above which the "
                                        "rotation is unreliable: a dropout for a task with rotation axes (null: the "
                                        "tracker's default)")
    border_margin: float | None = Field(None, ge=0, description="px, a corner closer to the image border is a "
                                        "dropout (null: the tracker's default)")
    min_contrast: float | None = Field(None, ge=0, description="grey levels; a frame without the tag and less "
                                       "contrast is low_contrast (null: the tracker's default)")
    corner_refine: Literal["apriltag", "subpix", "none"] | None = Field(None, description="OpenCV's corner "
                                                                         "refinement (null: the tracker's default)")

    @field_validator("tag")
    @classmethod
    def _tag(cls, v: str) -> str:
        try:
            from selfid_jax.robot.camera.live import parse_tag
            from selfid_jax.robot.camera.tracker import tag_dictionary
        except ImportError as err:
            raise ValueError(f"a camera tracker needs the camera extra (OpenCV): pip install 'selfid_jax[camera]' "
                             f"({err})") from None
        family, tag_id, _ = parse_tag(v)
        count = tag_dictionary(family).bytesList.shape[0]
        if not 0 <= tag_id < count:
            raise ValueError(f"family {family} has ids 0..{count - 1}, got {tag_id} (in {v!r})")
        return v

    @field_validator("camera")
    @classmethod
    def _camera(cls, v: int | str) -> int | str:
        if isinstance(v, str) and not v.strip():
            raise ValueError("give a device index (0: the first webcam) or a URL")
        return v


class OnlineConfig(BaseModel):
    """The ``selfid-jax online`` config."""

    model_config = STRICT

    robot: RobotSection
    selfid: SelfIDSection = Field(default_factory=SelfIDSection)
    safety: SafetySection = Field(default_factory=SafetySection)
    path: PathSection | None = None
    tracker: TrackerSection | None = Field(None, description="a live camera and an AprilTag as the tracker (null: "
                                           "the driver's own tracker)")
    out: str | None = None


def options(cfg: OnlineConfig, config_dir: str | Path | None = None,
            estimate: str | Path | None = None) -> OnlineOptions:
    """The config as :class:`~selfid_jax.robot.options.OnlineOptions` (the same names, one level flatter).

    A relative ``path.file`` is taken from ``config_dir`` (the config's
    folder) where it is there, else as given (the current directory).
    ``estimate``: a file of an inverse Jacobian to follow with (``--estimate FILE``; OnlineOptions.estimate).
    """
    config_dir = None if config_dir is None else Path(config_dir)
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


def load_online_config(path: str | Path, overrides: Sequence[str] = ()) -> OnlineConfig:
    """The validated config of the YAML file ``path`` with ``key.sub=value`` ``overrides`` applied (``--set``).

    Raises :class:`selfid_jax.runner.errors.ConfigError` naming the file and
    the dotted key (unknown keys, wrong types, out-of-range values, a robot
    section of neither or both forms, a shipped driver's argument it does
    not take or lacks), before anything connects.
    """
    from selfid_jax.runner.config import read_config, validate

    data, set_keys = read_config(path, overrides)
    cfg: OnlineConfig = validate(OnlineConfig, data, path, set_keys)  # type: ignore[arg-type,assignment]
    _check_shipped_driver_args(cfg, path, set_keys)
    return cfg


def _check_shipped_driver_args(cfg: OnlineConfig, path: str | Path, set_keys: dict[str, str]) -> None:
    """A shipped driver's ``robot.args`` against its class's signature (the driver's module, not its vendor
    library, is imported): ConfigError naming the file, ``robot.args.<key>``, the arguments the driver takes and
    the ``--set`` that gave it. A user's driver (``'module:Class'``) is checked the same way when it is imported,
    at connect."""
    from selfid_jax.robot.drivers.load import (
        DRIVERS,
        DriverArgumentError,
        check_driver_args,
        driver_spec,
        import_driver,
    )
    from selfid_jax.runner.errors import ConfigError

    if cfg.robot.driver is None or driver_spec(cfg.robot.driver) not in DRIVERS.values():
        return
    try:
        check_driver_args(import_driver(cfg.robot.driver), cfg.robot.args, cfg.robot.driver)
    except DriverArgumentError as err:
        key = f"robot.args.{err.key}"
        source = f" (from --set {set_keys[key]})" if key in set_keys else ""
        raise ConfigError(f"{path}: key '{key}': {err}{source}") from None


def default_out(cfg: OnlineConfig, config_path: str | Path) -> Path:
    """The run directory of a session without ``--out``: the config's ``out``, else ``runs/online_<config stem>``."""
    return Path(cfg.out) if cfg.out else Path("runs") / f"online_{Path(config_path).stem}"
