"""The robot protocol over TCP: a server for any :class:`~selfid_jax.robot.protocol.Robot` and the
:class:`RemoteRobot` client.

Plain TCP (the standard library's sockets) carrying msgpack messages, one
request and one reply at a time. A lost peer shows at once as EOF, a reset or
a refused connection, and every call has one deadline, so the online runner's
watchdog sees a dead, silent or dripping robot within ``timeout_s``. (ZeroMQ's
REQ/REP would hide a lost peer behind silent reconnects and leave the REQ socket
waiting for a reply that never comes.)

Framing: each message is a 4-byte big-endian length, then a msgpack map.
Requests ``{"op": "hello" | "limits" | "read" | "move" | "close", "id": N, ...}``
(``move`` carries ``"target"``, a list of float64; ``id`` an integer the client
counts up); replies ``{"ok": true, "id": N, ...}`` or ``{"ok": false, "id": N,
"error": "...", "kind": "robot" | "request"}``, echoing the request's ``id``
(a request without one gets a reply without one). Floats travel as msgpack
float64: lossless. The server answers one client at a time; a second client
waits until the first disconnects.

What the transport guarantees:

* the client: the whole call (send and reply) finishes within ``timeout_s`` or
  raises :class:`~selfid_jax.robot.protocol.RobotConnectionError`, however the
  reply's bytes trickle in; a reply whose ``id`` is not the request's (a
  duplicated or late reply) is a protocol error, never the answer; every reply
  is checked (fields present, types, shapes, finite numbers, ``valid`` a real
  boolean) and a bad one raises ``RobotConnectionError`` naming the field. After
  any ``RobotConnectionError`` the client is closed: it never retries.
* the server: a frame is read whole within ``frame_timeout_s`` of its first
  byte or the connection is dropped; bytes inside a frame are never read as a
  new frame. Every move is checked before the driver sees it (a list of
  ``n`` numbers, finite, within the driver's limits, within ``max_step`` of the
  actuators' current position); a refused move gets an error reply and the
  driver is not called. No request, malformed or not, ends the serve loop.

Size: about 450 lines, both ends of one wire protocol (framing, ids, reply and move checks), kept together so
the two cannot drift apart.
"""

from __future__ import annotations

import math
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any, NoReturn

import numpy as np

from selfid_jax.robot.protocol import Observation, RobotConnectionError, RobotError, RobotLimits, check_limits

__all__ = ["MAX_MESSAGE", "FRAME_TIMEOUT_S", "RemoteRobot", "RobotServer", "recv_message", "send_message"]

MAX_MESSAGE = 1 << 20
"""Largest message accepted (bytes): a malformed length cannot make a peer allocate more."""

FRAME_TIMEOUT_S = 5.0
"""The server's default deadline for a whole frame, from its first byte [s]."""

_HEADER = struct.Struct(">I")


class _Deadline(TimeoutError):
    """The deadline passed (a ``TimeoutError``) with ``got`` bytes of the frame already read."""

    def __init__(self, got: int):
        super().__init__("deadline passed")
        self.got = got


def send_message(sock: socket.socket, message: dict[str, Any], deadline: float | None = None) -> None:
    """Send one msgpack map, length-prefixed (``TimeoutError`` if not sent by ``deadline``, monotonic s)."""
    import msgpack

    body = msgpack.packb(message, use_bin_type=True)
    if deadline is not None:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("deadline passed before sending")
        sock.settimeout(left)
    sock.sendall(_HEADER.pack(len(body)) + body)


def _recv_exact(sock: socket.socket, size: int, deadline: float | None, buf: bytearray) -> None:
    """Append ``size`` bytes to ``buf`` by ``deadline`` (``_Deadline`` with the count read so far if not)."""
    end = len(buf) + size
    while len(buf) < end:
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0:
                raise _Deadline(len(buf))
            sock.settimeout(left)
        try:
            chunk = sock.recv(end - len(buf))
        except TimeoutError:
            raise _Deadline(len(buf)) from None
        if not chunk:
            raise ConnectionResetError("the peer closed the connection")
        buf.extend(chunk)


def _decode(body: bytes) -> dict[str, Any]:
    import msgpack

    try:
        message = msgpack.unpackb(body, raw=False)
    except Exception as err:  # noqa: BLE001 - msgpack raises several unrelated types for bad bytes
        raise ValueError(f"not msgpack ({type(err).__name__}: {err})") from None
    if not isinstance(message, dict):
        raise ValueError(f"expected a map, got {type(message).__name__}")
    return message


