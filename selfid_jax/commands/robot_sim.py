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

The config's schema, building the robot and serving it are
:mod:`selfid_jax.sessions.online_sim` (:func:`~selfid_jax.sessions.online_sim.serve`):
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

__all__ = ["add_arguments", "command", "run"]

DESCRIPTION = (
    "Run a MuJoCo/JAX simulation of a configured system (a built-in name or an MJCF file and site) in real time, "
    "with the real loop's non-idealities (control period, tracker latency, noise and dropouts, servo lag, "
    "deadband) and injected faults, serving the robot protocol over TCP (msgpack) for 'selfid-jax online'."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``robot-sim`` subcommand's arguments."""
    p.add_argument("config", type=Path, help="YAML config, or a shipped one by name (robot_sim_ur5e, ...)")
    p.add_argument("--port", type=int, default=None, help="TCP port (overrides the config's; 0: a free port)")
    p.add_argument("--port-file", type=Path, default=None, help="write the port there once listening")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value by dotted key, e.g. --set realism.latency=2 (repeatable)")


def run(args: argparse.Namespace) -> int:
    """``selfid-jax robot-sim``: load the config, serve the virtual robot until a signal, print its clock's stats."""
    from selfid_jax.runner.command_line import find_config
    from selfid_jax.runner.errors import ConfigError
    from selfid_jax.sessions.online_sim import load_sim_config, serve

    args.config = find_config(args.config, args.config_dirs)  # a path, or a shipped config by name
    cfg = load_sim_config(args.config, args.overrides)
    port = cfg.port if args.port is None else args.port
    if not 0 <= port <= 65535:
        raise ConfigError(f"--port must be 0..65535, got {port}")

    def listening(robot, server) -> None:
        print(f"robot-sim: serving {robot.system.name} on {server.host}:{server.port} (period {robot.period} s, "
              f"latency {robot.latency})", flush=True)

    def camera_serving(url: str) -> None:
        print(f"robot-sim: camera stream at {url}", flush=True)

    s = serve(cfg, port=port, port_file=args.port_file, listening=listening, camera_serving=camera_serving)
    print(f"robot-sim: stopped after {s.elapsed:.1f} s: {s.ticks} ticks, wake-up lateness p50 {1e3 * s.late_p50:.2f} "
          f"ms, p99 {1e3 * s.late_p99:.2f} ms, {s.caught_up} ticks caught up", flush=True)
    return 0


def command():
    """The ``robot-sim`` subcommand for :func:`selfid_jax.runner.command_line.main`."""
    from selfid_jax.runner.command_line import Command

    return Command(help="a virtual robot (any configured system) in real time, serving the robot protocol over TCP",
                   description=DESCRIPTION, add_arguments=add_arguments, run=run)
