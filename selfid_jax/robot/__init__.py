"""Facing a real robot: self-ID from recorded logs (:func:`fit`) and live (:mod:`~selfid_jax.robot.live`).

:mod:`selfid_jax.robot.log` reads a recorded log (CSV, Parquet, NPZ) into
self-ID sample pairs, rejecting and counting bad rows; :mod:`selfid_jax.robot.offline`
runs the estimator over them under one ``lax.scan`` with the convergence test
of Sec. IV-D. :mod:`selfid_jax.robot.protocol` is what a driver implements;
:mod:`selfid_jax.robot.live` runs Algorithm 1 live over it inside a safety
envelope, appending every event to a session log (:mod:`selfid_jax.robot.journal`,
the only file it writes) from which a stopped session resumes. The run directory's
lock, config and summary files are the commands' job (:mod:`selfid_jax.commands.fit`,
:mod:`selfid_jax.commands.online`). Its modules are imported on first use
(``sj.robot.live``), listed once in ``__init__.pyi``; ``sj.fit`` is :func:`selfid_jax.robot.offline.fit`.
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
