"""The robot protocol over TCP: a server for any :class:`~selfid_jax.robot.protocol.Robot` and the
:class:`RemoteRobot` client.

Plain TCP (the standard library's sockets) carrying msgpack messages, one
request and one reply at a time. A lost peer shows at once as EOF, a reset or
a refused connection, and every call has a timeout, so the online runner's
watchdog sees a dead or silent robot within ``timeout_s``. (ZeroMQ's REQ/REP
would hide a lost peer behind silent reconnects and leave the REQ socket
waiting for a reply that never comes.)

Framing: each message is a 4-byte big-endian length, then a msgpack map.
Requests ``{"op": "hello" | "limits" | "read" | "move" | "close", ...}``
(``move`` carries ``"target"``, a list of float64); replies
``{"ok": true, ...}`` or ``{"ok": false, "error": "...", "kind": "robot" |
"request"}``. Floats travel as msgpack float64: lossless. The server answers
one client at a time; a second client waits until the first disconnects.
"""

from __future__ import annotations

import socket
import struct
import threading
from typing import Any

import numpy as np

from selfid_jax.robot.protocol import Observation, RobotConnectionError, RobotError, RobotLimits

__all__ = ["MAX_MESSAGE", "RemoteRobot", "RobotServer", "recv_message", "send_message"]

MAX_MESSAGE = 1 << 20
"""Largest message accepted (bytes): a malformed length cannot make a peer allocate more."""

_HEADER = struct.Struct(">I")


def send_message(sock: socket.socket, message: dict[str, Any]) -> None:
    """Send one msgpack map, length-prefixed."""
    import msgpack

    body = msgpack.packb(message, use_bin_type=True)
    sock.sendall(_HEADER.pack(len(body)) + body)


def _recv_exact(sock: socket.socket, size: int) -> bytes:
    chunks, got = [], 0
    while got < size:
        chunk = sock.recv(size - got)
        if not chunk:
            raise ConnectionResetError("the peer closed the connection")
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


def recv_message(sock: socket.socket) -> dict[str, Any]:
    """Receive one length-prefixed msgpack map (``ValueError`` if it is not one or is too large)."""
    import msgpack

    (size,) = _HEADER.unpack(_recv_exact(sock, _HEADER.size))
    if size > MAX_MESSAGE:
        raise ValueError(f"message of {size} bytes, more than {MAX_MESSAGE}")
    message = msgpack.unpackb(_recv_exact(sock, size), raw=False)
    if not isinstance(message, dict):
        raise ValueError(f"expected a map, got {type(message).__name__}")
    return message


def _floats(values: Any) -> list[float]:
    return [float(v) for v in np.asarray(values, np.float64).reshape(-1)]


class RobotServer:
    """Serve ``robot`` (any :class:`~selfid_jax.robot.protocol.Robot`) on ``host:port`` (0: a free port).

    ``serve_forever`` answers clients one at a time until :meth:`shutdown`. A
    malformed request gets an error reply and changes nothing; a ``RobotError``
    from the robot (a refused move) is passed back as one. ``close`` from a
    client only ends that client's session: the robot is held where it is and
    keeps running for the next client; the robot itself is closed by :meth:`shutdown`.
    """

    def __init__(self, robot: Any, host: str = "127.0.0.1", port: int = 0, *, info: dict | None = None):
        self.robot = robot
        self.info = dict(info or {})
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
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._session(conn)

    def _session(self, conn: socket.socket) -> None:
        conn.settimeout(0.2)
        while not self._stop.is_set():
            try:
                request = recv_message(conn)
            except TimeoutError:
                continue
            except (ConnectionError, OSError):
                return
            except ValueError as err:  # a malformed message: say so and drop the client
                try:
                    send_message(conn, {"ok": False, "kind": "request", "error": f"malformed message: {err}"})
                except OSError:
                    pass
                return
            reply = self.handle(request)
            try:
                send_message(conn, reply)
            except OSError:
                return
            if request.get("op") == "close":
                return

    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        """The reply to one request (never raises for a bad request or a robot error)."""
        op = request.get("op")
        try:
            if op == "hello":
                return {"ok": True, "info": self.info}
            if op == "limits":
                lim = self.robot.limits()
                return {"ok": True, "lower": _floats(lim.lower), "upper": _floats(lim.upper),
                        "max_step": _floats(lim.max_step)}
            if op == "read":
                o = self.robot.read()
                return {"ok": True, "t": float(o.t), "q": _floats(o.q), "position": _floats(o.position),
                        "quaternion": _floats(o.quaternion), "tracker_t": float(o.tracker_t), "valid": bool(o.valid)}
            if op == "move":
                target = request.get("target")
                if not isinstance(target, list) or not all(isinstance(v, int | float) for v in target):
                    return {"ok": False, "kind": "request", "error": "move needs 'target', a list of numbers"}
                self.robot.move(np.asarray(target, np.float64))
                return {"ok": True}
            if op == "close":
                hold = getattr(self.robot, "hold", None)
                if hold is not None:
                    hold()
                return {"ok": True}
        except RobotError as err:
            return {"ok": False, "kind": "robot", "error": str(err)}
        return {"ok": False, "kind": "request", "error": f"unknown op {op!r}; ops: hello, limits, read, move, close"}


class RemoteRobot:
    """A :class:`~selfid_jax.robot.protocol.Robot` served by :class:`RobotServer` at ``host:port``.

    Every call waits at most ``timeout_s`` seconds for its reply; a timeout, a
    refused or lost connection or a malformed reply raises
    :class:`~selfid_jax.robot.protocol.RobotConnectionError` and the client is
    unusable afterwards (the runner stops: it never retries a move it cannot
    confirm). A move the robot refuses raises :class:`~selfid_jax.robot.protocol.RobotError`.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 50007, timeout_s: float = 5.0):
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self.address = (host, int(port))
        self.timeout_s = float(timeout_s)
        try:
            self._sock: socket.socket | None = socket.create_connection(self.address, timeout=self.timeout_s)
        except OSError as err:
            raise RobotConnectionError(f"robot at {host}:{port}: cannot connect ({err})") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.info = self._call({"op": "hello"}).get("info", {})

    def _call(self, request: dict[str, Any]) -> dict[str, Any]:
        where = f"robot at {self.address[0]}:{self.address[1]}"
        if self._sock is None:
            raise RobotConnectionError(f"{where}: the connection is closed")
        try:
            send_message(self._sock, request)
            reply = recv_message(self._sock)
        except TimeoutError:
            self._drop()
            raise RobotConnectionError(f"{where}: no reply to {request['op']!r} within {self.timeout_s} s") from None
        except (OSError, ValueError) as err:
            self._drop()
            raise RobotConnectionError(f"{where}: connection lost during {request['op']!r} ({err})") from None
        if not reply.get("ok"):
            if reply.get("kind") == "robot":
                raise RobotError(f"{where}: {reply.get('error')}")
            self._drop()
            raise RobotConnectionError(f"{where}: request {request['op']!r} refused: {reply.get('error')}")
        return reply

    def _drop(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def limits(self) -> RobotLimits:
        """The robot's limits, ``(n,)`` arrays."""
        r = self._call({"op": "limits"})
        return RobotLimits(*(np.asarray(r[k], np.float64) for k in ("lower", "upper", "max_step")))

    def read(self) -> Observation:
        """The latest actuator positions and tracker pose."""
        r = self._call({"op": "read"})
        return Observation(float(r["t"]), np.asarray(r["q"], np.float64), np.asarray(r["position"], np.float64),
                           np.asarray(r["quaternion"], np.float64), float(r["tracker_t"]), bool(r["valid"]))

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
