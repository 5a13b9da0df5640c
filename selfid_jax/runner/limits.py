"""Size limits a sweep is checked against before it allocates: rows, and the estimated peak host memory of its table.

Defaults suit a 24 GiB machine: at most :data:`DEFAULT_MAX_ROWS` rows per
sweep and :data:`DEFAULT_MAX_MEMORY_GB` GiB for the results a sweep holds in
memory. Set them with ``$SELFID_JAX_MAX_ROWS`` / ``$SELFID_JAX_MAX_MEMORY_GB``
(or ``selfid-jax sweep --max-rows / --max-memory-gb``). A sweep above either
raises :class:`SizeError` (exit 2 from the command line) with the numbers and
the axes that make it large, before the big arrays exist.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping

from selfid_jax.runner.errors import ConfigError

__all__ = ["DEFAULT_MAX_MEMORY_GB", "DEFAULT_MAX_ROWS", "SizeError", "check_memory", "check_rows", "max_memory_bytes",
           "max_rows"]

DEFAULT_MAX_ROWS = 20_000_000
DEFAULT_MAX_MEMORY_GB = 12.0
_ROWS_ENV, _MEM_ENV = "SELFID_JAX_MAX_ROWS", "SELFID_JAX_MAX_MEMORY_GB"


class SizeError(ConfigError):
    """A sweep larger than the limits; the message gives its size, the limit and what makes it large."""


def _env_number(name: str, default: float) -> float:
    raw = os.environ.get(name)
    if raw is None or not raw.strip():
        return default
    try:
        value = float(raw)
    except ValueError:
        raise ConfigError(f"${name}={raw!r}: not a number") from None
    if not value > 0:
        raise ConfigError(f"${name}={raw!r}: must be positive")
    return value


def max_rows() -> int:
    """The row limit in force (``$SELFID_JAX_MAX_ROWS``, default :data:`DEFAULT_MAX_ROWS`)."""
    return int(_env_number(_ROWS_ENV, DEFAULT_MAX_ROWS))


def max_memory_bytes() -> int:
    """The memory limit in force, bytes (``$SELFID_JAX_MAX_MEMORY_GB`` GiB, default :data:`DEFAULT_MAX_MEMORY_GB`)."""
    return int(_env_number(_MEM_ENV, DEFAULT_MAX_MEMORY_GB) * 2**30)


def _size(n: float) -> str:
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{int(n)} bytes"


def _factors(sizes: Mapping[str, int]) -> str:
    big = sorted(sizes.items(), key=lambda kv: -kv[1])
    return " x ".join(f"{k} {v:,}" for k, v in big)


def check_rows(sizes: Mapping[str, int], what: str = "the sweep") -> int:
    """The product of ``sizes`` (axis -> length); :class:`SizeError` naming the axes if it is above :func:`max_rows`."""
    n = math.prod(int(v) for v in sizes.values())
    limit = max_rows()
    if n > limit:
        raise SizeError(f"{what} has {n:,} rows ({_factors(sizes)}), above the limit of {limit:,}; make the largest "
                        f"of these smaller, or raise the limit (${_ROWS_ENV} or --max-rows)")
    return n


def check_memory(n_rows: int, bytes_per_row: int, what: str = "the sweep") -> int:
    """Estimated peak bytes of an ``n_rows``-row table (3 copies: arrays, table, file); :class:`SizeError` if above."""
    peak = 3 * n_rows * bytes_per_row
    limit = max_memory_bytes()
    if peak > limit:
        raise SizeError(f"{what}: {n_rows:,} rows x {bytes_per_row:,} bytes per row need about {_size(peak)} "
                        f"of memory, above the limit of {_size(limit)}; reduce the rows or raise the limit "
                        f"(${_MEM_ENV} or --max-memory-gb)")
    return peak