def recv_message(sock: socket.socket, deadline: float | None = None) -> dict[str, Any]:
    """Receive one length-prefixed msgpack map, whole, by ``deadline`` (monotonic s; None: the socket's timeout
    per ``recv``). ``TimeoutError`` if it does not arrive in time, ``ValueError`` if it is not one or too large."""
    buf = bytearray()
    _recv_exact(sock, _HEADER.size, deadline, buf)
    (size,) = _HEADER.unpack(bytes(buf))
    if size > MAX_MESSAGE:
        raise ValueError(f"message of {size} bytes, more than {MAX_MESSAGE}")
    _recv_exact(sock, size, deadline, buf)
    return _decode(bytes(buf[_HEADER.size:]))


def _floats(values: Any) -> list[float]:
    return [float(v) for v in np.asarray(values, np.float64).reshape(-1)]


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


class RobotServer:
    """Serve ``robot`` (any :class:`~selfid_jax.robot.protocol.Robot`) on ``host:port`` (0: a free port).

    ``serve_forever`` answers clients one at a time until :meth:`shutdown`. A
    malformed request gets an error reply and changes nothing; a ``RobotError``
    (or any other exception) from the robot is passed back as one. ``close`` from a
    client only ends that client's session: the robot is held where it is and
    keeps running for the next client; the robot itself is closed by :meth:`shutdown`.

    A frame must arrive whole within ``frame_timeout_s`` of its first byte or the
    connection is dropped. Every move is checked here before the robot sees it
    (module docstring); ``position``, a callable returning the actuators' current
    position ``(n,)``, is what ``max_step`` is measured from (default
    ``robot.read().q``).
    """

    def __init__(self, robot: Any, host: str = "127.0.0.1", port: int = 0, *, info: dict | None = None,
                 frame_timeout_s: float = FRAME_TIMEOUT_S, position: Callable[[], Any] | None = None,
                 on_connect: Callable[[], Any] | None = None):
        if not frame_timeout_s > 0:
            raise ValueError(f"frame_timeout_s must be > 0, got {frame_timeout_s}")
        self.robot = robot
        self.info = dict(info or {})
        self.frame_timeout_s = float(frame_timeout_s)
        self._position = position if position is not None else (lambda: robot.read().q)
        self._on_connect = on_connect
        self._limits: RobotLimits | None = None
        self._sock = socket.create_server((host, port))
        self._sock.settimeout(0.2)
        self.host, self.port = self._sock.getsockname()[:2]
        self._stop = threading.Event()

    def shutdown(self) -> None:
        """Stop serving and close the robot (idempotent)."""
        self._stop.set()
        try:
            self._sock.close()
        finally:
            self.robot.close()

    def serve_forever(self) -> None:
        """Answer clients until :meth:`shutdown` (from another thread or a signal handler)."""
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                raise
            with conn:
                try:
                    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    if self._on_connect is not None:
                        self._on_connect()
                    self._session(conn)
                except OSError:
                    pass  # the client went away: serve the next one

    def _next_request(self, conn: socket.socket) -> dict[str, Any] | None:
        """The next whole request, or None when the connection is to be dropped (EOF, stall, stop)."""
        buf = bytearray()
        while True:  # idle between frames: poll so that shutdown is seen
            if self._stop.is_set():
                return None
            conn.settimeout(0.2)
            try:
                chunk = conn.recv(_HEADER.size)
            except TimeoutError:
                continue
            if not chunk:
                return None
            buf.extend(chunk)
            break
        deadline = time.monotonic() + self.frame_timeout_s  # the whole frame from its first byte
        try:
            _recv_exact(conn, _HEADER.size - len(buf), deadline, buf)
            (size,) = _HEADER.unpack(bytes(buf))
            if size > MAX_MESSAGE:
                raise ValueError(f"message of {size} bytes, more than {MAX_MESSAGE}")
            _recv_exact(conn, size, deadline, buf)
        except TimeoutError:
            return None  # a client stalled inside a frame: framing cannot be trusted, drop it
        return _decode(bytes(buf[_HEADER.size:]))

    def _session(self, conn: socket.socket) -> None:
        while not self._stop.is_set():
            try:
                request = self._next_request(conn)
            except (ConnectionError, OSError):
                return
            except ValueError as err:  # a malformed message: say so and drop the client
                try:
                    send_message(conn, {"ok": False, "kind": "request", "error": f"malformed message: {err}"},
                                 time.monotonic() + self.frame_timeout_s)
                except OSError:
                    pass
                return
            if request is None:
                return
            reply = self.handle(request)
            try:
                send_message(conn, reply, time.monotonic() + self.frame_timeout_s)
            except OSError:
                return
            if request.get("op") == "close":
                return

    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        """The reply to one request, echoing its ``id`` (never raises for a bad request or a robot error)."""
        try:
            reply = self._answer(request)
        except RobotError as err:
            reply = {"ok": False, "kind": "robot", "error": str(err)}
        except Exception as err:  # noqa: BLE001 - any driver fault is a reply, never a dead serve thread
            reply = {"ok": False, "kind": "robot", "error": f"{type(err).__name__}: {err}"}
        if "id" in request:
            reply["id"] = request["id"]
        return reply

    def limits(self) -> RobotLimits:
        """The robot's limits, checked once (``ValueError`` naming the field if they are not valid)."""
        if self._limits is None:
            self._limits = check_limits(self.robot.limits())
        return self._limits

    def check_move(self, target: Any) -> np.ndarray | str:
        """``target`` as an ``(n,)`` array, or why it is refused (nothing is moved either way)."""
        if not isinstance(target, list) or not all(_is_number(v) for v in target):
            return "move needs 'target', a list of numbers"
        lim = self.limits()
        n = lim.lower.shape[0]
        if len(target) != n:
            return f"move refused: target has {len(target)} entries, the robot has {n} actuators"
        u = np.asarray(target, np.float64)
        bad = np.flatnonzero(~np.isfinite(u))
        if bad.size:
            return f"move refused: target[{bad[0]}] is {u[bad[0]]}"
        bad = np.flatnonzero((u < lim.lower) | (u > lim.upper))
        if bad.size:
            i = bad[0]
            return (f"move refused: target[{i}] = {u[i]:.6g} is outside the limits "
                    f"[{lim.lower[i]:.6g}, {lim.upper[i]:.6g}]")
        q = np.asarray(self._position(), np.float64).reshape(-1)
        if q.shape != (n,) or not np.all(np.isfinite(q)):
            return f"move refused: the actuators' position is not {n} finite numbers: {q.tolist()}"
        step = np.abs(u - q)
        bad = np.flatnonzero(step > lim.max_step * (1 + 1e-9) + 1e-12)
        if bad.size:
            i = bad[0]
            return (f"move refused: actuator {i} would step {step[i]:.6g} from {q[i]:.6g}, "
                    f"more than max_step {lim.max_step[i]:.6g}")
        return u

    def _answer(self, request: dict[str, Any]) -> dict[str, Any]:
        op = request.get("op")
        if op == "hello":
            return {"ok": True, "info": self.info}
        if op == "limits":
            lim = self.limits()
            return {"ok": True, "lower": _floats(lim.lower), "upper": _floats(lim.upper),
                    "max_step": _floats(lim.max_step)}
        if op == "read":
            o = self.robot.read()
            valid = bool(o.valid) if isinstance(o.valid, bool | np.bool_) else f"not a boolean: {o.valid!r:.80}"
            return {"ok": True, "t": float(o.t), "q": _floats(o.q), "position": _floats(o.position),
                    "quaternion": _floats(o.quaternion), "tracker_t": float(o.tracker_t),
                    "valid": valid}
        if op == "move":
            u = self.check_move(request.get("target"))
            if isinstance(u, str):
                kind = "request" if u.startswith("move needs") else "robot"
                return {"ok": False, "kind": kind, "error": u}
            self.robot.move(u)
            return {"ok": True}
        if op == "close":
            hold = getattr(self.robot, "hold", None)
            if hold is not None:
                hold()
            return {"ok": True}
        return {"ok": False, "kind": "request", "error": f"unknown op {op!r}; ops: hello, limits, read, move, close"}


