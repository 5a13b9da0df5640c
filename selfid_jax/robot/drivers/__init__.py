"""Drivers for vendors' arms, each over its vendor's client library (an optional extra), loaded by name.

:mod:`selfid_jax.robot.drivers.load` reaches a robot from a config's plain values (:func:`connect`: a driver class
``'package.module:Class'`` with its ``args``, or the TCP client at ``host:port``; :func:`import_driver`,
:func:`check_robot_args`, :class:`ConnectError`). :mod:`selfid_jax.robot.drivers.franka`: a Franka arm (FR3, Panda)
over libfranka through ``franky-control`` (``pip install "selfid-jax[franka]"``); a config names it
``robot: {driver: "selfid_jax.robot.drivers.franka:Franka"}``. No vendor library is imported here: a driver's
module imports its vendor's library when the driver connects.
"""

from selfid_jax.robot.drivers.load import ConnectError, check_robot_args, connect, import_driver

__all__ = ["ConnectError", "check_robot_args", "connect", "import_driver"]
