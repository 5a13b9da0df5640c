"""Eager argument checks shared by the public API.

Shapes and dtypes are static under ``jit``/``vmap``, so these checks run at
trace time too and raise before any compute starts.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np


def check_array(name: str, x, shape: Sequence[int | None], *, floating: bool = True) -> None:
    """Raise ``ValueError`` unless ``x`` has ``shape`` (``None`` matches any size)."""
    try:
        got = tuple(np.shape(x))
    except Exception as err:  # pragma: no cover - exotic inputs
        raise ValueError(f"{name}: expected an array of shape {tuple(shape)}, got {type(x).__name__}") from err
    want = tuple(shape)
    if len(got) != len(want) or any(w is not None and w != g for w, g in zip(want, got)):
        shown = tuple("*" if w is None else w for w in want)
        raise ValueError(f"{name}: expected shape {shown}, got {got}")
    if floating:
        dtype = np.asarray(x).dtype if isinstance(x, (list, tuple)) else jnp.result_type(x)
        if not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)):
            raise ValueError(f"{name}: expected a real floating-point array, got dtype {dtype}")


def check_positive_int(name: str, value) -> int:
    """Return ``value`` as int, raising ``ValueError`` unless it is a positive Python integer."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name}: expected a positive integer, got {value!r}")
    return int(value)


def is_traced(x) -> bool:
    """True if ``x`` is a JAX tracer (we are inside jit/vmap/grad)."""
    return isinstance(x, jax.core.Tracer)


def float_dtype():
    """The default floating dtype (float64 when x64 is on, else float32)."""
    return jnp.zeros(()).dtype


def check_float_dtype(name: str, dtype) -> np.dtype:
    """``dtype`` as a numpy dtype, raising ``ValueError`` unless it is float32 or float64."""
    try:
        dt = np.dtype(dtype)
    except TypeError as err:
        raise ValueError(f"{name}: expected float32 or float64, got {dtype!r}") from err
    if dt not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ValueError(f"{name}: expected float32 or float64, got {dt}")
    return dt


def check_scalar(name: str, value, *, ge: float | None = None, gt: float | None = None, finite: bool = True):
    """Eager check of a number that may also be traced: concrete values must be real, in range (and finite).

    Traced values (inside ``jit``/``vmap``) and arrays with a batch axis pass
    through unchecked elementwise only where concrete; returns ``value``.
    """
    if is_traced(value):
        return value
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu" or arr.dtype == bool:
        raise ValueError(f"{name}: expected a real number, got {value!r}")
    arr = arr.astype(np.float64)
    if np.isnan(arr).any():
        raise ValueError(f"{name}: must not be NaN, got {value!r}")
    if finite and not np.isfinite(arr).all():
        raise ValueError(f"{name}: must be finite, got {value!r}")
    if ge is not None and (arr < ge).any():
        raise ValueError(f"{name}: must be >= {ge}, got {value!r}")
    if gt is not None and (arr <= gt).any():
        raise ValueError(f"{name}: must be > {gt}, got {value!r}")
    return value


def check_magnitude(name: str, m_a, n: int):
    """Check a self-ID magnitude ``m_a`` [rad or m]: one number or ``(n,)``, one per actuator, each finite and > 0.

    Raises ``ValueError`` naming ``name``, the shape or the value; traced
    values pass unchecked (their shape still is). Returns ``m_a`` unchanged.
    The one check of ``m_a`` for Algorithm 1, the live runner, the design
    search and the systems.
    """
    if np.ndim(m_a) not in (0, 1) or (np.ndim(m_a) == 1 and np.shape(m_a)[0] != n):
        raise ValueError(f"{name}: expected a scalar or shape ({n},) (one per actuator), got shape {np.shape(m_a)}")
    return check_scalar(name, m_a, gt=0.0)


class HostBoundWarning(UserWarning):
    """A program that steps on the host (a ``jax.pure_callback`` into MuJoCo) built where the default device is
    an accelerator: every call waits on the host."""


def warn_if_host_bound(what: str, alternative: str) -> bool:
    """Warn (:class:`HostBoundWarning`, once per call site) that ``what`` runs on the host when JAX's default
    backend is not the CPU, naming ``alternative``; returns whether it warned. Nothing on the CPU."""
    backend = jax.default_backend()
    if backend == "cpu":
        return False
    import warnings

    warnings.warn(f"{what} runs on the host (MuJoCo through a host callback), not on the default device "
                  f"({backend}): each call waits on the host. {alternative}", HostBoundWarning, stacklevel=3)
    return True
