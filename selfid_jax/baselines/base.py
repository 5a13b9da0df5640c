"""One interface for every inverse-Jacobian estimation method of the ablation (Sec. V-A, Fig. 5).

A :class:`Method` is a static, hashable description (name, static options,
defaults of the traced parameters) with three pure functions:

* ``method.init(n, m, key, *, capacity=64, dtype=None, **params) -> state``:
  a pytree of fixed-shape arrays. ``key`` feeds the methods that draw random
  numbers (others ignore it and accept ``None``; those raise on ``None``); ``capacity`` is the sample-buffer size of the
  buffer-based methods (others ignore it). ``params`` override the traced
  parameters chosen in :func:`get_method` and may be traced, so one
  compilation serves a sweep (``vmap`` over ``init``).
* ``method.update(state, dtheta (n,), V (m,)) -> state``: one self-ID sample
  (actuator units, task units). A sample with a non-finite entry, or an
  all-zero ``dtheta`` or ``V``, is rejected: only ``state.rejected`` changes.
* ``method.estimate(state, truth (n, m)) -> Jinv (n, m)``: the current estimate;
  ``truth``, the true inverse Jacobian at the configuration of interest, is read
  by the oracle methods only.

Every state is a ``NamedTuple`` with ``count`` (accepted samples, int32),
``rejected`` (rejected samples, int32), a ``params`` dict of traced scalars and
a ``shape_ref`` property (an ``(n, m)`` array of the state's dtype) that gives
sizes and dtype; families never touch ``count``/``rejected`` themselves. :func:`get_method` builds a method by name
(:data:`METHOD_NAMES`); :func:`run_stream` feeds a sample stream to one method
and returns the estimate after every sample.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable, Hashable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from selfid_jax._checks import check_array, check_positive_int, float_dtype
from selfid_jax.estimator import is_valid_sample

METHOD_NAMES = ("ours", "direct", "sign_true_mag", "true", "broyden", "rls", "kalman", "particle")

# Which module implements each method; imported lazily by get_method (no import cycle).
_MODULES = {
    "ours": "ours",
    "direct": "direct",
    "sign_true_mag": "oracle",
    "true": "oracle",
    "broyden": "broyden",
    "rls": "rls",
    "kalman": "kalman",
    "particle": "particle",
}


class Family(NamedTuple):
    """How a module implements one method (internal; users see :class:`Method`).

    ``init(n, m, key, capacity, dtype, static, params) -> state``,
    ``update(state, dtheta, V, static) -> state`` (``dtheta``/``V`` already cast,
    validity handled by the caller), ``estimate(state, truth, static) -> (n, m)``;
    ``static`` and ``params`` are dicts. ``validate(static)`` raises on bad values.
    """

    init: Callable
    update: Callable
    estimate: Callable
    static_defaults: Mapping[str, Hashable]
    param_defaults: Mapping[str, float]
    validate: Callable[[dict], None] = lambda static: None


@dataclasses.dataclass(frozen=True)
class Method:
    """A named estimation method with its options: static, hashable, equal by value.

    ``static``: sorted ``(name, value)`` pairs of structural options (sizes,
    variant names, step counts). ``params``: sorted ``(name, default)`` pairs of
    numeric options that live in the state as traced scalars. Use
    :func:`get_method` to build one; pass it to ``jit`` as a static argument.
    """

    name: str
    static: tuple[tuple[str, Hashable], ...] = ()
    params: tuple[tuple[str, float], ...] = ()

    @property
    def _family(self) -> Family:
        return _family(self.name)

    def init(self, n: int, m: int, key=None, *, capacity: int = 64, dtype=None, **params):
        """Initial state for ``n`` actuators and ``m`` task dims; ``params`` override traced defaults."""
        n = check_positive_int("n", n)
        m = check_positive_int("m", m)
        capacity = check_positive_int("capacity", capacity)
        dtype = float_dtype() if dtype is None else dtype
        defaults = dict(self.params)
        unknown = set(params) - set(defaults)
        if unknown:
            raise ValueError(
                f"{self.name}: unknown parameter(s) {sorted(unknown)}; traced parameters are {sorted(defaults)}"
            )
        values = {k: jnp.asarray(params.get(k, v), dtype) for k, v in defaults.items()}
        return self._family.init(n, m, key, capacity, dtype, dict(self.static), values)

    def update(self, state, dtheta, V):
        """Fold one sample ``dtheta (n,)``, ``V (m,)`` into ``state``; invalid samples only bump ``rejected``."""
        n, m = self.estimate_shape(state)
        check_array("dtheta", dtheta, (n,))
        check_array("V", V, (m,))
        dtype = _dtype(state)
        dtheta = jnp.asarray(dtheta, dtype)
        V = jnp.asarray(V, dtype)
        ok = is_valid_sample(dtheta, V)
        # Zero invalid samples before any arithmetic so no inf/NaN reaches the state.
        new = self._family.update(state, jnp.where(ok, dtheta, 0.0), jnp.where(ok, V, 0.0), dict(self.static))
        return accept(ok, new, state)

    def estimate(self, state, truth):
        """Inverse-Jacobian estimate ``(n, m)``; ``truth (n, m)`` is read by the oracle methods only."""
        check_array("truth", truth, self.estimate_shape(state))
        return self._family.estimate(state, jnp.asarray(truth, _dtype(state)), dict(self.static))

    @staticmethod
    def estimate_shape(state) -> tuple[int, int]:
        """Static ``(n, m)`` of an (unbatched) state."""
        return tuple(state.shape_ref.shape[-2:])


def _dtype(state):
    return state.shape_ref.dtype


def _family(name: str) -> Family:
    if name not in _MODULES:
        raise ValueError(f"unknown method {name!r}; valid names: {', '.join(METHOD_NAMES)}")
    module = importlib.import_module(f"selfid_jax.baselines.{_MODULES[name]}")
    return module.FAMILIES[name]


def get_method(name: str, **options) -> Method:
    """The method called ``name`` (one of :data:`METHOD_NAMES`) with ``options`` set.

    Options are either static (strings, booleans, integers that shape the
    computation) or traced parameters (numbers stored in the state; their value
    here is the default that ``Method.init(**params)`` may override). Unknown
    names or options raise ``ValueError`` listing the valid ones.
    """
    family = _family(name)
    static = dict(family.static_defaults)
    params = dict(family.param_defaults)
    for k, v in options.items():
        if k in static:
            static[k] = v
        elif k in params:
            try:
                params[k] = float(v)
            except (TypeError, ValueError) as err:
                raise ValueError(
                    f"{name}: option {k!r} must be a concrete number here; pass traced values to Method.init"
                ) from err
        else:
            raise ValueError(
                f"{name}: unknown option {k!r}; static options {sorted(static)}, traced parameters {sorted(params)}"
            )
    family.validate(static)
    try:
        hash(tuple(static.items()))
    except TypeError as err:
        raise ValueError(f"{name}: static options must be hashable, got {static}") from err
    return Method(name, tuple(sorted(static.items())), tuple(sorted(params.items())))


def keep_finite_gain(state, J, P):
    """``state`` with the filter update ``(J, P)`` if both are finite, else unchanged (RLS and Kalman)."""
    good = jnp.all(jnp.isfinite(J)) & jnp.all(jnp.isfinite(P))
    return state._replace(J=jnp.where(good, J, state.J), P=jnp.where(good, P, state.P))


def accept(ok, new, old):
    """``new`` with ``count + 1`` if the sample was valid, else ``old`` with ``rejected + 1``."""
    new = new._replace(count=old.count + 1, rejected=old.rejected)
    old = old._replace(rejected=old.rejected + 1)
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, old)


def scan(method: Method, state, dthetas, Vs, truth) -> tuple[Any, jax.Array]:
    """Fold ``dthetas (T, n)``, ``Vs (T, m)`` into ``state`` with ``lax.scan``.

    Returns the final state and the estimate after every sample ``(T, n, m)``.
    ``truth`` is ``(n, m)`` (one configuration) or ``(T, n, m)`` (per sample).
    """
    n, m = method.estimate_shape(state)
    T = dthetas.shape[0]
    check_array("dthetas", dthetas, (T, n))
    check_array("Vs", Vs, (T, m))
    truth = jnp.asarray(truth, _dtype(state))
    per_step = truth.ndim == 3
    check_array("truth", truth, (T, n, m) if per_step else (n, m))

    def body(s, x):
        d, v, t = x
        s = method.update(s, d, v)
        return s, method.estimate(s, t if per_step else truth)

    xs = (dthetas, Vs, truth if per_step else jnp.zeros((T,), _dtype(state)))
    return jax.lax.scan(body, state, xs)


def run_stream(method: Method, key, dthetas, Vs, truth, *, capacity: int | None = None, **params) -> jax.Array:
    """Estimates ``(T, n, m)`` of ``method`` after each sample of the stream ``dthetas (T, n)``, ``Vs (T, m)``.

    A fresh state is built with ``key``, ``capacity`` (default ``T``: the buffer
    keeps every sample) and traced ``params``; ``truth`` is ``(n, m)`` or
    ``(T, n, m)``. Jit it with ``method`` and ``capacity`` static::

        jax.jit(run_stream, static_argnames=("method", "capacity"))
    """
    T, n = dthetas.shape
    m = Vs.shape[-1]
    state = method.init(n, m, key, capacity=T if capacity is None else capacity, dtype=_float_of(dthetas), **params)
    _, estimates = scan(method, state, dthetas, Vs, truth)
    return estimates


def _float_of(x):
    dtype = jnp.result_type(x)
    return dtype if jnp.issubdtype(dtype, jnp.floating) else float_dtype()
