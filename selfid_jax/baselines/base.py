"""The estimator protocol of the ablation (Sec. V-A, Fig. 5), its one sample screen, and stream runners.

An :class:`Estimator` is a ``NamedTuple`` of pure functions, in the manner of
optax's ``GradientTransformation(init, update)``:

* ``init(n, m, key=None, *, capacity=64, dtype=None) -> state``: a
  ``NamedTuple`` of fixed-shape arrays. ``key`` feeds the methods that draw
  random numbers (the others ignore it and accept ``None``; those raise on
  ``None``); ``capacity`` is the sample-buffer size of the methods that need
  samples (the others, the paper's estimator with its default options
  included, keep constant-size statistics and ignore it; 0 is allowed, and
  those that need samples then raise); ``dtype`` defaults
  to JAX's default float.
* ``update(state, dtheta (n,), V (m,)) -> state``: one self-ID sample (actuator
  units, task units). A sample with a non-finite entry, or an all-zero
  ``dtheta`` or ``V``, is rejected: only the state's ``rejected`` counter
  changes, and no inf/NaN reaches the state.
* ``estimate(state, truth (n, m)) -> (n, m)``: the current inverse-Jacobian
  estimate (actuator per task unit); ``truth``, the true inverse Jacobian at
  the configuration of interest, is read by the oracle methods only.
* ``name``: the method's name in :data:`selfid_jax.baselines.METHODS`.

A factory per method builds one from keyword-only options (``rls(lam=0.99)``).
Structural options (variant names, booleans, step and particle counts) are
checked when the factory is called; numeric options are captured by the
returned closures and may be traced JAX values, so a jitted or vmapped
function that calls the factory compiles once for all their values.

Every method is put together by :func:`assemble` from its own ``init``,
``fold`` (a valid sample) and ``read`` functions, so the eager shape checks,
the dtype casts and the sample screen
(:func:`selfid_jax.identify.estimator.guarded_update`, shared with the paper's
:func:`selfid_jax.identify.estimator.update`) are one code path for all. Accepted and
rejected samples are counted in the state's int32 fields ``count`` and
``rejected``; the buffer-based methods keep them in their
:class:`~selfid_jax.identify.estimator.EstimatorState`, not a second time.
:func:`scan` and :func:`run_stream` feed a sample stream to an estimator.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Literal, NamedTuple, TypeVar, overload

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.identify import estimator as _estimator
from selfid_jax.math.checks import check_array, check_positive_int, float_dtype


class Estimator(NamedTuple):
    """An inverse-Jacobian estimation method as three pure functions and a name (see the module docstring).

    ``init(n, m, key=None, *, capacity=64, dtype=None) -> state``;
    ``update(state, dtheta (n,), V (m,)) -> state``;
    ``estimate(state, truth (n, m)) -> (n, m)``. Build one with a factory of
    :mod:`selfid_jax.baselines` or :func:`selfid_jax.baselines.make`.
    """

    init: Callable[..., Any]
    update: Callable[[Any, jax.Array, jax.Array], Any]
    estimate: Callable[[Any, jax.Array], jax.Array]
    name: str


def assemble(
    name: str,
    *,
    init: Callable[..., Any],
    fold: Callable[[Any, jax.Array, jax.Array], Any],
    read: Callable[[Any, jax.Array], jax.Array],
    ref: Callable[[Any], jax.Array],
    tally: Callable[[Any, jax.Array], Any] = _estimator.tally,
    admit: Callable[[Any, jax.Array, jax.Array], jax.Array] | None = None,
    zero_is_identity: bool = False,
) -> Estimator:
    """An :class:`Estimator` from one method's parts, with the checks and the sample screen shared by all.

    Args:
      name: the method's name.
      init: ``(n, m, key, capacity, dtype) -> state``; sizes already checked
        positive, ``dtype`` resolved.
      fold: ``(state, dtheta (n,), V (m,)) -> state`` for a valid sample, cast
        to the state's dtype; leaves the counters alone.
      read: ``(state, truth (n, m)) -> (n, m)`` estimate; ``truth`` cast to the
        state's dtype.
      ref: ``state -> (..., n, m)`` array of the state's dtype: the sizes and
        dtype the checks and casts use.
      tally: ``(state, ok) -> state`` counting the sample where the state keeps
        its counters (default: its own ``count``/``rejected`` fields).
      admit, zero_is_identity: passed to
        :func:`~selfid_jax.identify.estimator.guarded_update`: an extra acceptance test
        ``(state, dtheta, V) -> () bool`` (e.g. that sums stay finite), and
        whether ``fold`` leaves the state unchanged for the all-zero sample
        (which saves selecting between the old and the folded state).
    """

    def init_fn(n: int, m: int, key=None, *, capacity: int = 64, dtype=None):
        n = check_positive_int("n", n)
        m = check_positive_int("m", m)
        capacity = _estimator.check_nonnegative_int("capacity", capacity)
        return init(n, m, key, capacity, float_dtype() if dtype is None else dtype)

    def update_fn(state, dtheta, V):
        r = ref(state)
        return _estimator.guarded_update(fold, state, dtheta, V, shape=r.shape[-2:], dtype=r.dtype, tally=tally,
                                         admit=admit, zero_is_identity=zero_is_identity)

    def estimate_fn(state, truth):
        r = ref(state)
        check_array("truth", truth, r.shape[-2:])
        return read(state, jnp.asarray(truth, r.dtype))

    init_fn.__doc__ = f"Initial {name} state for ``n`` actuators and ``m`` task dimensions."
    update_fn.__doc__ = (
        f"Fold one sample ``dtheta (n,)``, ``V (m,)`` into a {name} state; an invalid one only bumps ``rejected``."
    )
    estimate_fn.__doc__ = f"The {name} inverse-Jacobian estimate ``(n, m)``."
    return Estimator(init=init_fn, update=update_fn, estimate=estimate_fn, name=name)


# ---- eager option checks shared by the factories --------------------------------------------------


_Choice = TypeVar("_Choice", bound=str)


def check_choice(method: str, option: str, value, allowed: Sequence[_Choice]) -> _Choice:
    """``value`` if it is one of ``allowed``, else ``ValueError`` naming the option, the value and ``allowed``."""
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"{method}: {option}: expected one of {tuple(allowed)}, got {value!r}")
    return value  # type: ignore[return-value]  # it is one of allowed


def check_bool(method: str, option: str, value) -> bool:
    """``value`` if it is a Python bool, else ``ValueError`` (allowed: True, False)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{method}: {option}: expected one of (True, False), got {value!r}")  # noqa: TRY004
    return bool(value)


