"""A live camera as the online runner's tracker: frames read in the background, the tag's pose in each reading.

:class:`LiveCamera` opens a camera as OpenCV opens one, ``cv2.VideoCapture``:
a device index (``0``: the first webcam, V4L2 on Linux) or a URL (an IP
camera's MJPEG or RTSP stream, through FFmpeg; ``robot-sim``'s simulated
camera, :mod:`selfid_jax.robot.camera.stream`). A thread grabs every frame
as it arrives and keeps only the newest, so a reading never uses a frame
that waited in a buffer; each frame is stamped on the runner's clock
(``time.monotonic``) when ``grab()`` returns, less the camera's stated
``latency_s`` (exposure to arrival), which the frame cannot tell. A camera
that cannot be opened, or sends no frame within ``open_timeout_s``, raises
:class:`CameraError` naming it; a stream that ends later makes the next
reading raise :class:`~selfid_jax.robot.protocol.RobotConnectionError` (the
session stops as ``connection``).

:class:`CameraTracked` puts the camera in front of a driver: the driver
still gives the actuator positions, the limits and the moves; the camera's
:class:`~selfid_jax.robot.camera.tracker.TagTracker` gives the tracker
fields of each :class:`~selfid_jax.robot.protocol.Observation`, so
:func:`selfid_jax.robot.live.run_online` runs unchanged. On one clock: a
reading's ``t`` is the runner's clock when the driver's reading returned
(the driver's own clock may be another), its ``tracker_t`` the newest
frame's capture time. Each frame is tracked once, at the first reading
that finds it:

* a dropout (no tag, a cut or ambiguous tag, a blank frame: the tracker's
  reasons) is ``valid`` False, with the last good pose and its stamp (NaN
  before the first), so the runner rejects the sample and its watchdog
  counts the pose's age;
* a frozen camera, the identical frame again, is a dropout of reason
  ``stale``; the first frame only primes that test (a pose is reported
  from a frame that differs from the one before it), so a camera frozen
  from the start never yields a pose, and the runner's watchdog stops the
  session (``stale``) before any motion;
* a camera that stops sending frames repeats its last reading, whose stamp
  no longer advances: the runner's watchdog stops the session (``stale``);
* after a move, a frame exposed before the move was commanded is never
  reported as a pose: the reading waits up to ``wait_s`` for a newer frame,
  else it is a dropout (``late``).

The driver's optional ``jacobian`` is not passed on: it is a model of the
driver's tracked point in its frame, not of the tag in the camera's.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, NamedTuple

import cv2
import numpy as np

from selfid_jax.robot.camera.tracker import TAG_FAMILIES, TagPose, TagTracker
from selfid_jax.robot.protocol import Observation, Robot, RobotConnectionError, RobotLimits

__all__ = ["CameraError", "CameraTracked", "Frame", "LiveCamera", "parse_tag"]


class CameraError(RuntimeError):
    """A camera that cannot be opened or sends no usable frame; the one-line message names the camera."""


class Frame(NamedTuple):
    """One frame of a :class:`LiveCamera`."""

    seq: int  # frames received since the camera was opened, 1-based
    image: np.ndarray  # (H, W, 3) BGR uint8, as OpenCV decodes it
    t: float  # capture time, s, on the camera's clock (time.monotonic): arrival less latency_s


def parse_tag(text: str) -> tuple[str, int, float]:
    """``"FAMILY:ID:EDGE_M"`` (e.g. ``"tag36h11:7:0.05"``) -> ``(family, id, edge in m)``; ValueError otherwise.

    ``EDGE_M`` is the edge of the tag's black square in metres (OpenCV's marker length).
    """
    parts = str(text).split(":")
    if len(parts) != 3:
        raise ValueError(f"expected 'FAMILY:ID:EDGE_M' (e.g. 'tag36h11:0:0.05'), got {text!r}")
    family, tag_id, edge = (p.strip() for p in parts)
    if family not in TAG_FAMILIES:
        raise ValueError(f"tag family {family!r} is not one of {sorted(TAG_FAMILIES)} (in {text!r})")
    try:
        number, metres = int(tag_id), float(edge)
    except ValueError:
        raise ValueError(f"the id must be a whole number and the edge a number of metres, got {text!r}") from None
    if not (math.isfinite(metres) and metres > 0):
        raise ValueError(f"the tag's edge must be > 0 m, got {edge!r} (in {text!r})")
    return family, number, metres


def _describe(source: int | str) -> str:
    return f"camera {source}" if isinstance(source, int) else f"camera {source!r}"


class LiveCamera:
    """A camera opened with ``cv2.VideoCapture(source)``, its newest frame kept by a thread (module docstring).

    ``source``: a device index (int >= 0) or a URL or device path (str).
    ``latency_s``: s from exposure to the frame's arrival, subtracted from
    each stamp. ``open_timeout_s``: s for the camera to open and send its
    first frame. ``size``: ``(width, height)`` the frames must have (the
    intrinsics'); a device camera is asked for it, a stream must send it.
    ``clock``: the runner's clock (``time.monotonic``). Raises
    :class:`CameraError` (naming the camera) before returning if any of
    this fails; :meth:`close` stops the thread and releases the camera.
    """

    def __init__(self, source: int | str, *, latency_s: float = 0.0, open_timeout_s: float = 5.0,
                 size: tuple[int, int] | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        if isinstance(source, bool) or not isinstance(source, (int, str)) or (isinstance(source, int) and source < 0):
            raise CameraError(f"camera: expected a device index >= 0 or a URL, got {source!r}")
        for key, value in (("latency_s", latency_s), ("open_timeout_s", open_timeout_s)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise CameraError(f"{_describe(source)}: {key} must be a finite number of seconds >= 0, got {value!r}")
        self.source, self.name = source, _describe(source)
        self.latency_s, self._clock = float(latency_s), clock
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)
        self._frame: Frame | None = None
        self._ended: str | None = None  # why the stream ended (None while it runs)
        self._stop = threading.Event()
        self._cap = self._open(source, open_timeout_s, size)
        self._thread = threading.Thread(target=self._run, name="camera-reader", daemon=True)
        self._thread.start()
        first = self.wait_newer(0, open_timeout_s)
        if first is None:
            why = self._ended or f"no frame within {open_timeout_s:g} s (open_timeout_s)"
            self.close()
            raise CameraError(f"{self.name}: opened, but {why}")
        h, w = first.image.shape[:2]
        if size is not None and (w, h) != tuple(size):
            self.close()
            raise CameraError(f"{self.name} sends {w}x{h} frames, but the intrinsics are for {size[0]}x{size[1]}: "
                              "calibrate the camera at the resolution it sends (or set it to the calibrated one)")
        self.size = (w, h)

    def _open(self, source: int | str, timeout_s: float, size: tuple[int, int] | None) -> Any:
        url = isinstance(source, str) and "://" in source
        ms = int(max(1.0, 1e3 * timeout_s))
        try:
            if url:  # FFmpeg: an IP camera's stream, with timeouts so that a silent host cannot hang the runner
                cap = cv2.VideoCapture(source, cv2.CAP_FFMPEG, [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms,
                                                                cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms])
            else:
                cap = cv2.VideoCapture(source)
        except cv2.error as err:
            raise CameraError(f"{self.name}: OpenCV cannot open it ({str(err).strip().splitlines()[-1]})") from None
        if not cap.isOpened():
            cap.release()
            hint = ("is the URL right and the camera serving it?" if url else
                    "is it connected, and not in use by another program?")
            raise CameraError(f"{self.name}: OpenCV cannot open it (cv2.VideoCapture); {hint}")
        if size is not None and not url:  # a device camera: ask for the calibrated resolution
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, int(size[0]))
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, int(size[1]))
        return cap

    def _run(self) -> None:
        cap, seq = self._cap, 0
        try:
            while not self._stop.is_set():
                ok = cap.grab()  # blocks until the next frame arrives (OpenCV releases the GIL)
                arrived = self._clock()
                if not ok:
                    self._end("the stream ended or the camera stopped sending frames")
                    return
                ok, image = cap.retrieve()
                if not ok or image is None:
                    self._end("a frame could not be decoded")
                    return
                seq += 1
                frame = Frame(seq, image, arrived - self.latency_s)
                with self._arrived:
                    self._frame = frame
                    self._arrived.notify_all()
        except Exception as err:  # noqa: BLE001 - reported to the reader as a lost camera, not lost in a thread
            self._end(f"reading failed: {type(err).__name__}: {err}")
        finally:
            cap.release()  # in this thread: never while grab() runs

    def _end(self, why: str) -> None:
        with self._arrived:
            if self._ended is None and not self._stop.is_set():
                self._ended = why
            self._arrived.notify_all()

    @property
    def ended(self) -> str | None:
        """Why the stream ended (None while frames come, or after :meth:`close`)."""
        return self._ended

    def latest(self) -> Frame | None:
        """The newest frame (None before the first)."""
        with self._lock:
            return self._frame

    def wait_newer(self, seq: int, timeout_s: float) -> Frame | None:
        """The newest frame once it is later than frame number ``seq``, waiting up to ``timeout_s``; None if
        none came (or the stream ended)."""
        deadline = time.monotonic() + timeout_s
        with self._arrived:
            while (self._frame is None or self._frame.seq <= seq) and self._ended is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._arrived.wait(left)
            frame = self._frame
        return frame if frame is not None and frame.seq > seq else None

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the reader thread; the camera is released in it (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def __enter__(self) -> LiveCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class CameraTracked:
    """``robot`` with its tracker fields from ``camera`` through ``tracker`` (see the module docstring).

    ``robot``: a connected driver (:class:`~selfid_jax.robot.protocol.Robot`).
    ``camera``: an open :class:`LiveCamera`; ``tracker``: a
    :class:`~selfid_jax.robot.camera.tracker.TagTracker` for its intrinsics
    (its ``rotation`` setting as the task's). ``wait_s``: how long a reading
    after a move waits for a frame exposed after it. Closing closes both.
    """

    def __init__(self, robot: Robot, camera: LiveCamera, tracker: TagTracker, *, wait_s: float = 0.5,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.robot, self.camera, self.tracker = robot, camera, tracker
        self.wait_s, self._clock = float(wait_s), clock
        self.late = 0  # readings after a move with no frame exposed after it (dropouts "late")
        self._moved_at = -math.inf  # the runner's clock when the last move was sent
        self._closed = False
        first = camera.latest()
        assert first is not None  # LiveCamera opens with a frame
        self._prime_reason = self.tracker.track(first.image, first.t).reason  # primes the stale test; not reported
        self._seq = first.seq
        self._pose: TagPose | None = None  # the newest tracked frame's result
        self._good: TagPose | None = None  # the last valid pose
        self._first_t = first.t

    def limits(self) -> RobotLimits:
        """The driver's limits."""
        return self.robot.limits()

    def move(self, target: np.ndarray) -> None:
        """The driver's move; frames exposed before it are not reported as its result."""
        self.robot.move(target)
        self._moved_at = self._clock()

    def read(self) -> Observation:
        """The driver's actuator positions with the camera's newest pose, ``t`` and ``tracker_t`` on the runner's
        clock; RobotConnectionError if the camera's stream has ended."""
        obs = self.robot.read()
        frame = self.camera.latest()
        t = self._clock()  # after the frame was taken: its stamp is not later than the reading's
        if self.camera.ended is not None:
            raise RobotConnectionError(f"{self.camera.name}: {self.camera.ended}")
        late = False
        if frame is not None and frame.t <= self._moved_at:  # exposed before the last move: wait for a newer one
            deadline = self._clock() + self.wait_s
            while frame.t <= self._moved_at:
                newer = self.camera.wait_newer(frame.seq, deadline - self._clock())
                if newer is None:
                    late = True
                    self.late += 1
                    break
                frame = newer
        if frame is not None and frame.seq != self._seq:
            self._seq = frame.seq
            self._pose = self.tracker.track(frame.image, frame.t)
            if self._pose.valid:
                self._good = self._pose
        pose = self._pose
        if pose is not None and pose.valid and not late:
            return Observation(t, obs.q, pose.position.copy(), pose.quaternion.copy(), pose.t, True)
        good = self._good  # a dropout: the last good pose and its stamp, which does not advance while it lasts
        if good is not None:
            return Observation(t, obs.q, good.position.copy(), good.quaternion.copy(), good.t, False)
        stamp = self._first_t if pose is None else pose.t
        return Observation(t, obs.q, np.full(3, np.nan), np.full(4, np.nan), min(stamp, t), False)

    def counts(self) -> dict[str, Any]:
        """Frames received, tracked (the first, which primes the stale test, apart) and valid, and dropouts by
        reason (``late`` included): plain values for a summary."""
        latest = self.camera.latest()
        dropouts: Counter[str] = Counter(self.tracker.dropouts)
        if self._prime_reason:
            dropouts[self._prime_reason] -= 1
        if self.late:
            dropouts["late"] += self.late
        tracked = self.tracker.frames - 1
        return {"camera": str(self.camera.source), "frames": 0 if latest is None else latest.seq,
                "tracked": tracked, "poses": tracked - sum(v for k, v in dropouts.items() if k != "late"),
                "dropouts": {k: v for k, v in sorted(dropouts.items()) if v > 0}}

    def close(self) -> None:
        """Close the driver, then the camera (both, whichever fails; idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.robot.close()
        finally:
            self.camera.close()

