"""Facing a real robot: self-ID from recorded logs (:func:`fit`), above the method and the controllers.

:mod:`selfid_jax.robot.log` reads a recorded log (CSV, Parquet, NPZ) into
self-ID sample pairs, rejecting and counting bad rows; :mod:`selfid_jax.robot.fit`
runs the estimator over them under one ``lax.scan`` with the convergence test
of Sec. IV-D. Neither writes files (that is the ``selfid-jax fit`` command's
job, :mod:`selfid_jax.app.fit`). Nothing is imported here (``selfid_jax.robot.fit``
stays the module; ``sj.fit`` is the function).
"""