@overload
def check_count(method: str, option: str, value, *, allow_none: Literal[False] = False) -> int: ...
@overload
def check_count(method: str, option: str, value, *, allow_none: bool) -> int | None: ...
def check_count(method: str, option: str, value, *, allow_none: bool = False) -> int | None:
    """``value`` as a Python int if it is a positive integer (or ``None`` if allowed), else ``ValueError``."""
    if value is None and allow_none:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 1:
        want = "None or a positive integer" if allow_none else "a positive integer"
        raise ValueError(f"{method}: {option}: expected {want}, got {value!r}")
    return int(value)


def check_number(method: str, option: str, value, *, scalar: bool = True):
    """``value`` if it is a real number (Python, numpy or JAX, possibly traced), else ``ValueError``.

    ``scalar``: also require shape ``()`` (shapes are static, so this holds for
    traced values too).
    """
    try:
        dtype = jnp.result_type(value)
        shape = np.shape(value)
    except Exception as err:
        raise ValueError(f"{method}: {option}: expected a real number, got {value!r}") from err
    if isinstance(value, (bool, np.bool_)) or not (
        jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)
    ):
        raise ValueError(f"{method}: {option}: expected a real number, got {value!r}")
    if scalar and shape != ():
        raise ValueError(f"{method}: {option}: expected a scalar (shape ()), got shape {shape}")
    return value


# ---- running a stream ------------------------------------------------------------------------------


def scan(estimator: Estimator, state, dthetas, Vs, truth) -> tuple[Any, jax.Array]:
    """Fold the stream ``dthetas (T, n)``, ``Vs (T, m)`` into ``state`` with ``lax.scan``.

    Returns the final state and the estimate after every sample ``(T, n, m)``.
    ``truth`` is ``(n, m)`` (one configuration) or ``(T, n, m)`` (per sample).
    Shapes are checked eagerly against each other and, by ``update`` and
    ``estimate``, against the state.
    """
    check_array("dthetas", dthetas, (None, None))
    T, n = np.shape(dthetas)
    check_array("Vs", Vs, (T, None))
    m = np.shape(Vs)[1]
    per_step = np.ndim(truth) == 3
    check_array("truth", truth, (T, n, m) if per_step else (n, m))

    def body(s, x):
        d, v, t = x
        s = estimator.update(s, d, v)
        return s, estimator.estimate(s, t if per_step else truth)

    xs = (dthetas, Vs, truth if per_step else jnp.zeros((T,), jnp.result_type(dthetas)))
    return jax.lax.scan(body, state, xs)


def run_stream(estimator: Estimator, key, dthetas, Vs, truth, *, capacity: int | None = None) -> jax.Array:
    """Estimates ``(T, n, m)`` of ``estimator`` after each sample of the stream ``dthetas (T, n)``, ``Vs (T, m)``.

    A fresh state is built with ``key`` and ``capacity`` (default ``T``: the
    buffer keeps every sample), in the float dtype of ``dthetas``; ``truth`` is
    ``(n, m)`` or ``(T, n, m)``. Jit it with the estimator closed over or
    static: ``jax.jit(functools.partial(run_stream, rls(lam=0.9)))``, or build
    the estimator inside the jitted function to trace its numeric options.
    """
    check_array("dthetas", dthetas, (None, None))
    T, n = np.shape(dthetas)
    check_array("Vs", Vs, (T, None))
    m = np.shape(Vs)[1]
    state = estimator.init(n, m, key, capacity=T if capacity is None else capacity, dtype=_float_of(dthetas))
    _, estimates = scan(estimator, state, dthetas, Vs, truth)
    return estimates


def _float_of(x):
    dtype = jnp.result_type(x)
    return dtype if jnp.issubdtype(dtype, jnp.floating) else float_dtype()
