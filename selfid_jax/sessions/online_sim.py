"""The virtual robot of ``selfid-jax robot-sim``: its strict config, building it, and serving it over TCP.

The YAML a lab writes for ``selfid-jax robot-sim CONFIG`` (and for
:func:`load_sim_config`)::

    system: ur5e                    # a built-in system (selfid-jax list) ...
    # mjcf: robots/arm.xml          # ... or a user's MJCF or URDF (relative to the config) with its site
    # site: tip                     # ... or body: tool, offset: [0, 0, 0.05] (m, in the body's frame)
    # actuators: joints             # a URDF has no actuators: drive every hinge and slide joint
    q0: [...]                       # start position (default: the system's home)
    reset_on_connect: false         # true: each new client finds the robot at rest at q0
    max_step: 0.05                  # largest accepted step per move (default: the system's dq_max)
    realism: {period: 0.01, latency: 2, noise_pos: 1.0e-4, noise_rot: 0.0, dropout: 0.01,
              servo_tau: 0.03, deadband: 0.0}
    faults: {latency_spike: {at_s: 5, duration_s: 1, extra_s: 2}, dropout_burst: {at_s: 3, duration_s: 0.5},
             freeze_tracker_at_s: null, freeze_camera_at_s: null}
    seed: 0
    host: 127.0.0.1
    port: 50007
    camera:                         # optional: a camera filming the arm, served as an IP camera serves one
      body: link6                   # the body carrying the tag, its place (m, wxyz) in the body's frame
      tag: "tag36h11:0:0.05"
      tag_pos: [0, 0, 0.1]
      tag_quat: [1, 0, 0, 0]
      position: [-1.0, 0.0, 0.8]    # m, world frame; the camera looks at look_at, up is up
      look_at: [-0.5, -0.13, 0.69]
      width: 640
      height: 480
      fovy: 45
      noise: 2.0                    # grey levels of read noise (a frame at rest then differs from the last)
      fps: 10
      latency_s: 0.1                # s from exposure to sending: the online tracker's latency_s
      port: 8080                    # http://HOST:PORT/stream.mjpg; 0: a free port (see url_file)
      intrinsics: runs/sim_camera/camera.yaml   # written (OpenCV's YAML) for the tracker's camera_info

Unknown keys, wrong types and out-of-range values are refused with the
dotted key, before the port is bound. :func:`build` makes the
:class:`selfid_jax.robot.virtual.VirtualRobot` (ticking at
``realism.period``); :func:`serve` binds a
:class:`selfid_jax.robot.transport.RobotServer` (one client at a time; it
reads each frame whole and checks every move before the virtual robot sees
it), writes the port to a file atomically and serves until SIGTERM or Ctrl-C
(under the console script's signal handling) or KeyboardInterrupt, which stop
the clock where the actuators are. The robot keeps its pose between clients,
as a real arm does; with ``reset_on_connect`` each new client finds it at rest
at ``q0``, as a freshly started simulator.

With a ``camera`` section, :func:`serve` also films the arm: a
:class:`~selfid_jax.robot.camera.sim.SimCamera` of the same MJCF (the
config's ``mjcf``, or the built-in UR5e's) with a generated AprilTag on
``camera.body`` renders the actuators' latest position ``fps`` times a
second (:class:`~selfid_jax.robot.camera.stream.FrameFeed`, headless
``MUJOCO_GL=egl``), and an :class:`~selfid_jax.robot.camera.stream.MjpegServer`
serves the frames as MJPEG over HTTP at ``http://HOST:PORT/stream.mjpg``,
which ``cv2.VideoCapture`` opens as it opens an IP camera; the camera's
intrinsics are written (OpenCV's YAML) to ``camera.intrinsics``, so the
online config's ``tracker`` section points at the URL and that file. The
runner sees the arm only through those frames. ``faults.freeze_camera_at_s``
freezes the picture (the stream goes on sending the last frame).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, NamedTuple

from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax.runner.config import STRICT

if TYPE_CHECKING:
    from selfid_jax.robot.camera.sim import SimCamera
    from selfid_jax.robot.camera.stream import FrameFeed, MjpegServer
    from selfid_jax.robot.transport import RobotServer
    from selfid_jax.robot.virtual import TickStats, VirtualRobot

__all__ = ["CameraServer", "RobotSimConfig", "SimCameraSection", "SimFaults", "SimRealism", "build", "listen",
           "load_sim_config", "serve", "sim_camera", "start_camera"]

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class SimRealism(BaseModel):
    """The virtual robot's non-idealities (:class:`selfid_jax.control.realism.Realism`), one value each."""

    model_config = STRICT

    period: float = Field(0.01, gt=0, le=1.0, description="control period [s]")
    latency: int = Field(0, ge=0, le=1000, description="tracker latency [control periods]")
    noise_pos: float = Field(0.0, ge=0, le=0.1, description="tracker position noise, std per axis [m]")
    noise_rot: float = Field(0.0, ge=0, le=1.0, description="tracker rotation noise, std per axis [rad]")
    dropout: float = Field(0.0, ge=0, lt=1, description="probability a tracker reading is missing")
    servo_tau: float = Field(0.0, ge=0, le=10.0, description="first-order servo time constant [s]")
    deadband: float = Field(0.0, ge=0, description="commanded changes at most this large do not move [rad or m]")


