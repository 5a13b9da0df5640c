"""Drivers for vendors' arms, each over its vendor's client library (an optional extra), loaded by name.

:mod:`selfid_jax.robot.drivers.load` reaches a robot from a config's plain values (:func:`connect`: a driver by
name, ``franka``, ``trossen`` or ``'package.module:Class'``, with its ``args``, or the TCP client at ``host:port``;
:data:`DRIVERS`, :func:`import_driver`, :func:`check_robot_args`, :func:`check_driver_args` (a config's
``args`` against the driver's signature), :class:`ConnectError` (bad input, exit 2), :class:`DriverFailure` (the
driver failed connecting or in ``limits()``, exit 3)).
:mod:`selfid_jax.robot.drivers.franka`: a Franka arm (FR3, Panda) over libfranka through ``franky-control``
(``pip install "selfid-jax[franka]"``, ``robot: {driver: franka}``). :mod:`selfid_jax.robot.drivers.trossen`: a
Trossen WidowX AI over its vendor's ``trossen-arm`` (``pip install "selfid-jax[trossen]"``, ``robot: {driver:
trossen}``). :mod:`selfid_jax.robot.drivers.common`: what the drivers share (settling, limits, the arm's clock,
vendor errors, an external tracker), so that a further vendor is one short module and a line in :data:`DRIVERS`.
No vendor library is imported here: a driver's module imports its vendor's library when the driver connects.
"""

from selfid_jax.robot.drivers.load import (
    DRIVERS,
    ConnectError,
    DriverFailure,
    check_driver_args,
    check_robot_args,
    connect,
    import_driver,
)

__all__ = ["DRIVERS", "ConnectError", "DriverFailure", "check_driver_args", "check_robot_args", "connect",
           "import_driver"]
