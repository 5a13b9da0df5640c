"""Reaching a robot by name: a shipped driver (``franka``, ``trossen``), ``'package.module:Class'``, or the TCP client.

:func:`connect` is what a ``robot`` config section means (``selfid-jax online``
and :func:`selfid_jax.sessions.online_run.run_session` call it with the
section's plain values): either ``host``/``port`` (the TCP client of
``selfid-jax robot-sim`` or of a bridge, :class:`~selfid_jax.robot.transport.RemoteRobot`)
or ``driver``/``args`` (``Class(**args)``). ``driver`` is the name of a
shipped driver (:data:`DRIVERS`: ``franka`` for
:class:`~selfid_jax.robot.drivers.franka.Franka`, ``trossen`` for
:class:`~selfid_jax.robot.drivers.trossen.Trossen`) or
``'package.module:Class'`` (a shipped driver's full name, or a lab's own
driver file). A driver module is imported as Python finds it, else from the
config's folder, else from the current directory, so a driver file beside
the config needs no install. Plain values in, a connected
:class:`~selfid_jax.robot.protocol.Robot` out; no pydantic and no runner here.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

__all__ = ["DRIVERS", "ConnectError", "check_robot_args", "connect", "driver_spec", "import_driver"]

# The shipped drivers by name, each over its vendor's library (an optional extra of the same name): a vendor's
# driver is one module in this folder and one line here.
DRIVERS = {
    "franka": "selfid_jax.robot.drivers.franka:Franka",
    "trossen": "selfid_jax.robot.drivers.trossen:Trossen",
}


def driver_spec(driver: str) -> str:
    """``'package.module:Class'`` of a shipped driver's name (:data:`DRIVERS`), or ``driver`` itself if it is one
    already; ValueError naming the choices otherwise."""
    if driver in DRIVERS:
        return DRIVERS[driver]
    if ":" not in str(driver):
        raise ValueError(f"driver must be one of {', '.join(DRIVERS)} or 'package.module:Class', got {driver!r}")
    return driver


class ConnectError(RuntimeError):
    """A robot that cannot be reached: its driver cannot be imported or built, the TCP server does not answer, or
    what was built is not a Robot. ``key`` names the argument at fault (``driver`` or ``host``), the config's
    ``robot.<key>``."""

    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key = key


def check_robot_args(*, host: str | None = None, port: int | None = None, driver: str | None = None,
                     args: Mapping[str, Any] | None = None) -> None:
    """Check that the values name one way to reach a robot: ``host`` and ``port`` (the TCP client) or ``driver``
    (a shipped driver's name or ``'package.module:Class'``, with ``args`` for its class); ValueError saying what is
    wrong otherwise."""
    tcp, drv = host is not None or port is not None, driver is not None
    if tcp == drv:
        raise ValueError("give either host and port (the TCP client) or driver (a user's driver class), "
                         "not both" if tcp else "give host and port, or driver")
    if tcp and (host is None or port is None):
        raise ValueError("the TCP client needs both host and port")
    if args and not drv:
        raise ValueError("args are for a driver class")
    if drv:
        driver_spec(str(driver))


def import_driver(spec: str, config_dir: str | Path | None = None) -> Callable[..., Any]:
    """The factory named by a shipped driver's name (:data:`DRIVERS`) or ``'package.module:Class'``, its module
    imported as Python would, else from the config's folder ``config_dir``, else from the current directory (a
    driver file beside the config needs no install). The search path is restored afterwards. Raises ImportError /
    AttributeError as Python does, ValueError for a name that is neither."""
    module, _, name = driver_spec(spec).partition(":")
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


def connect(*, host: str | None = None, port: int | None = None, timeout_s: float = 5.0, driver: str | None = None,
            args: Mapping[str, Any] | None = None, config_dir: str | Path | None = None):
    """A connected :class:`~selfid_jax.robot.protocol.Robot`: ``driver(**args)`` (a shipped driver's name or
    ``'package.module:Class'``) or the TCP client at ``host:port``.

    ``timeout_s`` [s]: the TCP client's limit per request. ``config_dir``: the
    config's folder, where a ``driver`` module is looked for after the Python
    path (then the current directory). Raises ValueError for values that name
    no one way (:func:`check_robot_args`), and :class:`ConnectError` (its
    ``key`` ``driver`` or ``host``) when the driver cannot be imported, its
    class raises a :class:`~selfid_jax.robot.protocol.RobotError` or OSError,
    the server does not answer, or the object built is not a Robot.
    """
    from selfid_jax.robot.protocol import Robot, RobotError

    check_robot_args(host=host, port=port, driver=driver, args=args)
    if driver is not None:
        key = "driver"
        try:
            factory = import_driver(driver, config_dir)
        except (ImportError, AttributeError) as err:
            raise ConnectError(key, f"cannot import {driver!r} (looked on the Python path, in the config's folder "
                                    f"and in the current directory): {err}") from None
        try:
            robot = factory(**dict(args or {}))
        except (RobotError, OSError) as err:
            raise ConnectError(key, f"cannot connect with {driver}: {err}") from None
    else:
        key = "host"
        from selfid_jax.robot.transport import RemoteRobot

        try:
            robot = RemoteRobot(str(host), int(port or 0), timeout_s=timeout_s)
        except (RobotError, OSError) as err:
            raise ConnectError(key, f"cannot connect to {host}:{port}: {err}") from None
    if not isinstance(robot, Robot):
        raise ConnectError(key, f"{type(robot).__name__} does not implement the Robot protocol "
                                "(limits, read, move, close)")
    return robot