class Window(BaseModel):
    model_config = STRICT

    at_s: float = Field(ge=0, description="start [s on the simulator's clock]")
    duration_s: float = Field(gt=0, description="length [s]")


class Spike(Window):
    extra_s: float = Field(gt=0, le=600, description="delay added to each reply in the window [s]")


class SimFaults(BaseModel):
    model_config = STRICT

    latency_spike: Spike | None = None
    dropout_burst: Window | None = None
    freeze_tracker_at_s: float | None = Field(None, ge=0, description="the tracker repeats one reading from then")
    freeze_camera_at_s: float | None = Field(None, ge=0, description="s after the camera starts: from then on it "
                                             "sends its last frame again (a frozen camera)")


class SimCameraSection(BaseModel):
    """A camera filming the virtual robot's arm, served as MJPEG over HTTP (see the module docstring)."""

    model_config = STRICT

    body: str = Field(min_length=1, description="the MJCF body carrying the tag")
    tag: str = Field("tag36h11:0:0.05", description="'FAMILY:ID:EDGE_M': the generated tag's family, id and the "
                     "edge of its black square [m]")
    tag_pos: Vec3 = Field([0.0, 0.0, 0.0], description="m, the tag's centre in the body's frame")
    tag_quat: list[float] = Field([1.0, 0.0, 0.0, 0.0], min_length=4, max_length=4, description="(w, x, y, z), the "
                                  "tag's frame in the body's: the tag faces its +z, its top towards +y")
    position: Vec3 = Field(description="m, the camera's centre, world frame")
    look_at: Vec3 = Field(description="m, a point on the optical axis, world frame")
    up: Vec3 = Field([0.0, 0.0, 1.0], description="the world direction that appears up in the image")
    width: int = Field(640, ge=16, le=4096, description="pixels")
    height: int = Field(480, ge=16, le=4096, description="pixels")
    fovy: float = Field(45.0, gt=0, lt=180, description="degrees, vertical field of view")
    noise: float = Field(2.0, gt=0, le=50, description="std of the read noise, grey levels: a real sensor's, so "
                         "that a frame at rest differs from the last (identical frames are a frozen camera)")
    blur: float = Field(0.0, ge=0, le=20, description="std of a Gaussian blur, pixels")
    fps: float = Field(10.0, gt=0, le=120, description="frames exposed per second (software rendering: 640x480 "
                       "takes tens of ms a frame)")
    latency_s: float = Field(0.1, ge=0, le=5, description="s from a frame's exposure to its sending (later if it "
                             "takes longer to render): the tracker's latency_s")
    quality: int = Field(90, ge=1, le=100, description="JPEG quality of the stream")
    host: str = Field("127.0.0.1", description="the stream's host")
    port: int = Field(8080, ge=0, le=65535, description="the stream's port (0: a free port, see url_file)")
    intrinsics: str = Field(min_length=1, description="where to write the camera's intrinsics (OpenCV's "
                            "calibration YAML), relative to the current directory")
    url_file: str | None = Field(None, description="write the stream's URL there once serving (relative to the "
                                 "current directory)")

    @field_validator("tag")
    @classmethod
    def _tag(cls, v: str) -> str:
        try:
            from selfid_jax.robot.camera.live import parse_tag
        except ImportError as err:
            raise ValueError(f"a camera needs the camera extra (OpenCV): pip install 'selfid_jax[camera]' ({err})"
                             ) from None
        parse_tag(v)
        return v


