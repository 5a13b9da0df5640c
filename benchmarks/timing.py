"""The timers every benchmark script shares: one jitted call, several interleaved in rounds, one child process.

All in-process times are ``time.perf_counter`` seconds around the call with
``jax.block_until_ready`` on its result, so asynchronous dispatch never hides
work. The first call of a jitted function is timed apart (it includes the
trace and compile); the statistic of the later calls is the caller's choice
(``statistics.median`` by default, ``min`` for a best-of-N), so each script
keeps the statistic it reports.

    from timing import time_call
    t = time_call(fn, x, reps=5)            # median of 5 calls after the first
    t = time_call(fn, x, reps=3, stat=min)  # best of 3
    t.out, t.first_s, t.run_s               # first call's result, its seconds, the statistic

JAX is imported inside the functions, so importing this module never starts
JAX before a script has set its flags (``import selfid_jax``, ``jax_enable_x64``).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple


class Timed(NamedTuple):
    """What :func:`time_call` measured, in seconds."""

    out: Any  # the result of the first call
    first_s: float  # the first call: trace + compile + one run
    run_s: float  # ``stat`` of ``times``
    times: list[float]  # seconds per call (divided by ``per``) of each later call


def usable_cpus() -> int:
    """The CPUs this process may run on: its affinity mask where the OS has one, else ``os.cpu_count()``."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def pin_one_core(ap) -> None:
    """Pin this process to its lowest usable CPU, before JAX starts its CPU client; ``ap.error`` (an
    ``argparse.ArgumentParser``'s) where the OS has no CPU affinity."""
    if not hasattr(os, "sched_setaffinity"):
        ap.error("this OS has no CPU affinity (os.sched_setaffinity); pin the process with the OS tool")
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def first_call(fn: Callable, *args) -> tuple[Any, float]:
    """``(fn(*args), seconds)`` of one call, blocked on its result (for a jitted ``fn``: compile + first run)."""
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def repeat(fn: Callable, *args, reps: int, per: int = 1) -> list[float]:
    """Seconds of each of ``reps`` calls ``fn(*args)``, blocked on the result, each divided by ``per``."""
    import jax

    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append((time.perf_counter() - t0) / per)
    return times


def time_call(fn: Callable, *args, reps: int = 3, stat: Callable = statistics.median, per: int = 1) -> Timed:
    """Time ``fn(*args)``: one first call (the warm-up, timed apart), then ``stat`` of ``reps`` further calls.

    ``per`` divides each later call's seconds (steps or samples per call) so
    ``run_s`` is seconds per step; ``first_s`` is never divided.
    """
    out, first = first_call(fn, *args)
    times = repeat(fn, *args, reps=reps, per=per)
    return Timed(out, first, stat(times), times)


def interleaved(calls: dict[str, tuple[Callable[[], Any], int]], reps: int, rounds: int) -> dict[str, list[float]]:
    """Per-call seconds of several already-warm calls, interleaved in rounds so outside load hits all alike.

    ``calls``: ``{name: (thunk, per)}``; each round runs every thunk ``reps``
    times in turn, and each time (seconds / ``per``) is appended to that name's
    list (``reps * rounds`` entries); the caller takes the statistic.
    """
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(rounds):
        for name, (thunk, per) in calls.items():
            times[name] += repeat(thunk, reps=reps, per=per)
    return times


def run_process(cmd: Sequence[str], **kwargs) -> tuple[subprocess.CompletedProcess, float]:
    """``(subprocess.run(cmd, **kwargs), wall seconds)``: a child's whole-process time, interpreter start to exit.

    On ``timeout`` the child is killed and ``TimeoutExpired`` raised, as by ``subprocess.run``.
    """
    t0 = time.perf_counter()
    proc = subprocess.run(list(cmd), **kwargs)
    return proc, time.perf_counter() - t0
