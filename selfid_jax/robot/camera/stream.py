"""A camera served as IP cameras serve one: JPEG frames over HTTP as ``multipart/x-mixed-replace`` (MJPEG).

:class:`MjpegServer` binds ``host:port`` (``port`` 0: a free one) and
streams, at ``url`` (``http://HOST:PORT/stream.mjpg``), each frame published
with :meth:`MjpegServer.publish` to every client connected, newest first: a
client that reads slowly skips frames rather than queueing them, as a
camera does. Any other path is answered 404. OpenCV opens the stream as it
opens an IP camera, ``cv2.VideoCapture(url)`` (FFmpeg's ``mpjpeg`` demuxer),
so a simulated camera reaches the online runner by the road a real one
takes (:mod:`selfid_jax.robot.camera.live`), not by a side channel.

:class:`FrameFeed` is the camera's shutter: a thread that calls a frame
source's ``render()`` every ``1 / fps`` s (``time.monotonic``; after a late
frame the next one follows a period later, none is made up) and publishes
the frame ``latency_s`` after it was exposed, a steady pipeline delay as a
camera's (a frame that takes longer to render is sent when it is ready).
The source is built by a factory in the feed's own thread, so an OpenGL
context (:class:`~selfid_jax.robot.camera.sim.SimCamera`) is created and used
in one thread. ``freeze_at_s`` (s after :meth:`FrameFeed.start`) injects a
frozen camera: from then on the last frame's bytes are sent again at the
same rate (the stream goes on, the picture does not change: the tracker's
``stale`` frames).

Plain sockets, ``http.server`` and OpenCV's JPEG encoder; no pydantic, no runner.
"""

from __future__ import annotations

import http.server
import math
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import cv2
import numpy as np

__all__ = ["BOUNDARY", "STREAM_PATH", "FrameFeed", "FrameSource", "MjpegServer", "encode_jpeg"]

#: The path of the stream (as IP cameras name it).
STREAM_PATH = "/stream.mjpg"
#: The multipart boundary between frames.
BOUNDARY = "frame"
_WAIT_S = 0.5  # a client's longest wait for the next frame before it checks whether the server is closing


def encode_jpeg(frame: np.ndarray, quality: int = 90) -> bytes:
    """A frame ``(H, W)`` grey or ``(H, W, 3)`` RGB uint8 as JPEG bytes (``quality`` 1-100)."""
    frame = np.asarray(frame)
    if frame.dtype != np.uint8 or frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] != 3):
        raise ValueError(f"frame: expected (H, W) or (H, W, 3) uint8, got {frame.dtype} {frame.shape}")
    image = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)  # OpenCV writes BGR
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"frame: OpenCV could not encode a {frame.shape} frame as JPEG")
    return buffer.tobytes()


class _Handler(http.server.BaseHTTPRequestHandler):
    server: _HttpServer
    protocol_version = "HTTP/1.0"  # the stream ends when the connection closes, as IP cameras' do

    def do_GET(self) -> None:  # http.server's name for a GET handler
        if self.path.split("?", 1)[0] != self.server.stream_path:
            self.send_error(404, f"no such stream; the camera is at {self.server.stream_path}")
            return
        self.send_response(200)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-cache, no-store")
        self.send_header("Pragma", "no-cache")
        self.end_headers()
        owner = self.server.owner
        seq = 0
        try:
            while True:
                got = owner.wait_frame(seq)
                if got is None:  # the server is closing
                    return
                seq, jpeg = got
                head = f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n"
                self.wfile.write(head.encode("ascii") + jpeg + b"\r\n")
                self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            return  # the client went away

    def log_message(self, format: str, *args: Any) -> None:  # http.server's signature
        pass  # a camera does not log each request


class _HttpServer(http.server.ThreadingHTTPServer):
    daemon_threads = True
    owner: MjpegServer
    stream_path: str


