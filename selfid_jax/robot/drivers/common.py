"""What every vendor driver shares: argument checks, limits, settling, the arm's clock, an external tracker, errors.

A vendor driver (:mod:`~selfid_jax.robot.drivers.franka`,
:mod:`~selfid_jax.robot.drivers.trossen`) is the vendor's calls around these:

* :func:`check_range` refuses an argument outside its interval, naming the
  driver, the argument and the interval (before anything connects);
* :func:`import_vendor` imports the vendor's library or says which extra
  brings it; :data:`CONNECT_TIMEOUT_S` is the drivers' default limit on
  connecting, and :func:`call_within` ends a vendor's call that would wait
  longer (a blocking connect) with a
  :class:`~selfid_jax.robot.protocol.RobotConnectionError` naming the limit;
* :class:`VendorErrors` turns the vendor's exceptions into the runner's: a
  lost link into :class:`~selfid_jax.robot.protocol.RobotConnectionError`
  (the ``connection`` stop), any other vendor exception into
  :class:`~selfid_jax.robot.protocol.RobotError` (``robot_error``), each with
  the vendor's message and, where the driver knows what it means, our hint
  beside it (:class:`Hint`);
* :func:`narrow_limits` narrows the arm's own joint limits by a margin;
* :class:`Settling` and :func:`wait_settled`: a move returns only once every
  joint is within ``target_tol`` of its target and has moved less than
  ``settle_tol`` over the last ``settle_window_s`` (its speed), or less than
  ``band_tol`` inside the position band ``settle_band`` about its target (a
  joint creeping in a stick-slip band has arrived; one that keeps moving
  outside it, swings through it or stays off its target has not), else
  RobotError after ``settle_timeout_s`` naming the joint, how far off it is
  and how far it still moves;
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
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np

from selfid_jax.robot.protocol import Observation, RobotConnectionError, RobotError, RobotLimits

__all__ = ["CONNECT_TIMEOUT_S", "ArmClock", "Hint", "Settling", "VendorErrors", "call_within", "check_range",
           "check_tracker", "close_tracker", "corrected_offset", "import_vendor", "load_tracker", "narrow_limits",
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
    """The vendor's library ``module``; ImportError saying which extra installs ``package`` when it is missing (an
    install to fix, not a failing robot: the command exits 2)."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ImportError(f"the {driver} driver needs {package}, which is not installed: "
                          f"pip install \"selfid-jax[{extra}]\" ({err})") from err


def call_within(call: Callable[[], Any], timeout_s: float, *, what: str,
                hint: str | Callable[[], str] = "") -> Any:
    """``call()``'s result if it returns within ``timeout_s`` [s]; its exception if it raises in time;
    RobotConnectionError ``'<what>: no answer within <timeout_s> s; <hint>'`` if it is still waiting then
    (``hint`` a text, or a function giving it then).

    For a vendor's call that has no limit of its own (libfranka's connect waits
    as long as another client holds the arm): the call runs in a daemon thread
    that is left behind when the limit passes; should it return later, what it
    returned is dropped (a connection then closes as its object is freed).
    """
    done = threading.Event()
    box: dict[str, Any] = {}
    abandoned = threading.Event()

    def run() -> None:
        try:
            box["value"] = call()
        except BaseException as err:  # noqa: BLE001 - handed to the caller's thread, raised there
            box["error"] = err
        if abandoned.is_set():
            box.clear()  # nobody waits for it: free what it made
        done.set()

    threading.Thread(target=run, name=f"call_within({what})", daemon=True).start()
    if not done.wait(timeout_s):
        abandoned.set()
        text = hint() if callable(hint) else hint
        raise RobotConnectionError(f"{what}: no answer within {timeout_s:g} s" + (f"; {text}" if text else ""))
    if "error" in box:
        raise box["error"]
    return box["value"]


class Hint(NamedTuple):
    """What a vendor's message means for the user: ``pattern`` (a regular expression, searched case-insensitively
    in the vendor's message) and ``text``, our hint printed beside it; ``{host}`` in ``text`` is the arm's
    address. ``calls``: the driver's calls it is for (``connect``, ``move``, ...; empty: all)."""

    pattern: str
    text: str
    calls: tuple[str, ...] = ()


