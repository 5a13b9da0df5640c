"""A robot's runs as a lab makes them: a fitted log or an online session written into a run directory.

The layer between the robot (:mod:`selfid_jax.robot`: reading logs, the
estimator over them, drivers, the live runner) and the command line
(:mod:`selfid_jax.commands`, which parses arguments, calls one function here
and prints). It is the only place that joins the robot layer with the run
directory's files (:mod:`selfid_jax.runner`), the online config schema
(pydantic) and the figures (matplotlib), so a Python user gets everything a
command does by calling the same function.
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