class MjpegServer:
    """An MJPEG-over-HTTP camera at ``http://HOST:PORT/stream.mjpg`` (see the module docstring).

    Binding happens here (``OSError`` if ``host:port`` cannot be bound);
    :meth:`start` serves in a daemon thread; :meth:`close` (or a ``with``
    block) ends every stream and frees the port. ``quality``: the JPEG
    quality of :meth:`publish` (1-100).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *, quality: int = 90) -> None:
        if isinstance(quality, bool) or not isinstance(quality, int) or not 1 <= quality <= 100:
            raise ValueError(f"quality: expected a JPEG quality 1..100, got {quality!r}")
        self.quality = quality
        self._cond = threading.Condition()
        self._jpeg: bytes | None = None
        self._seq = 0  # frames published
        self._closed = False
        self._thread: threading.Thread | None = None
        self._httpd = _HttpServer((host, int(port)), _Handler)
        self._httpd.owner = self
        self._httpd.stream_path = STREAM_PATH
        self.host = str(self._httpd.server_address[0])
        self.port = int(self._httpd.server_address[1])

    @property
    def url(self) -> str:
        """``http://HOST:PORT/stream.mjpg``, what ``cv2.VideoCapture`` opens."""
        return f"http://{self.host}:{self.port}{STREAM_PATH}"

    @property
    def frames(self) -> int:
        """Frames published so far."""
        return self._seq

    def start(self) -> MjpegServer:
        """Serve in a daemon thread (once); returns the server."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.1},
                                            name="mjpeg-server", daemon=True)
            self._thread.start()
        return self

    def publish(self, frame: np.ndarray) -> None:
        """Send ``frame`` (``(H, W)`` grey or ``(H, W, 3)`` RGB uint8) to every client as the newest frame."""
        self.publish_jpeg(encode_jpeg(frame, self.quality))

    def publish_jpeg(self, jpeg: bytes) -> None:
        """Send already encoded JPEG bytes (the same bytes again: a frozen camera's next frame)."""
        with self._cond:
            self._jpeg = bytes(jpeg)
            self._seq += 1
            self._cond.notify_all()

    @property
    def last_jpeg(self) -> bytes | None:
        """The newest frame's JPEG bytes (None before the first)."""
        return self._jpeg

    def wait_frame(self, seen: int) -> tuple[int, bytes] | None:
        """The newest frame after frame number ``seen`` as ``(number, jpeg)``, waiting for it; None once closed."""
        with self._cond:
            while not self._closed and (self._seq == seen or self._jpeg is None):
                self._cond.wait(_WAIT_S)
            if self._closed or self._jpeg is None:
                return None
            return self._seq, self._jpeg

    def close(self) -> None:
        """End every stream and free the port (idempotent)."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._httpd.shutdown()
        self._httpd.server_close()

    def __enter__(self) -> MjpegServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FrameSource(Protocol):
    """What a :class:`FrameFeed` films: ``render() -> (H, W)`` or ``(H, W, 3)`` RGB uint8, and ``close()``."""

    def render(self) -> np.ndarray: ...

    def close(self) -> None: ...


class FrameFeed:
    """Publish ``source.render()`` to ``server`` every ``1 / fps`` s from a thread of its own (module docstring).

    ``make_source``: called once, in the feed's thread, to build the
    :class:`FrameSource` (its OpenGL context then lives in that thread);
    :meth:`start` waits for it and the first frame, and re-raises its
    exception. ``latency_s``: each frame is sent this long after its
    exposure (the moment ``render`` is called: the scene's state then), as
    a camera's pipeline delays it, or later where rendering takes longer
    (counted in ``late``); a steady latency is what a tracker can subtract.
    Frames are exposed every ``max(1 / fps, latency_s)`` s.
    ``freeze_at_s``: s after :meth:`start` from which the last
    frame is sent again unchanged (None: never). ``clock``: seconds,
    ``time.monotonic`` by default.
    """

    def __init__(self, server: MjpegServer, make_source: Callable[[], FrameSource], *, fps: float,
                 latency_s: float = 0.0, freeze_at_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps: expected a frame rate > 0, got {fps!r}")
        if not (isinstance(latency_s, (int, float)) and math.isfinite(latency_s) and latency_s >= 0):
            raise ValueError(f"latency_s: expected seconds >= 0, got {latency_s!r}")
        if freeze_at_s is not None and not (math.isfinite(freeze_at_s) and freeze_at_s >= 0):
            raise ValueError(f"freeze_at_s: expected seconds >= 0 or None, got {freeze_at_s!r}")
        self.server, self._make, self.period = server, make_source, 1.0 / float(fps)
        self.latency_s, self.freeze_at_s, self._clock = float(latency_s), freeze_at_s, clock
        self.source: FrameSource | None = None  # built in the feed's thread (start)
        self.rendered = 0  # frames rendered
        self.render_s = 0.0  # s spent rendering and encoding, all frames
        self.late = 0  # frames whose rendering took longer than latency_s (sent late)
        self._ready = threading.Event()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    def start(self, timeout_s: float = 60.0) -> FrameFeed:
        """Start the thread, wait until the source is built and its first frame published; re-raise the source's
        error (a scene that cannot be built or rendered), or TimeoutError."""
        if self._thread is not None:
            raise RuntimeError("the frame feed is already started")
        self._thread = threading.Thread(target=self._run, name="camera-feed", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            self.close()
            raise TimeoutError(f"the camera's first frame took longer than {timeout_s:g} s")
        if self._error is not None:
            self.close()
            raise self._error
        return self

    def _run(self) -> None:
        source: FrameSource | None = None
        try:
            try:
                source = self.source = self._make()
                t0 = self._clock()
                jpeg = self._frame(t0)
            except BaseException as err:  # noqa: BLE001 - handed to start(), which re-raises it in the caller's thread
                self._error = err
                return
            finally:
                self._ready.set()
            due = t0 + self.period
            while not self._stop.is_set():
                wait = due - self._clock()
                if wait > 0 and self._stop.wait(wait):
                    break
                exposed = self._clock()
                due = max(exposed, due) + self.period  # a late frame is followed one period later, none made up
                if self.freeze_at_s is not None and exposed - t0 >= self.freeze_at_s:
                    self.server.publish_jpeg(jpeg)  # a frozen camera: the same picture, still streaming
                else:
                    jpeg = self._frame(exposed)
        finally:
            if source is not None:
                source.close()

    def _frame(self, exposed: float) -> bytes:
        """Render and encode a frame exposed now, hold it until ``exposed + latency_s``, publish it."""
        assert self.source is not None
        jpeg = encode_jpeg(self.source.render(), self.server.quality)
        took = self._clock() - exposed
        self.render_s += took
        self.rendered += 1
        self.late += took > self.latency_s
        hold = exposed + self.latency_s - self._clock()
        if hold > 0:
            self._stop.wait(hold)
        self.server.publish_jpeg(jpeg)
        return jpeg

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the thread and free the source (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