class RobotSimConfig(BaseModel):
    """``selfid-jax robot-sim`` config (see the module docstring)."""

    model_config = STRICT

    system: str | None = Field(None, description="built-in system name")
    mjcf: str | None = Field(None, description="MJCF or URDF (.urdf) file, relative to the config file")
    site: str | None = Field(None, min_length=1, description="name of the POM site (or give body and offset)")
    body: str | None = Field(None, min_length=1, description="name of the POM's body, when the model has no site")
    offset: list[float] | None = Field(None, min_length=3, max_length=3,
                                       description="POM position in the body's frame [m] (with body; default 0 0 0)")
    actuators: list[str] | Literal["joints"] | None = Field(
        None, min_length=1, description="actuator names (default: all), or 'joints': every hinge and slide joint "
        "(a URDF has no actuators)")
    reset_on_connect: bool = Field(False, description="each new client finds the robot at rest at q0, as from a "
                                   "fresh simulator (default: it keeps its pose between sessions, as a real arm)")
    q0: list[float] | None = Field(None, min_length=1, description="start position [rad or m]")
    max_step: float | None = Field(None, gt=0, description="largest accepted step per move [rad or m]")
    realism: SimRealism = SimRealism()
    faults: SimFaults = SimFaults()
    seed: int = Field(0, ge=0)
    host: str = "127.0.0.1"
    port: int = Field(50007, ge=0, le=65535, description="0: a free port (see --port-file)")
    camera: SimCameraSection | None = Field(None, description="a camera filming the arm, served as MJPEG over HTTP "
                                            "(null: none)")

    @model_validator(mode="after")
    def _one_system(self):
        if (self.system is None) == (self.mjcf is None):
            raise ValueError("give 'system: NAME' (a built-in) or 'mjcf: FILE' with 'site: NAME' (or 'body: NAME' "
                             "and 'offset'), one of them")
        if self.mjcf is None and (self.site or self.body or self.offset or self.actuators) is not None:
            raise ValueError("'site', 'body', 'offset' and 'actuators' are for an 'mjcf' file, not a built-in system")
        if self.mjcf is not None and (self.site is None) == (self.body is None):
            raise ValueError("'mjcf' needs the point the tracker follows: 'site: NAME', or 'body: NAME' with "
                             "'offset: [x, y, z]' (m, in the body's frame), one of them")
        if self.offset is not None and self.body is None:
            raise ValueError("'offset' is a position in the frame of 'body'; give 'body'")
        return self


def load_sim_config(path: str | Path, overrides: Sequence[str] = ()) -> RobotSimConfig:
    """The validated config of the YAML file ``path`` with ``key.sub=value`` ``overrides`` applied
    (``ConfigError`` naming the file and key); a relative ``mjcf`` is resolved beside the config."""
    from selfid_jax.runner.config import read_config, validate

    data, set_keys = read_config(path, overrides)
    cfg: RobotSimConfig = validate(RobotSimConfig, data, path, set_keys)  # type: ignore[arg-type,assignment]
    if cfg.mjcf is not None and not Path(cfg.mjcf).is_absolute():
        cfg = cfg.model_copy(update={"mjcf": str((Path(path).parent / cfg.mjcf).resolve())})
    return cfg


def build(cfg: RobotSimConfig, *, start: bool = True) -> VirtualRobot:
    """The :class:`~selfid_jax.robot.virtual.VirtualRobot` a config describes, its clock started unless ``start``
    is False (``ConfigError`` if it cannot be built)."""
    from selfid_jax.control.realism import Realism
    from selfid_jax.robot import virtual
    from selfid_jax.runner.errors import ConfigError

    f = cfg.faults
    faults = virtual.Faults(
        latency_spike=None if f.latency_spike is None else virtual.LatencySpike(
            f.latency_spike.at_s, f.latency_spike.duration_s, f.latency_spike.extra_s),
        dropout_burst=None if f.dropout_burst is None else virtual.Window(f.dropout_burst.at_s,
                                                                          f.dropout_burst.duration_s),
        freeze_tracker_at_s=f.freeze_tracker_at_s)
    try:
        system = virtual.build_system(cfg.system, mjcf=cfg.mjcf, site=cfg.site, body=cfg.body, offset=cfg.offset,
                                          actuators=cfg.actuators)
        return virtual.VirtualRobot(system, realism=Realism(**cfg.realism.model_dump()), q0=cfg.q0, faults=faults,
                                    seed=cfg.seed, max_step=cfg.max_step, start=start)
    except ValueError as err:
        raise ConfigError(f"cannot build the virtual robot: {' '.join(str(err).split())}") from None


