"""Facing a real robot: self-ID from recorded logs (:func:`fit`) and live (:mod:`~selfid_jax.robot.live`).

:mod:`selfid_jax.robot.read` reads any recorded log (CSV, Parquet, NPZ, ROS 1/2
bags, MCAP; declared units; continuous streams reduced to settled moves, tracker
latency removed) into self-ID sample pairs and a report of what it did, with the
options of :mod:`selfid_jax.robot.fit_options`; :mod:`selfid_jax.robot.offline`
runs the estimator over them under one ``lax.scan`` with the convergence test
of Sec. IV-D and says how far to trust the fit (:mod:`selfid_jax.robot.quality`).
:mod:`selfid_jax.robot.protocol` is what a driver implements (vendor drivers and
their loading by name in :mod:`selfid_jax.robot.drivers`); :mod:`selfid_jax.robot.live`
runs Algorithm 1 live over it inside a safety envelope, appending every event to
a session log (:mod:`selfid_jax.robot.journal`, the only file it writes) from
which a stopped session resumes. The run directory's lock, config and summary
files are :mod:`selfid_jax.sessions`' job (:mod:`~selfid_jax.sessions.fit_run`,
:mod:`~selfid_jax.sessions.online_run`). Its modules are imported on first use
(``sj.robot.live``), listed once in ``__init__.pyi``; ``sj.fit`` is
:func:`selfid_jax.robot.offline.fit`.
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
