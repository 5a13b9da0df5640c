"""The generic runner: config machinery, the experiment contract and registry, resumable sweeps, run directories, CLI.

It knows no robot, controller or method (an import-linter contract in
``pyproject.toml`` holds it to that). ``selfid_jax.runner`` re-exports the
contract (:class:`Experiment`, :class:`Part`), the registry (:func:`get`,
:func:`available`, :func:`register`, :func:`load`) and :func:`run`.
"""

from selfid_jax.runner.contract import Experiment, Part
from selfid_jax.runner.execute import precision, run
from selfid_jax.runner.registry import ENTRY_POINT_GROUP, available, get, load, register

__all__ = ["ENTRY_POINT_GROUP", "Experiment", "Part", "available", "get", "load", "precision", "register", "run"]