def listen(cfg: RobotSimConfig, port: int | None = None) -> tuple[VirtualRobot, RobotServer]:
    """The virtual robot (its clock not started) and a server bound to ``cfg.host`` and ``port`` (default the
    config's; 0: a free one), not yet serving. ``ConfigError`` if the robot cannot be built or the port bound (the
    robot is closed then)."""
    from selfid_jax.robot.transport import RobotServer
    from selfid_jax.runner.errors import ConfigError

    port = cfg.port if port is None else port
    if not 0 <= port <= 65535:
        raise ConfigError(f"port must be 0..65535, got {port}")
    robot = build(cfg, start=False)
    try:
        server = RobotServer(robot, cfg.host, port, info=robot.info(), position=robot.position,
                             on_connect=robot.reset if cfg.reset_on_connect else None)
    except OSError as err:
        robot.close()
        raise ConfigError(f"cannot listen on {cfg.host}:{port}: {err}") from None
    return robot, server


def _camera_mjcf(cfg: RobotSimConfig) -> str:
    """The MJCF the camera films: the config's, or the built-in UR5e's (ConfigError for another built-in)."""
    from selfid_jax.runner.errors import ConfigError

    if cfg.mjcf is not None:
        return cfg.mjcf
    if cfg.system in ("ur5e", "ur5e_6d"):
        from selfid_jax.systems.ur5e import UR5E_XML

        return UR5E_XML
    raise ConfigError(f"camera: films an arm from its MJCF: give 'mjcf: FILE' (and its site or body) or system ur5e; "
                      f"the built-in {cfg.system!r} is not one")


def sim_camera(cfg: RobotSimConfig) -> SimCamera:
    """The config's camera as a :class:`~selfid_jax.robot.camera.sim.SimCamera` (its OpenGL context current in the
    calling thread): the arm's MJCF with the tag on ``camera.body``; its ``truth(qpos)`` is the tag's pose and
    Jacobian in the camera frame. ConfigError without a camera section or where the scene cannot be built."""
    from selfid_jax.robot.camera.live import parse_tag
    from selfid_jax.robot.camera.render import CameraSettings
    from selfid_jax.robot.camera.sim import SimCamera
    from selfid_jax.robot.camera.tracker import TrackerSettings
    from selfid_jax.runner.errors import ConfigError

    c = cfg.camera
    if c is None:
        raise ConfigError("camera: the config has no camera section")
    family, tag_id, edge = parse_tag(c.tag)
    def vec3(v: list[float]) -> tuple[float, float, float]:
        return (float(v[0]), float(v[1]), float(v[2]))

    settings = CameraSettings(width=c.width, height=c.height, fovy=c.fovy, position=vec3(c.position),
                              look_at=vec3(c.look_at), up=vec3(c.up), noise=c.noise, blur=c.blur, seed=cfg.seed)
    scene = _camera_mjcf(cfg)
    try:
        return SimCamera(scene, c.body, tag=TrackerSettings(family=family, tag_id=tag_id, edge=edge),
                         tag_pos=c.tag_pos, tag_quat=c.tag_quat, camera=settings)
    except ValueError as err:
        raise ConfigError(f"camera: {' '.join(str(err).split())}") from None


class _ArmFilm:
    """What the camera sees now: ``camera`` rendering ``robot``'s latest actuator position as the MJCF's qpos."""

    def __init__(self, camera: SimCamera, robot: VirtualRobot) -> None:
        import numpy as np

        self.camera, self.robot = camera, robot
        qmap = getattr(robot.system.pose_fn, "qmap", None)  # qpos = b + A q (selfid_jax.systems.actuation)
        nq = camera.model.nq
        self._A = np.eye(nq, robot.n) if qmap is None else qmap.A
        self._b = np.zeros(nq) if qmap is None else qmap.b

    def render(self) -> Any:
        return self.camera.render(self._b + self._A @ self.robot.position())

    def close(self) -> None:
        self.camera.close()


