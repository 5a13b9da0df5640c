"""``selfid-jax robot-sim CONFIG``: a virtual robot in its own process, serving the robot protocol over TCP.

    selfid-jax robot-sim CONFIG [--port P] [--port-file FILE] [--set key.sub=value ...]

CONFIG (YAML, strict: unknown keys, wrong types and out-of-range values are
refused with the dotted key, before the port is bound)::

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

:class:`selfid_jax.robot.virtual.VirtualRobot` ticks at ``realism.period``;
:class:`selfid_jax.robot.transport.RobotServer` answers one client at a time; it reads each frame whole (a
client stalling inside one is dropped) and checks every move (a list of numbers of the right length, finite,
within the limits and ``max_step`` of the actuators' position) before the virtual robot sees it.
Once listening it prints ``robot-sim: serving SYSTEM on HOST:PORT`` (and
writes the port to ``--port-file`` atomically), and serves until SIGTERM or
Ctrl-C, which stop the clock where the actuators are. The robot keeps its
pose between clients, as a real arm does; with ``reset_on_connect`` each new
client finds it at rest at ``q0``, as a freshly started simulator.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field, model_validator

from selfid_jax.runner.config import STRICT

__all__ = ["RobotSimConfig", "add_arguments", "command", "run"]

DESCRIPTION = (
    "Run a MuJoCo/JAX simulation of a configured system (a built-in name or an MJCF file and site) in real time, "
    "with the real loop's non-idealities (control period, tracker latency, noise and dropouts, servo lag, "
    "deadband) and injected faults, serving the robot protocol over TCP (msgpack) for 'selfid-jax online'."
)


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


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``robot-sim`` subcommand's arguments."""
    p.add_argument("config", type=Path, help="YAML config (see the description)")
    p.add_argument("--port", type=int, default=None, help="TCP port (overrides the config's; 0: a free port)")
    p.add_argument("--port-file", type=Path, default=None, help="write the port there once listening")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value by dotted key, e.g. --set realism.latency=2 (repeatable)")


def load(path: Path, overrides=()) -> RobotSimConfig:
    """The validated config (``ConfigError`` naming the key)."""
    from selfid_jax.runner.config import read_config, validate

    data, set_keys = read_config(path, overrides)
    cfg: RobotSimConfig = validate(RobotSimConfig, data, path, set_keys)  # type: ignore[arg-type,assignment]
    if cfg.mjcf is not None and not Path(cfg.mjcf).is_absolute():
        cfg = cfg.model_copy(update={"mjcf": str((Path(path).parent / cfg.mjcf).resolve())})
    return cfg


def build(cfg: RobotSimConfig, *, start: bool = True):
    """The :class:`~selfid_jax.robot.virtual.VirtualRobot` a config describes (``ConfigError`` if it cannot be)."""
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


def run(args: argparse.Namespace) -> int:
    """``selfid-jax robot-sim``: build, bind, announce, serve until a signal."""
    from selfid_jax.robot.transport import RobotServer
    from selfid_jax.runner import signals
    from selfid_jax.runner.errors import ConfigError
    from selfid_jax.runner.files import atomic_write_text

    cfg = load(args.config, args.overrides)
    port = cfg.port if args.port is None else args.port
    if not 0 <= port <= 65535:
        raise ConfigError(f"--port must be 0..65535, got {port}")
    signals.phase("build")
    robot = build(cfg, start=False)
    try:
        server = RobotServer(robot, cfg.host, port, info=robot.info(), position=robot.position,
                             on_connect=robot.reset if cfg.reset_on_connect else None)
    except OSError as err:
        robot.close()
        raise ConfigError(f"cannot listen on {cfg.host}:{port}: {err}") from None
    robot.start()
    if args.port_file is not None:
        atomic_write_text(args.port_file, f"{server.port}\n")
    print(f"robot-sim: serving {robot.system.name} on {server.host}:{server.port} (period {robot.period} s, "
          f"latency {robot.latency})", flush=True)
    signals.phase("serve")
    try:
        with signals.graceful("robot-sim: stopped", server.shutdown, interrupt=True):
            server.serve_forever()
    finally:
        server.shutdown()
    s = robot.stats()
    print(f"robot-sim: stopped after {s.elapsed:.1f} s: {s.ticks} ticks, wake-up lateness p50 {1e3 * s.late_p50:.2f} "
          f"ms, p99 {1e3 * s.late_p99:.2f} ms, {s.caught_up} ticks caught up", flush=True)
    return 0


def command():
    """The ``robot-sim`` subcommand for :func:`selfid_jax.runner.command_line.main`."""
    from selfid_jax.runner.command_line import Command

    return Command(help="a virtual robot (any configured system) in real time, serving the robot protocol over TCP",
                   description=DESCRIPTION, add_arguments=add_arguments, run=run)
