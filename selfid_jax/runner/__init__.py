"""The generic runner: config machinery, the experiment contract and registry, resumable sweeps, run directories, CLI.

It knows no robot, controller or method (an import-linter contract in
``pyproject.toml`` holds it to that). ``selfid_jax.runner`` re-exports the
contract (:class:`Experiment`, :class:`Part`), the registry (:func:`get`,
:func:`available`, :func:`register`, :func:`load`), :func:`run` and :func:`part_threads`, and its
modules, each imported on first use (so that :mod:`selfid_jax.runner.signals` loads alone); the names are
listed once, in ``__init__.pyi`` (read by type checkers and by :func:`lazy_loader.attach_stub`).
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
