"""The CPUs a test's real-time simulator runs on: all of the machine's, though its pytest-xdist worker is pinned to
one (``tests/conftest.py``)."""

from __future__ import annotations

import os
from collections.abc import Callable


def all_cpus() -> Callable[[], None] | None:
    """A ``preexec_fn`` for ``subprocess.Popen`` that gives the child every CPU the test run started with (None when
    this worker is not pinned), so that a simulator's threads are not confined to its client's CPU."""
    cpus = os.environ.get("SELFID_JAX_TEST_ALL_CPUS")
    if not cpus or not hasattr(os, "sched_setaffinity"):
        return None
    mask = {int(c) for c in cpus.split(",")}
    return lambda: os.sched_setaffinity(0, mask)
