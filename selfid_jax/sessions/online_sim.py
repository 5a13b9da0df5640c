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
             freeze_tracker_at_s: null}
    seed: 0
    host: 127.0.0.1
    port: 50007

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
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, Field, model_validator

from selfid_jax.runner.config import STRICT

if TYPE_CHECKING:
    from selfid_jax.robot.transport import RobotServer
    from selfid_jax.robot.virtual import TickStats, VirtualRobot

__all__ = ["RobotSimConfig", "SimFaults", "SimRealism", "build", "listen", "load_sim_config", "serve"]


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


def serve(cfg: RobotSimConfig, *, port: int | None = None, port_file: str | Path | None = None,
          listening: Callable[[VirtualRobot, RobotServer], None] | None = None) -> TickStats:
    """Serve the virtual robot of ``cfg`` on ``port`` (default the config's; 0: a free one) until a signal.

    Once listening it starts the robot's clock, writes the port to
    ``port_file`` (atomically) and calls ``listening(robot, server)``; it then
    serves clients one at a time until SIGTERM or Ctrl-C (the console
    script's signal handling) or KeyboardInterrupt, and returns the clock's
    :class:`~selfid_jax.robot.virtual.TickStats` (ticks, wake-up lateness [s]).
    """
    from selfid_jax.runner import signals
    from selfid_jax.runner.files import atomic_write_text

    signals.phase("build")
    robot, server = listen(cfg, port)
    robot.start()
    if port_file is not None:
        atomic_write_text(port_file, f"{server.port}\n")
    if listening is not None:
        listening(robot, server)
    signals.phase("serve")
    try:
        with signals.graceful("robot-sim: stopped", server.shutdown, interrupt=True):
            server.serve_forever()
    finally:
        server.shutdown()
    return robot.stats()
