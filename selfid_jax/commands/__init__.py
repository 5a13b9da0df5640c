"""Commands of the ``selfid-jax`` console script that join the domain layers to the runner's files.

The runner knows no robot or method, and the domain layers write no files;
a command that needs both (``fit``: a log in, a run directory out) lives
here, one layer under :mod:`selfid_jax.cli`, which registers it with the
runner's command line (:class:`selfid_jax.runner.command_line.Command`).
"""
