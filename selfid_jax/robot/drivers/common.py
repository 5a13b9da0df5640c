"""What every vendor driver shares: argument checks, limits, settling, the arm's clock, an external tracker, errors.

A vendor driver (:mod:`~selfid_jax.robot.drivers.franka`,
:mod:`~selfid_jax.robot.drivers.trossen`) is the vendor's calls around these:

* :func:`check_range` refuses an argument outside its interval, naming the
  driver, the argument and the interval (before anything connects);
* :func:`import_vendor` imports the vendor's library or says which extra
  brings it; :data:`CONNECT_TIMEOUT_S` is the drivers' default limit on
  connecting;
* :class:`VendorErrors` turns the vendor's exceptions into the runner's: a
  lost link into :class:`~selfid_jax.robot.protocol.RobotConnectionError`
  (the ``connection`` stop), any other vendor exception into
  :class:`~selfid_jax.robot.protocol.RobotError` (``robot_error``);
* :func:`narrow_limits` narrows the arm's own joint limits by a margin;
* :class:`Settling` and :func:`wait_settled`: a move returns only once every
  joint is within ``target_tol`` of its target and none moved more than
  ``settle_tol`` over the last ``settle_window_s``, else RobotError after
  ``settle_timeout_s``; :func:`corrected_offset` is the offset correction of
  a joint controller that holds a joint off its setpoint;
* :class:`ArmClock` keeps the pose stamp of the read at which the arm's own
  clock last advanced, so an arm whose state stops updating gives a stale
  pose (the runner's ``stale`` stop) rather than a fresh-looking one;
* :func:`check_tracker`, :func:`load_tracker`, :func:`tracker_observation`
  and :func:`close_tracker`: an external tracker ``"module:Class"`` with
  ``tracker_args`` in place of the arm's own pose.

Times are ``time.monotonic()`` unless a driver passes its own clock (the
drivers' tests run the settling on a clock they control).
"""

from __future__ import annotations

import contextlib
import importlib
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np

from selfid_jax.robot.protocol import Observation, RobotConnectionError, RobotError, RobotLimits

__all__ = ["CONNECT_TIMEOUT_S", "ArmClock", "Settling", "VendorErrors", "check_range", "check_tracker",
           "close_tracker", "corrected_offset", "import_vendor", "load_tracker", "narrow_limits",
           "tracker_observation", "wait_settled"]

CONNECT_TIMEOUT_S = 5.0  # s: the default limit on reaching an arm's controller


def check_range(driver: str, name: str, value: Any, lo: float, hi: float, *, include_lo: bool = False,
                include_hi: bool = True, unit: str = "") -> float:
    """``value`` as a float if it is a number in the interval ``(lo, hi]`` (brackets per ``include_lo`` /
    ``include_hi``); ValueError ``'<driver>: <name> must be in (lo, hi] <unit>, got <value>'`` otherwise."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)
    if ok:
        v = float(value)
        ok = (lo <= v if include_lo else lo < v) and (v <= hi if include_hi else v < hi)
    if not ok:
        interval = f"{'[' if include_lo else '('}{lo:g}, {hi:g}{']' if include_hi else ')'}"
        raise ValueError(f"{driver}: {name} must be in {interval}{' ' + unit if unit else ''}, got {value!r}")
    return float(value)


def import_vendor(module: str, *, driver: str, package: str, extra: str) -> ModuleType:
    """The vendor's library ``module``; RobotError saying which extra installs ``package`` when it is missing."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise RobotError(f"the {driver} driver needs {package}: pip install \"selfid-jax[{extra}]\" ({err})") from err


@dataclass(frozen=True)
class VendorErrors:
    """The vendor's exceptions inside ``with errors("move"):`` as the runner's.

    ``vendor``: the vendor library's exception classes (any other exception
    passes unchanged: the runner stops on it as ``driver_error``);
    ``is_connection``: whether one of them is a lost or refused link. Messages
    read ``'<driver> <call> at <host>: ...'``.
    """

    driver: str
    host: str
    vendor: type[BaseException] | tuple[type[BaseException], ...]
    is_connection: Callable[[BaseException], bool]

    @contextlib.contextmanager
    def __call__(self, call: str) -> Iterator[None]:
        try:
            yield
        except self.vendor as err:
            where = f"{self.driver} {call} at {self.host}"
            if self.is_connection(err):
                raise RobotConnectionError(f"{where}: {err}") from err
            raise RobotError(f"{where}: {type(err).__name__}: {err}") from err


def narrow_limits(driver: str, lower: Iterable[float], upper: Iterable[float], margin: float,
                  max_step: float) -> RobotLimits:
    """The arm's joint limits ``lower``/``upper (n,)`` narrowed by ``margin`` each side, with ``max_step`` per
    joint (all in joint units); RobotError naming the joint whose range the margin leaves empty."""
    lo = np.asarray(list(lower), np.float64) + margin
    hi = np.asarray(list(upper), np.float64) - margin
    bad = np.flatnonzero(~(lo < hi))
    if bad.size:
        i = int(bad[0])
        raise RobotError(f"{driver}: joint {i + 1}'s limits [{lo[i] - margin:g}, {hi[i] + margin:g}] leave nothing "
                         f"inside a margin of {margin:g}")
    return RobotLimits(lo, hi, np.full(lo.shape, float(max_step)))


