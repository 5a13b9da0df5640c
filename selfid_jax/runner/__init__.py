"""The generic runner: config machinery, the experiment contract and registry, resumable sweeps, run directories, CLI.

It knows no robot, controller or method (an import-linter contract in
``pyproject.toml`` holds it to that). ``selfid_jax.runner`` re-exports the
contract (:class:`Experiment`, :class:`Part`), the registry (:func:`get`,
:func:`available`, :func:`register`, :func:`load`), :func:`run` and :func:`part_threads`, each
imported on first use (so that :mod:`selfid_jax.runner.signals` loads alone).
"""

from typing import TYPE_CHECKING

_LAZY = {
    "Experiment": "selfid_jax.runner.contract",
    "Part": "selfid_jax.runner.contract",
    "precision": "selfid_jax.runner.execute",
    "part_threads": "selfid_jax.runner.execute",
    "run": "selfid_jax.runner.execute",
    "ENTRY_POINT_GROUP": "selfid_jax.runner.registry",
    "available": "selfid_jax.runner.registry",
    "get": "selfid_jax.runner.registry",
    "load": "selfid_jax.runner.registry",
    "register": "selfid_jax.runner.registry",
}

if TYPE_CHECKING:
    from selfid_jax.runner.contract import Experiment, Part
    from selfid_jax.runner.execute import part_threads, precision, run
    from selfid_jax.runner.registry import ENTRY_POINT_GROUP, available, get, load, register

__all__ = ["ENTRY_POINT_GROUP", "Experiment", "Part", "available", "get", "load", "part_threads", "precision",
           "register", "run"]


def __getattr__(name: str):
    """The re-exported names, imported on first use."""
    if name not in _LAZY:
        raise AttributeError(f"module 'selfid_jax.runner' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value