class RemoteRobot:
    """A :class:`~selfid_jax.robot.protocol.Robot` served by :class:`RobotServer` at ``host:port``.

    Every call (request and whole reply) finishes within ``timeout_s`` seconds;
    a timeout, a refused or lost connection, a reply to another request (its
    ``id`` is not this request's) or a malformed reply (a missing field, a wrong
    type or shape, a non-finite number, ``valid`` not a boolean) raises
    :class:`~selfid_jax.robot.protocol.RobotConnectionError` naming what was
    wrong, and the client is unusable afterwards (the runner stops: it never
    retries a move it cannot confirm). A move the robot refuses raises
    :class:`~selfid_jax.robot.protocol.RobotError`.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 50007, timeout_s: float = 5.0):
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self.address = (host, int(port))
        self.timeout_s = float(timeout_s)
        self._next_id = 1
        self._n: int | None = None  # actuators, once a limits or read reply has said
        try:
            self._sock: socket.socket | None = socket.create_connection(self.address, timeout=self.timeout_s)
        except OSError as err:
            raise RobotConnectionError(f"robot at {host}:{port}: cannot connect ({err})") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        info = self._call({"op": "hello"}).get("info", {})
        if not isinstance(info, dict):
            self._fail("'hello'", f"reply field 'info' is a {type(info).__name__}, not a map")
        self.info = info

    @property
    def _where(self) -> str:
        return f"robot at {self.address[0]}:{self.address[1]}"

    def _fail(self, what: str, why: str) -> NoReturn:
        self._drop()
        raise RobotConnectionError(f"{self._where}: protocol error in the reply to {what}: {why}")

    def _call(self, request: dict[str, Any]) -> dict[str, Any]:
        op = request["op"]
        if self._sock is None:
            raise RobotConnectionError(f"{self._where}: the connection is closed")
        rid = self._next_id
        self._next_id += 1
        deadline = time.monotonic() + self.timeout_s  # one deadline for the whole call
        try:
            send_message(self._sock, {**request, "id": rid}, deadline)
            reply = recv_message(self._sock, deadline)
        except TimeoutError:
            self._drop()
            raise RobotConnectionError(f"{self._where}: no reply to {op!r} within {self.timeout_s} s") from None
        except (OSError, ValueError) as err:
            self._drop()
            raise RobotConnectionError(f"{self._where}: connection lost during {op!r} ({err})") from None
        what = f"{op!r} (request id {rid})"
        if "id" not in reply:
            self._fail(what, "the reply has no 'id'")
        if reply["id"] != rid or isinstance(reply["id"], bool):
            self._fail(what, f"the reply has id {reply['id']!r}: a duplicated or late reply to another request")
        ok = reply.get("ok")
        if not isinstance(ok, bool):
            self._fail(what, f"reply field 'ok' is {ok!r}, not a boolean")
        if not ok:
            error = reply.get("error")
            if reply.get("kind") == "robot" and isinstance(error, str):
                raise RobotError(f"{self._where}: {error}")
            self._drop()
            raise RobotConnectionError(f"{self._where}: request {op!r} refused: {error}")
        return reply

    def _drop(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def _vector(self, what: str, reply: dict[str, Any], key: str, size: int | None, *,
                finite: bool = True) -> np.ndarray:
        if key not in reply:
            self._fail(what, f"reply field {key!r} is missing")
        v = reply[key]
        if not isinstance(v, list) or not all(_is_number(x) for x in v):
            self._fail(what, f"reply field {key!r} is {v!r:.80}, not a list of numbers")
        if size is None and not v:
            self._fail(what, f"reply field {key!r} is empty")
        if size is not None and len(v) != size:
            self._fail(what, f"reply field {key!r} has {len(v)} entries, expected {size}")
        x = np.array(v, np.float64)
        if finite and not np.all(np.isfinite(x)):
            i = int(np.flatnonzero(~np.isfinite(x))[0])
            self._fail(what, f"reply field {key!r}[{i}] is {x[i]}, not finite")
        return x

    def _time(self, what: str, reply: dict[str, Any], key: str) -> float:
        if key not in reply:
            self._fail(what, f"reply field {key!r} is missing")
        v = reply[key]
        if not _is_number(v) or not math.isfinite(v):
            self._fail(what, f"reply field {key!r} is {v!r:.80}, not a finite number")
        return float(v)

    def limits(self) -> RobotLimits:
        """The robot's limits, ``(n,)`` arrays."""
        r = self._call({"op": "limits"})
        what = "'limits'"
        lower = self._vector(what, r, "lower", self._n)
        upper = self._vector(what, r, "upper", lower.shape[0])
        step = self._vector(what, r, "max_step", lower.shape[0])
        self._n = lower.shape[0]
        return RobotLimits(lower, upper, step)

    def read(self) -> Observation:
        """The latest actuator positions and tracker pose (copies, checked)."""
        r = self._call({"op": "read"})
        what = "'read'"
        if "valid" not in r:
            self._fail(what, "reply field 'valid' is missing")
        valid = r["valid"]
        if not isinstance(valid, bool):
            self._fail(what, f"reply field 'valid' is {valid!r:.80}, not a boolean")
        t = self._time(what, r, "t")
        q = self._vector(what, r, "q", self._n)
        self._n = q.shape[0]
        position = self._vector(what, r, "position", 3, finite=valid)
        quaternion = self._vector(what, r, "quaternion", 4, finite=valid)
        tracker_t = self._time(what, r, "tracker_t")
        return Observation(t, q, position, quaternion, tracker_t, valid)

    def move(self, target: np.ndarray) -> None:
        """Command the absolute target ``(n,)``."""
        self._call({"op": "move", "target": _floats(target)})

    def close(self) -> None:
        """End the session (the robot holds where it is); idempotent, never raises."""
        if self._sock is None:
            return
        try:
            self._call({"op": "close"})
        except RobotError:
            pass
        finally:
            self._drop()
