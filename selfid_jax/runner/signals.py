"""Signals of the command line: SIGINT and SIGTERM at any phase end the process with 130 / 143 and one line.

:func:`install` blocks both signals in the calling (main) thread, and so in
every thread it starts afterwards (XLA's compile and compute pools included),
and waits for them in a thread of its own with ``sigwait``. That thread acts at
once, whatever the main thread is doing (importing, tracing, inside a long XLA
compile, writing figures): it writes one line to stderr and ends the process
with ``os._exit(128 + signal)``, which skips the interpreter's teardown (where a
``KeyboardInterrupt`` racing XLA's threads used to end in a segmentation fault
or be swallowed by a callback). Exiting this way is as safe for a run directory
as ``kill -9``, which the sweep's atomic files and manifest are built for:
finished chunks are kept, a figure or summary is the old file or the new one.

Inside :func:`graceful` (the chunk loop of a run), a first SIGTERM instead asks
the sweep to stop after the chunk in flight (:func:`selfid_jax.runner.sweep.request_stop`);
a second SIGTERM, or a SIGINT, ends the process at once. With ``interrupt=True``
(the robot commands) a first SIGINT asks to stop as well.

:func:`phase` marks the phases of a command on stderr when ``$SELFID_JAX_TRACE_PHASES``
is set (the signal tests use it to aim at each phase).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable, Iterator

__all__ = ["PHASE_ENV", "graceful", "install", "installed", "phase"]

PHASE_ENV = "SELFID_JAX_TRACE_PHASES"
_SIGNALS = {signal.SIGINT, signal.SIGTERM}


class _State:
    installed = False
    prog = "selfid-jax"
    message: str | None = None  # the line for an interruption inside graceful(); None outside
    stop: Callable[[], None] | None = None  # asks the sweep to stop after the chunk in flight
    interrupt = False  # a first SIGINT also calls stop (a command that moves a robot)
    last_words: Callable[[], None] | None = None  # called before a second signal ends the process
    terms = 0


_lock = threading.Lock()


def phase(name: str) -> None:
    """Write ``selfid-jax phase: NAME`` to stderr if ``$SELFID_JAX_TRACE_PHASES`` is set; nothing otherwise."""
    if os.environ.get(PHASE_ENV):
        os.write(2, f"{_State.prog} phase: {name}\n".encode())


def installed() -> bool:
    """Whether :func:`install` has taken over SIGINT and SIGTERM in this process."""
    return _State.installed


def install(prog: str = "selfid-jax") -> None:
    """Handle SIGINT and SIGTERM in a dedicated thread (see the module docstring); call first, from the main thread."""
    if _State.installed:
        return
    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError("signals.install must be called from the main thread")
    _State.prog, _State.installed = prog, True
    signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    threading.Thread(target=_wait, name=f"{prog}-signals", daemon=True).start()


def _wait() -> None:
    while True:
        signum = signal.sigwait(_SIGNALS)
        with _lock:
            if signum == signal.SIGTERM or _State.interrupt:
                _State.terms += 1
            stop = _State.stop
            if (signum == signal.SIGTERM or _State.interrupt) and _State.terms == 1 and stop is not None:
                stop()  # the sweep saves the chunk in flight, then raises SweepInterrupted in the main thread
                continue
            line = _State.message or f"{_State.prog}: {'interrupted' if signum == signal.SIGINT else 'terminated'}"
            last_words = _State.last_words
        if last_words is not None:
            try:
                last_words()
            except Exception:  # noqa: BLE001 - the process ends now whatever the record's fate
                pass
        os.write(2, (line + "\n").encode(errors="replace"))
        os._exit(128 + signum)


@contextlib.contextmanager
def graceful(message: str, stop: Callable[[], None], *, interrupt: bool = False,
             last_words: Callable[[], None] | None = None) -> Iterator[None]:
    """Inside the block: an interruption prints ``message``; a first SIGTERM calls ``stop`` instead of exiting.

    ``interrupt``: a first SIGINT (Ctrl-C) calls ``stop`` too, for a command that moves a robot, which
    must stop it and close the connection rather than vanish mid-move; a second signal of either kind
    ends the process at once, after ``last_words()`` (from the signal thread: it must be quick and
    thread-safe, e.g. one appended line; the robot commands record the stop in the session log).
    """
    with _lock:
        _State.message, _State.stop, _State.terms, _State.interrupt = message, stop, 0, interrupt
        _State.last_words = last_words
    try:
        yield
    finally:
        with _lock:
            _State.message, _State.stop, _State.interrupt, _State.last_words = None, None, False, None