@dataclass(frozen=True)
class VendorErrors:
    """The vendor's exceptions inside ``with errors("move"):`` as the runner's.

    ``vendor``: the vendor library's exception classes (any other exception
    passes unchanged: the runner stops on it as ``driver_error``);
    ``is_connection``: whether one of them is a lost or refused link;
    ``hints``: what a vendor message means (:class:`Hint`; the first that
    matches). Messages read ``'<driver> <call> at <host>: <vendor's message>
    (<our hint>)'``, on one line.
    """

    driver: str
    host: str
    vendor: type[BaseException] | tuple[type[BaseException], ...]
    is_connection: Callable[[BaseException], bool]
    hints: tuple[Hint, ...] = ()

    def hint(self, message: str, call: str = "") -> str:
        """Our hint for a vendor's ``message`` in ``call``, or ``''`` when none of :attr:`hints` matches it."""
        for h in self.hints:
            if (not h.calls or call in h.calls) and re.search(h.pattern, message, re.IGNORECASE):
                return h.text.format(host=self.host)
        return ""

    def message(self, call: str, err: BaseException, *, kind: bool = True) -> str:
        """``'<driver> <call> at <host>: [<type>: ]<vendor's message> (<hint>)'`` on one line."""
        text = " ".join(str(err).split())
        hint = self.hint(text, call)
        return (f"{self.driver} {call} at {self.host}: {type(err).__name__ + ': ' if kind else ''}{text}"
                + (f" ({hint})" if hint else ""))

    @contextlib.contextmanager
    def __call__(self, call: str) -> Iterator[None]:
        try:
            yield
        except self.vendor as err:
            if self.is_connection(err):
                raise RobotConnectionError(self.message(call, err, kind=False)) from err
            raise RobotError(self.message(call, err)) from err


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
    """When a joint move is over (joint units and seconds); checked by :meth:`check`.

    A joint has settled when it is within ``target_tol`` of its target and its
    readings over the last ``settle_window_s`` span less than ``settle_tol``
    (it is still); or, inside the position band ``settle_band`` about its
    target, less than ``band_tol`` (it creeps, slowly, where it can wander no
    further than the band: franky-sim's joint 7 creeps back and forth in a
    stick-slip band of about ±1.8 mrad for seconds after a move, moving more
    than ``settle_tol`` in one window of five, up to 0.62 mrad). A joint
    outside the band is held to ``settle_tol``; one swinging through the band
    moves more than ``band_tol`` in a window.
    """

    settle_tol: float = 2e-4  # a joint that moved more than this over the last settle_window_s is still moving
    settle_window_s: float = 0.1  # the window of that test [s]
    target_tol: float = 0.01  # a settled joint is within this of its target
    settle_timeout_s: float = 3.0  # the longest wait after the vendor's move returns [s], then RobotError
    poll_s: float = 0.01  # between joint reads while settling [s]
    settle_band: float = 2e-3  # within this of its target a joint may still creep (a stick-slip band) ...
    band_tol: float = 5e-4  # ... by at most this per settle_window_s

    def check(self, driver: str) -> Settling:
        """These values as floats, each in its range; ValueError naming the first one that is not."""
        ranges = {"settle_tol": 0.1, "settle_window_s": 10.0, "target_tol": 0.5, "settle_timeout_s": 600.0,
                  "poll_s": 1.0, "settle_band": 0.5, "band_tol": 0.5}
        s = Settling(*(check_range(driver, name, getattr(self, name), 0.0, ranges[name]) for name in self._fields))
        if s.settle_band > s.target_tol:
            raise ValueError(f"{driver}: settle_band ({s.settle_band:g}) must be at most target_tol "
                             f"({s.target_tol:g}): the band is the part of the target's tolerance a joint may creep in")
        return s


def wait_settled(read_q: Callable[[], tuple[float, np.ndarray]], target: np.ndarray, settling: Settling, *,
                 driver: str, monotonic: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> np.ndarray:
    """Read the joints every ``poll_s`` until they have settled at ``target (n,)`` and return them ``(n,)``.

    ``read_q() -> (t [s] on the clock of monotonic, q (n,))``. Settled: every
    joint as :class:`Settling` says, its motion taken over a window of
    readings spanning at least ``settle_window_s`` (so a read slower than the
    window is never taken for a settled arm). RobotError after
    ``settle_timeout_s`` naming the joint furthest from settling, how far it is
    from its target and how far it still moves, each against its limit.
    """
    s = settling
    start = monotonic()
    window: deque[tuple[float, np.ndarray]] = deque()
    while True:
        now, q = read_q()
        window.append((now, q))
        while len(window) > 2 and now - window[1][0] >= s.settle_window_s:
            window.popleft()  # keep one reading at least settle_window_s old: the window spans settle_window_s
        full = len(window) >= 2 and now - window[0][0] >= s.settle_window_s
        qs = np.array([x for _, x in window])
        moved = qs.max(axis=0) - qs.min(axis=0)  # how far each joint moved over the window: its velocity's bound
        off = np.abs(q - target)
        allowed = np.where(off <= s.settle_band, max(s.band_tol, s.settle_tol), s.settle_tol)  # per joint
        if full and np.all(moved <= allowed) and off.max() <= s.target_tol:
            return q
        if now - start > s.settle_timeout_s:
            i = int(np.argmax(np.maximum(off / s.target_tol, moved / allowed)))
            why = []
            if off[i] > s.target_tol:
                why.append(f"it stays {off[i] * 1e3:.3g} mrad from its target, beyond target_tol "
                           f"{s.target_tol * 1e3:g} mrad (held off by a load, an obstacle or a collision)")
            if moved[i] > allowed[i]:
                where = (f"within settle_band {s.settle_band * 1e3:g} mrad of its target, band_tol"
                         if off[i] <= s.settle_band else f"{off[i] * 1e3:.3g} mrad from its target, settle_tol")
                why.append(f"it still moved {moved[i] * 1e3:.3g} mrad in the last {s.settle_window_s:g} s ({where} "
                           f"{allowed[i] * 1e3:g} mrad: still travelling, oscillating or pushed)")
            raise RobotError(f"{driver}: joint {i + 1} did not settle within {s.settle_timeout_s:g} s of the move: "
                             f"{'; '.join(why) or 'its readings did not span settle_window_s'}; stopped so that no "
                             "sample pairs a moving arm with its pose (a slow simulator: raise settle_timeout_s in "
                             "robot.args)")
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
