"""Python's garbage collector in processes that trace JAX programs.

Tracing a JAX program allocates many short-lived Python objects (tracers, jaxpr equations, MLIR builders). At
Python's default gen-0 threshold of 700 allocations the collector runs every few hundred of them, and each gen-1
and gen-2 pass walks JAX's and MuJoCo's long-lived objects: in a ``perf`` profile of a compile-bound test
(``tests/test_design.py``'s rotation gradient) the collector was 10 % of the time. At a gen-0 threshold of 10,000
the same test and ``tests/test_native.py`` took 45.7 s instead of 55.3 s (2-core CPU, back to back), at the same
peak memory (1.58 GB); a larger threshold, or no collector at all, gained nothing more.
"""

from __future__ import annotations

import gc

TRACING_THRESHOLD: tuple[int, int, int] = (10_000, 10, 10)
"""``gc.set_threshold`` arguments for a compile-bound process: gen 0 collected every 10,000 net allocations (Python's
default is 700), gens 1 and 2 at Python's default ratios."""


def collect_less_often() -> None:
    """Raise this process's collector thresholds to :data:`TRACING_THRESHOLD` (never lower them): cyclic garbage is
    still collected, in larger, rarer passes. The console script calls it first; so do the tests."""
    current = gc.get_threshold()
    gc.set_threshold(*(max(c, t) for c, t in zip(current, TRACING_THRESHOLD, strict=True)))