class Settling(NamedTuple):
    """When a joint move is over (joint units and seconds); checked by :meth:`check`."""

    settle_tol: float = 2e-4  # a joint that moved more than this over the last settle_window_s is still moving
    settle_window_s: float = 0.1  # the window of that test [s]
    target_tol: float = 0.01  # a settled joint is within this of its target
    settle_timeout_s: float = 3.0  # the longest wait after the vendor's move returns [s], then RobotError
    poll_s: float = 0.01  # between joint reads while settling [s]

    def check(self, driver: str) -> Settling:
        """These values as floats, each in its range; ValueError naming the first one that is not."""
        ranges = {"settle_tol": 0.1, "settle_window_s": 10.0, "target_tol": 0.5, "settle_timeout_s": 600.0,
                  "poll_s": 1.0}
        return Settling(*(check_range(driver, name, getattr(self, name), 0.0, ranges[name]) for name in self._fields))


def wait_settled(read_q: Callable[[], tuple[float, np.ndarray]], target: np.ndarray, settling: Settling, *,
                 driver: str, monotonic: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> np.ndarray:
    """Read the joints every ``poll_s`` until they have settled at ``target (n,)`` and return them ``(n,)``.

    ``read_q() -> (t [s] on the clock of monotonic, q (n,))``. Settled: every
    joint within ``target_tol`` of its target and none moving more than
    ``settle_tol`` over a window of readings spanning at least
    ``settle_window_s`` (so a read slower than the window is never taken for
    a settled arm). RobotError naming the joint that is furthest from
    settling after ``settle_timeout_s``.
    """
    s = settling
    start = monotonic()
    window: deque[tuple[float, np.ndarray]] = deque()
    while True:
        now, q = read_q()
        window.append((now, q))
        while len(window) > 2 and now - window[1][0] >= s.settle_window_s:
            window.popleft()  # keep one reading at least settle_window_s old: the spread spans the window
        full = len(window) >= 2 and now - window[0][0] >= s.settle_window_s
        qs = np.array([x for _, x in window])
        spread = qs.max(axis=0) - qs.min(axis=0)
        off = np.abs(q - target)
        if full and spread.max() <= s.settle_tol and off.max() <= s.target_tol:
            return q
        if now - start > s.settle_timeout_s:
            i = int(np.argmax(np.maximum(off / s.target_tol, spread / s.settle_tol)))
            raise RobotError(f"{driver}: joint {i + 1} did not settle within {s.settle_timeout_s:g} s: "
                             f"{off[i]:.3g} rad from its target (target_tol {s.target_tol:g}), moved "
                             f"{spread[i]:.3g} rad in the last {s.settle_window_s:g} s (settle_tol "
                             f"{s.settle_tol:g})")
        sleep(s.poll_s)


def corrected_offset(offset: np.ndarray, q: np.ndarray, target: np.ndarray, bound: float) -> np.ndarray:
    """The offset ``(n,)`` a joint controller holds each joint at (measured minus commanded), updated by half of
    this move's landing error ``q - target`` and kept within ``±bound``: a constant offset goes, friction's sign
    flips average out. A driver commands ``target - offset`` so that the joints land on ``target``."""
    return np.clip(offset + 0.5 * (q - target), -bound, bound)


class ArmClock:
    """The pose stamp of an arm's own state: the read at which the arm's clock last advanced.

    :meth:`stamp` takes the arm's clock of a read and our stamp of it (s) and
    returns the stamp to give the pose: ours while the arm's clock advances,
    the last one at which it did while it does not (a frozen state reads stale).
    """

    def __init__(self) -> None:
        self._arm_t = -np.inf
        self._pose_t = -np.inf

    def stamp(self, arm_t: float, now: float) -> float:
        if arm_t != self._arm_t:
            self._arm_t, self._pose_t = arm_t, now
        return self._pose_t


def check_tracker(driver: str, tracker: str, tracker_args: dict[str, Any] | None, own: tuple[str, ...]) -> None:
    """``tracker`` is one of the arm's ``own`` poses or ``'module:Class'``; ``tracker_args`` only with the latter.
    ValueError naming the driver otherwise."""
    if tracker not in own and ":" not in tracker:
        names = ", ".join(repr(x) for x in own)
        raise ValueError(f"{driver}: tracker must be {names} or 'module:Class', got {tracker!r}")
    if tracker_args and ":" not in tracker:
        raise ValueError(f"{driver}: tracker_args are for an external tracker ('module:Class')")


def load_tracker(tracker: str, tracker_args: dict[str, Any] | None) -> Any:
    """The external tracker ``'module:Class'`` built with ``tracker_args``, or None for the arm's own pose.

    Its ``read()`` returns ``(t from time.monotonic() [s], position (3,) [m],
    quaternion (4,) (w, x, y, z) or None, valid)``; its ``close()``, if any,
    releases it.
    """
    if ":" not in tracker:
        return None
    module, name = tracker.split(":", 1)
    return getattr(importlib.import_module(module), name)(**(tracker_args or {}))


def tracker_observation(tracker: Any, now: float, q: np.ndarray) -> Observation:
    """An observation of joints ``q (n,)`` read at ``now`` [s] with the external tracker's latest pose."""
    t, position, quaternion, valid = tracker.read()
    quat = None if quaternion is None else np.asarray(quaternion, np.float64)  # None: position only
    return Observation(now, q, np.asarray(position, np.float64), quat, float(t), bool(valid))  # type: ignore[arg-type]


def close_tracker(tracker: Any) -> None:
    """Release an external tracker (its ``close()``, if it has one); nothing for None."""
    if tracker is not None and hasattr(tracker, "close"):
        tracker.close()
