"""Method names -> factories, for configurations: :data:`METHODS`, :data:`METHOD_NAMES` and :func:`make`."""

from __future__ import annotations

import inspect
from collections.abc import Callable

from selfid_jax.baselines.base import Estimator
from selfid_jax.baselines.ekm import ekm
from selfid_jax.baselines.filters import kalman, rls
from selfid_jax.baselines.oracle import sign_true_mag, true
from selfid_jax.baselines.paper import direct, ours
from selfid_jax.baselines.particle_filter import particle
from selfid_jax.baselines.secant import broyden

METHODS: dict[str, Callable[..., Estimator]] = {
    "ours": ours,
    "direct": direct,
    "sign_true_mag": sign_true_mag,
    "true": true,
    "broyden": broyden,
    "rls": rls,
    "kalman": kalman,
    "particle": particle,
}
"""Every ablation method by name: the factory building its :class:`~selfid_jax.baselines.base.Estimator`."""

METHOD_NAMES: tuple[str, ...] = tuple(METHODS)

MODEL_BASED: dict[str, Callable[..., Estimator]] = {"ekm": ekm}
"""Methods that need a nominal model and the start configuration (``make("ekm", nominal=..., q0=...)``): kept
out of :data:`METHODS` until the ablation can give them both (their ``init`` raises without)."""


def options(name: str) -> tuple[str, ...]:
    """The keyword options of the factory of method ``name`` (``ValueError`` for an unknown name)."""
    return tuple(inspect.signature(_factory(name)).parameters)


def make(name: str, **options) -> Estimator:
    """The :class:`~selfid_jax.baselines.base.Estimator` of method ``name`` with keyword ``options``.

    ``METHODS[name](**options)``, with ``ValueError`` listing the valid names for
    an unknown ``name`` and the factory's options for an unknown option; the
    factory checks the values. Configurations call it to validate before compute.
    """
    factory = _factory(name)
    signature = inspect.signature(factory)
    unknown = sorted(set(options) - set(signature.parameters))
    if unknown:
        raise ValueError(
            f"{name}: unknown option(s) {', '.join(map(repr, unknown))}; options of {name}: "
            f"{', '.join(signature.parameters)} (signature {name}{signature})"
        )
    return factory(**options)


def _factory(name: str) -> Callable[..., Estimator]:
    if isinstance(name, str) and name in MODEL_BASED:
        return MODEL_BASED[name]
    if not isinstance(name, str) or name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid names: {', '.join(METHOD_NAMES + tuple(MODEL_BASED))}")
    return METHODS[name]
