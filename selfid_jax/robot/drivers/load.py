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

How it fails, each in one line: arguments the driver's class does not take,
or lacks (:func:`check_driver_args`, from its signature: the message names
the argument, the nearest one it takes and all it takes), values it refuses
(its ``ValueError``/``TypeError``), a driver that cannot be imported or whose
vendor library is missing: :class:`ConnectError` (bad input, exit 2). The
driver failing while it connects, or in ``limits()``
(:func:`checked_limits`): :class:`DriverFailure` naming the driver, the call
and the vendor's message (exit 3). Before a driver connects,
:func:`connect` says so in one line ("connecting to franka at HOST (up to
5 s, robot.args.connect_timeout_s) ...").
"""

from __future__ import annotations

import difflib
import importlib
import inspect
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

__all__ = ["DRIVERS", "ConnectError", "DriverArgumentError", "DriverFailure", "check_driver_args",
           "check_robot_args", "checked_limits", "connect", "display_name", "driver_spec", "import_driver"]

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
    """A robot that cannot be reached as configured: its driver cannot be imported, takes other arguments or
    refuses their values, the TCP server does not answer, or what was built is not a Robot. ``key`` names the
    argument at fault (``driver``, ``args`` or ``host``), the config's ``robot.<key>``; bad input (exit 2)."""

    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key = key


class DriverFailure(RuntimeError):
    """The robot's driver failed in one of its calls outside a session's moves (connecting, ``limits()``): one
    line ``"the robot's driver <name> failed in <call>, before any motion: <the vendor's message> (<our hint>)"``.
    ``exit_code`` 3: the robot or its driver failed, as for a session's ``connection``, ``robot_error`` and
    ``driver_error`` stops (the command line exits with it)."""

    exit_code = 3

    def __init__(self, driver: str, call: str, err: BaseException | str):
        if isinstance(err, BaseException):
            from selfid_jax.robot.protocol import RobotError

            text = " ".join(str(err).split()) or "(no message)"
            err = text if isinstance(err, RobotError) else f"{type(err).__name__}: {text}"
        super().__init__(f"the robot's driver {driver} failed in {call}, before any motion: {err}")
        self.driver, self.call = driver, call


class DriverArgumentError(ValueError):
    """``robot.args`` that the driver's class does not take, or lacks; ``key`` the argument (``robot.args.<key>``)."""

    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key = key


def display_name(driver: str) -> str:
    """A shipped driver's short name (``franka`` for ``selfid_jax.robot.drivers.franka:Franka``), else ``driver``."""
    return next((name for name, spec in DRIVERS.items() if spec == driver), driver)


def _parameters(factory: Callable[..., Any]) -> tuple[inspect.Signature | None, list[str], list[str]]:
    """``(signature, the keyword arguments it takes, the required ones)`` of a driver's class or function; None
    and empty lists where Python cannot tell (a builtin)."""
    try:
        sig = inspect.signature(factory)
    except (TypeError, ValueError):
        return None, [], []
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    names = [p.name for p in sig.parameters.values() if p.kind in kinds]
    required = [p.name for p in sig.parameters.values() if p.kind in kinds and p.default is inspect.Parameter.empty]
    return sig, names, required