class CameraServer(NamedTuple):
    """robot-sim's camera: the stream's server and the feed rendering into it (:func:`start_camera`)."""

    server: MjpegServer
    feed: FrameFeed
    intrinsics: Path  # the intrinsics file written

    @property
    def url(self) -> str:
        """``http://HOST:PORT/stream.mjpg``."""
        return self.server.url

    def close(self) -> None:
        """Stop rendering and serving (idempotent)."""
        try:
            self.feed.close()
        finally:
            self.server.close()


def start_camera(cfg: RobotSimConfig, robot: VirtualRobot, port: int | None = None) -> CameraServer | None:
    """Film ``robot`` as the config's ``camera`` section says and serve it (None without one): bind the stream's
    port (default the section's; 0: a free one), render the first frame, write the intrinsics file and the
    ``url_file``. ConfigError where the port cannot be bound or the scene cannot be built or rendered."""
    c = cfg.camera
    if c is None:  # no camera: neither OpenCV nor OpenGL is loaded
        return None
    from selfid_jax.robot.camera.intrinsics import write_intrinsics
    from selfid_jax.robot.camera.render import RenderUnavailable
    from selfid_jax.robot.camera.stream import FrameFeed, MjpegServer
    from selfid_jax.runner.errors import ConfigError
    from selfid_jax.runner.files import atomic_write_text

    _camera_mjcf(cfg)  # a system the camera cannot film is refused before anything starts
    port = c.port if port is None else port
    try:
        server = MjpegServer(c.host, port, quality=c.quality)
    except OSError as err:
        raise ConfigError(f"camera: cannot serve the stream on {c.host}:{port}: {err}") from None
    feed = FrameFeed(server, lambda: _ArmFilm(sim_camera(cfg), robot), fps=c.fps, latency_s=c.latency_s,
                     freeze_at_s=cfg.faults.freeze_camera_at_s)
    try:
        server.start()
        feed.start()
        film = feed.source
        assert isinstance(film, _ArmFilm)
        path = Path(c.intrinsics)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_intrinsics(path, film.camera.intrinsics)
        if c.url_file is not None:
            atomic_write_text(c.url_file, f"{server.url}\n")
    except (RenderUnavailable, OSError, ValueError) as err:
        feed.close()
        server.close()
        if isinstance(err, ConfigError):  # sim_camera's, naming the key already
            raise
        raise ConfigError(f"camera: {' '.join(str(err).split())}") from None
    except BaseException:
        feed.close()
        server.close()
        raise
    return CameraServer(server, feed, path)


def serve(cfg: RobotSimConfig, *, port: int | None = None, port_file: str | Path | None = None,
          listening: Callable[[VirtualRobot, RobotServer], None] | None = None,
          camera_serving: Callable[[str], None] | None = None) -> TickStats:
    """Serve the virtual robot of ``cfg`` on ``port`` (default the config's; 0: a free one) until a signal.

    Once listening it starts the camera of a ``camera`` section
    (:func:`start_camera`: its stream, intrinsics file and ``url_file``), the
    robot's clock (``camera_serving(url)`` once the camera's stream is up), writes the port to
    ``port_file`` (atomically) and calls ``listening(robot, server)``; it then
    serves clients one at a time until SIGTERM or Ctrl-C (the console
    script's signal handling) or KeyboardInterrupt, and returns the clock's
    :class:`~selfid_jax.robot.virtual.TickStats` (ticks, wake-up lateness [s]).
    """
    from selfid_jax.runner import signals
    from selfid_jax.runner.files import atomic_write_text

    signals.phase("build")
    robot, server = listen(cfg, port)
    camera = None
    try:
        camera = start_camera(cfg, robot)
        if camera is not None and camera_serving is not None:
            camera_serving(camera.url)
        robot.start()
        if port_file is not None:
            atomic_write_text(port_file, f"{server.port}\n")
        if listening is not None:
            listening(robot, server)
        signals.phase("serve")
        with signals.graceful("robot-sim: stopped", server.shutdown, interrupt=True):
            server.serve_forever()
    finally:
        try:
            if camera is not None:
                camera.close()
        finally:
            server.shutdown()
    return robot.stats()
