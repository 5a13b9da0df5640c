"""Drivers for vendors' arms, each over its vendor's client library (an optional extra), loaded by name.

:mod:`selfid_jax.robot.drivers.franka`: a Franka arm (FR3, Panda) over libfranka through ``franky-control``
(``pip install "selfid-jax[franka]"``); a config names it ``robot: {driver: "selfid_jax.robot.drivers.franka:Franka"}``.
Nothing is imported here: a driver's module imports its vendor's library when the driver connects.
"""