def check_driver_args(factory: Callable[..., Any], args: Mapping[str, Any], driver: str) -> None:
    """Check ``args`` against the signature of the driver's class ``factory`` (the name ``driver`` in messages):
    :class:`DriverArgumentError` naming an argument it does not take (with the nearest it does) or a required one
    missing, and listing the arguments it takes (with the driver's own note on it, its ``ARGUMENT_NOTES``, else
    the nearest name it takes). Nothing is built or connected; a factory taking ``**kwargs`` accepts any."""
    driver = display_name(driver)
    sig, names, required = _parameters(factory)
    if sig is None or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.parameters.values()):
        return
    takes = ", ".join(names) if names else "none"
    for key in args:
        if key not in names:
            near = difflib.get_close_matches(str(key), names, n=1)
            note = getattr(factory, "ARGUMENT_NOTES", {}).get(key)  # a driver's word on an argument users try
            guess = f" ({note})" if note else f" (did you mean {near[0]}?)" if near else ""
            raise DriverArgumentError(str(key), f"the {driver} driver takes no argument {key!r}{guess}; the "
                                                f"arguments it takes: {takes}")
    missing = [n for n in required if n not in args]
    if missing:
        raise DriverArgumentError(missing[0], f"the {driver} driver needs robot.args.{missing[0]}; the arguments it "
                                              f"takes: {takes}")


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


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def connect(*, host: str | None = None, port: int | None = None, timeout_s: float = 5.0, driver: str | None = None,
            args: Mapping[str, Any] | None = None, config_dir: str | Path | None = None,
            announce: Callable[[str], None] | None = _say):
    """A connected :class:`~selfid_jax.robot.protocol.Robot`: ``driver(**args)`` (a shipped driver's name or
    ``'package.module:Class'``) or the TCP client at ``host:port``.

    ``timeout_s`` [s]: the TCP client's limit per request. ``config_dir``: the
    config's folder, where a ``driver`` module is looked for after the Python
    path (then the current directory). ``announce``: given the line
    "connecting to NAME at HOST (up to T s, ...) ..." before connecting (default:
    stderr; None: nothing). Raises ValueError for values that name no one way
    (:func:`check_robot_args`); :class:`ConnectError` (its ``key`` ``driver``,
    ``args`` or ``host``; bad input) when the driver cannot be imported, does
    not take ``args`` (:func:`check_driver_args`) or refuses their values
    (ValueError, TypeError), the TCP server does not answer, or the object
    built is not a Robot; :class:`DriverFailure` (the robot failed) for any
    other exception the driver raises while it connects.
    """
    from selfid_jax.robot.protocol import Robot, RobotError

    check_robot_args(host=host, port=port, driver=driver, args=args)
    say = announce or (lambda line: None)
    if driver is not None:
        key = "driver"
        try:
            factory = import_driver(driver, config_dir)
        except (ImportError, AttributeError) as err:
            raise ConnectError(key, f"cannot import {driver!r} (looked on the Python path, in the config's folder "
                                    f"and in the current directory): {err}") from None
        kwargs = dict(args or {})
        try:
            check_driver_args(factory, kwargs, driver)
        except DriverArgumentError as err:
            raise ConnectError(f"args.{err.key}", str(err)) from None
        say(_connecting(driver, factory, kwargs))
        try:
            robot = factory(**kwargs)
        except ImportError as err:  # the vendor's library is missing: an install to make
            raise ConnectError(key, " ".join(str(err).split())) from None
        except (ValueError, TypeError) as err:  # refused before connecting: a value to fix
            raise ConnectError("args", f"the {display_name(driver)} driver refused its arguments: "
                                       f"{' '.join(str(err).split())}") from None
        except Exception as err:  # noqa: BLE001 - whatever the driver raises while connecting: the robot failed
            raise DriverFailure(display_name(driver), "connect", err) from None
    else:
        key = "host"
        from selfid_jax.robot.transport import RemoteRobot

        say(f"connecting to the robot server at {host}:{port} (up to {timeout_s:g} s, robot.timeout_s) ...")
        try:
            robot = RemoteRobot(str(host), int(port or 0), timeout_s=timeout_s)
        except (RobotError, OSError) as err:
            raise ConnectError(key, f"cannot connect to {host}:{port}: {err}") from None
    if not isinstance(robot, Robot):
        raise ConnectError(key, f"{type(robot).__name__} does not implement the Robot protocol "
                                "(limits, read, move, close)")
    return robot


def _connecting(driver: str, factory: Callable[..., Any], args: Mapping[str, Any]) -> str:
    """The line said before a driver connects: its name, its ``host`` and its ``connect_timeout_s`` (given, or its
    signature's default) where it takes them."""
    sig, names, _ = _parameters(factory)
    where = f" at {args['host']}" if isinstance(args.get("host"), str) else ""
    limit = ""
    if "connect_timeout_s" in names:
        t = args.get("connect_timeout_s")
        if t is None and sig is not None:
            t = sig.parameters["connect_timeout_s"].default
        if isinstance(t, int | float):
            limit = f" (up to {t:g} s, robot.args.connect_timeout_s)"
    return f"connecting to {display_name(driver)}{where}{limit} ..."


def checked_limits(robot: Any, driver: str):
    """``robot.limits()`` checked (:func:`~selfid_jax.robot.protocol.check_limits`); :class:`DriverFailure` naming
    ``driver`` and ``limits()`` for any exception the call raises (a vendor's ``OSError`` or ``ValueError``
    included) and for limits that cannot be used (the robot failed: exit 3, not a config to fix)."""
    from selfid_jax.robot.protocol import check_limits

    driver = display_name(driver)
    try:
        limits = robot.limits()
    except Exception as err:  # noqa: BLE001 - any exception from the driver's call is the driver's failure
        raise DriverFailure(driver, "limits()", err) from None
    try:
        return check_limits(limits)
    except Exception as err:  # noqa: BLE001 - malformed limits: the driver's fault
        raise DriverFailure(driver, "limits()", f"it returned limits that cannot be used: "
                                                f"{' '.join(str(err).split())}") from None
