"""The registry of experiments: found by name through entry points or registered at run time; configs loaded by name.

Experiments are found through the Python entry-point group
``selfid_jax.experiments`` (``pyproject.toml``: ``valid_region =
"selfid_jax.experiments.valid_region:EXPERIMENT"``), so a user's package adds one the same
way; :func:`register` adds one at run time (tests, notebooks). The runner never
imports an experiment module by name. :func:`load` reads a config file and
validates it against the model of the experiment it names.
"""

from __future__ import annotations

import functools
import importlib.metadata
from collections.abc import Sequence
from pathlib import Path

from selfid_jax.runner.config import BaseConfig, read_config, validate
from selfid_jax.runner.contract import Experiment
from selfid_jax.runner.errors import ConfigError

__all__ = ["ENTRY_POINT_GROUP", "available", "get", "load", "register"]

ENTRY_POINT_GROUP = "selfid_jax.experiments"


_RUNTIME: dict[str, Experiment] = {}


def register(experiment: Experiment) -> Experiment:
    """Make ``experiment`` available by name in this process (in addition to the entry points)."""
    if not isinstance(experiment, Experiment):
        raise TypeError(f"register needs an Experiment, got {type(experiment).__name__}")
    _RUNTIME[experiment.name] = experiment
    return experiment


def _entry_points() -> dict[str, importlib.metadata.EntryPoint]:
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


def available() -> list[str]:
    """Names of every experiment: installed entry points and run-time registrations, sorted."""
    return sorted(set(_entry_points()) | set(_RUNTIME))


@functools.cache
def _load(name: str) -> Experiment:
    ep = _entry_points()[name]
    exp = ep.load()
    if not isinstance(exp, Experiment) or exp.name != name:
        raise TypeError(
            f"entry point {name!r} = {ep.value!r} (group {ENTRY_POINT_GROUP}) must be an Experiment named {name!r}, "
            f"got {exp!r}"
        )
    return exp


def get(name: str) -> Experiment:
    """The experiment called ``name``; :class:`~selfid_jax.runner.config.ConfigError` listing the known ones if none."""
    if name in _RUNTIME:
        return _RUNTIME[name]
    if isinstance(name, str) and name in _entry_points():
        return _load(name)
    raise ConfigError(f"unknown experiment {name!r}; allowed: one of {', '.join(available()) or '(none installed)'}")


def load(path: str | Path, overrides: Sequence[str] = ()) -> BaseConfig:
    """Read the YAML config ``path``, apply ``a.b=value`` overrides, validate it against its experiment's model.

    The file's top-level ``experiment:`` key names the experiment (:func:`get`).

    Raises:
      ConfigError: what :func:`selfid_jax.runner.config.load_config` raises, and
        a missing or unknown ``experiment`` key (the message lists the known ones).
    """
    data, set_keys = read_config(path, overrides)
    name = data.get("experiment")
    known = ", ".join(available()) or "(none installed)"
    if name is None:
        raise ConfigError(f"{path}: key 'experiment': required key is missing; allowed: one of {known}")
    try:
        model = get(name).config if isinstance(name, str) else None
    except ConfigError:
        model = None
    if model is None:
        raise ConfigError(f"{path}: key 'experiment': unknown experiment {name!r}; allowed: one of {known}")
    return validate(model, data, path, set_keys)
