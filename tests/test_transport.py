"""The robot transport (selfid_jax.robot.transport) on localhost: one deadline per call, request ids echoed,
replies checked field by field, and a server that keeps framing across slow clients and checks every move before
its driver sees it. Small and fast: a fake server socket or a RobotServer in front of a numpy arm, in threads."""

from __future__ import annotations

import math
import re
import socket
import struct
import threading
import time

import msgpack
import numpy as np
import pytest

from selfid_jax.robot.protocol import Observation, RobotConnectionError, RobotError, RobotLimits
from selfid_jax.robot.transport import RemoteRobot, RobotServer, recv_message, send_message

N = 3
MAX_STEP = 0.1


class Arm:
    """A linear numpy arm (tracked point ``A q``) that records every move it is given."""

    def __init__(self):
        self.q = np.zeros(N)
        self.moves: list[np.ndarray] = []
        self.fail_read: Exception | None = None

    def limits(self):
        return RobotLimits(np.full(N, -1.0), np.full(N, 1.0), np.full(N, MAX_STEP))

    def read(self):
        if self.fail_read is not None:
            raise self.fail_read
        t = time.monotonic()
        p = np.array([[1.0, 0.2, 0.0], [0.0, 1.0, 0.3], [0.1, 0.0, 1.0]]) @ self.q
        return Observation(t, self.q.copy(), p, np.array([1.0, 0.0, 0.0, 0.0]), t, True)

    def move(self, target):
        self.moves.append(np.array(target, np.float64))
        if np.shape(target) != (N,):
            raise ValueError("operands could not be broadcast together")  # what a driver would do
        self.q = np.array(target, np.float64)

    def close(self):
        pass


@pytest.fixture
def served():
    """A RobotServer in front of an :class:`Arm`, serving in a thread: ``start(**kwargs) -> (server, arm)``."""
    started = []

    def start(**kwargs):
        arm = Arm()
        server = RobotServer(arm, "127.0.0.1", 0, **kwargs)
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        started.append((server, thread))
        return server, arm

    yield start
    for server, thread in started:
        server.shutdown()
        thread.join(timeout=2)
        assert not thread.is_alive()


def connect(server) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=3)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def frame(message) -> bytes:
    body = msgpack.packb(message, use_bin_type=True)
    return struct.pack(">I", len(body)) + body


class FakeServer:
    """One client, answered by ``answer(request) -> list of dicts (sent as frames) or bytes (sent raw)``; bounded."""

    def __init__(self, answer):
        self.answer = answer
        self.requests: list[dict] = []
        self._sock = socket.create_server(("127.0.0.1", 0))
        self._sock.settimeout(3)
        self.port = self._sock.getsockname()[1]
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self):
        try:
            conn, _ = self._sock.accept()
        except OSError:
            return
        with conn:
            conn.settimeout(3)
            for _ in range(20):
                try:
                    request = recv_message(conn)
                except (OSError, ValueError):
                    return
                self.requests.append(request)
                try:
                    for part in self.answer(request, conn):
                        conn.sendall(part if isinstance(part, bytes) else frame(part))
                except OSError:
                    return

    def close(self):
        self._sock.close()
        self._thread.join(timeout=5)


@pytest.fixture
def fake():
    made = []

    def make(answer):
        made.append(FakeServer(answer))
        return made[-1]

    yield make
    for f in made:
        f.close()


def echo(request, reply):
    """``reply`` with the request's id (when it has one)."""
    return {**reply, **({"id": request["id"]} if "id" in request else {})}


GOOD_READ = {"ok": True, "t": 1.0, "q": [0.0, 0.1, 0.2], "position": [0.1, 0.2, 0.3],
             "quaternion": [1.0, 0.0, 0.0, 0.0], "tracker_t": 0.99, "valid": True}
GOOD_LIMITS = {"ok": True, "lower": [-1.0] * N, "upper": [1.0] * N, "max_step": [MAX_STEP] * N}


# --- the client --------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_one_deadline_per_call_against_a_server_dripping_bytes(fake):
    """A reply dripped one byte every 0.3 s fails a 1 s call within about 1 s (the old per-recv timeout held it)."""

    def answer(request, conn):
        if request["op"] == "hello":
            return [echo(request, {"ok": True, "info": {}})]
        whole = frame(echo(request, GOOD_READ))
        for b in whole[:12]:  # bounded: about 3.6 s on a client that never gives up
            conn.sendall(bytes([b]))
            time.sleep(0.3)
        return []

    server = fake(answer)
    robot = RemoteRobot("127.0.0.1", server.port, timeout_s=1.0)
    t0 = time.monotonic()
    with pytest.raises(RobotConnectionError, match="no reply to 'read' within 1.0 s"):
        robot.read()
    assert time.monotonic() - t0 < 1.5
    with pytest.raises(RobotConnectionError, match="closed"):  # unusable afterwards: nothing more is sent
        robot.move(np.zeros(N))


def test_requests_carry_ids_and_a_duplicated_reply_is_a_protocol_error(fake):
    """Each reply is sent twice: the second copy of the 'limits' reply must not be taken as the 'read' reply."""
    server = fake(lambda request, conn: [echo(request, {"ok": True, "info": {}} if request["op"] == "hello"
                                                      else GOOD_LIMITS)] * 2)
    robot = RemoteRobot("127.0.0.1", server.port, timeout_s=2.0)
    with pytest.raises(RobotConnectionError, match=r"reply to 'limits' .*id 1.*duplicated or late"):
        robot.limits()  # the hello's duplicate (id 1) arrives as the answer to request 2
    deadline = time.monotonic() + 5  # the client refused the duplicate at once; let the server log request 2
    while len(server.requests) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    ids = [r.get("id") for r in server.requests]
    assert ids == [1, 2]


def test_a_reply_with_another_id_or_none_is_refused(fake):
    replies = iter([{"ok": True, "info": {}, "id": 1}, {**GOOD_READ, "id": 7}])
    server = fake(lambda request, conn: [next(replies)])
    robot = RemoteRobot("127.0.0.1", server.port, timeout_s=2.0)
    with pytest.raises(RobotConnectionError, match="has id 7"):
        robot.read()
    server2 = fake(lambda request, conn: [{"ok": True, "info": {}}])  # an old server: no ids at all
    with pytest.raises(RobotConnectionError, match="no 'id'"):
        RemoteRobot("127.0.0.1", server2.port, timeout_s=2.0)


def _without(d, key):
    return {k: v for k, v in d.items() if k != key}


@pytest.mark.parametrize(("op", "reply", "field"), [
    ("read", _without(GOOD_READ, "t"), "'t' is missing"),
    ("read", _without(GOOD_READ, "valid"), "'valid' is missing"),
    ("read", _without(GOOD_READ, "quaternion"), "'quaternion' is missing"),
    ("read", {**GOOD_READ, "t": "1.0"}, "'t' is '1.0', not a finite number"),
    ("read", {**GOOD_READ, "tracker_t": math.inf}, "'tracker_t' is inf"),
    ("read", {**GOOD_READ, "tracker_t": True}, "'tracker_t' is True"),
    ("read", {**GOOD_READ, "q": ["0.0", "0.1", "0.2"]}, "'q' is .*not a list of numbers"),
    ("read", {**GOOD_READ, "q": 0.5}, "'q' is 0.5, not a list of numbers"),
    ("read", {**GOOD_READ, "q": [0.0, math.nan, 0.0]}, r"'q'\[1\] is nan"),
    ("read", {**GOOD_READ, "position": [0.1, 0.2]}, "'position' has 2 entries, expected 3"),
    ("read", {**GOOD_READ, "quaternion": [1.0, 0.0, 0.0]}, "'quaternion' has 3 entries, expected 4"),
    ("read", {**GOOD_READ, "position": [0.1, math.nan, 0.3]}, r"'position'\[1\] is nan"),
    ("read", {**GOOD_READ, "valid": "False"}, "'valid' is 'False', not a boolean"),
    ("read", {**GOOD_READ, "valid": math.nan}, "'valid' is nan, not a boolean"),
    ("read", {**GOOD_READ, "valid": 1}, "'valid' is 1, not a boolean"),
    ("read", {**GOOD_READ, "ok": "yes"}, "'ok' is 'yes', not a boolean"),
    ("limits", _without(GOOD_LIMITS, "max_step"), "'max_step' is missing"),
    ("limits", {**GOOD_LIMITS, "upper": [1.0, 1.0]}, "'upper' has 2 entries, expected 3"),
    ("limits", {**GOOD_LIMITS, "lower": "low"}, "'lower' is 'low', not a list of numbers"),
])
def test_malformed_replies_raise_connection_error_naming_the_field(fake, op, reply, field):
    server = fake(lambda request, conn: [echo(request, {"ok": True, "info": {}} if request["op"] == "hello"
                                                      else reply)])
    robot = RemoteRobot("127.0.0.1", server.port, timeout_s=2.0)
    with pytest.raises(RobotConnectionError, match=field):
        getattr(robot, op)()


def test_a_read_whose_length_disagrees_with_the_limits_is_refused(fake):
    server = fake(lambda request, conn: [echo(request, {"hello": {"ok": True, "info": {}}, "limits": GOOD_LIMITS,
                                                        "read": {**GOOD_READ, "q": [0.0, 0.1]}}[request["op"]])])
    robot = RemoteRobot("127.0.0.1", server.port, timeout_s=2.0)
    assert robot.limits().lower.shape == (N,)
    with pytest.raises(RobotConnectionError, match="'q' has 2 entries, expected 3"):
        robot.read()


def test_a_dropout_may_carry_nan_pose_and_a_valid_reading_round_trips(fake):
    lost = {**GOOD_READ, "position": [math.nan] * 3, "quaternion": [math.nan] * 4, "valid": False}
    replies = iter([{"ok": True, "info": {"x": 1}}, GOOD_READ, lost])
    server = fake(lambda request, conn: [echo(request, next(replies))])
    robot = RemoteRobot("127.0.0.1", server.port, timeout_s=2.0)
    assert robot.info == {"x": 1}
    o = robot.read()
    assert o.valid is True and o.q.shape == (3,) and o.q.dtype == np.float64 and o.t == 1.0
    o = robot.read()
    assert o.valid is False and np.all(np.isnan(o.position))


# --- the server --------------------------------------------------------------------------------------------------


def _read_with_embedded_move(rid=1):
    """A whole 'read' frame whose body carries, as bytes, a whole 'move' frame; and where that frame starts."""
    inner = frame({"op": "move", "id": 99, "target": [0.05, 0.05, 0.05]})
    outer = frame({"op": "read", "id": rid, "pad": inner})
    return outer, outer.index(inner)


@pytest.mark.parametrize("stall_s", [0.0, 0.5])
def test_server_keeps_framing_across_a_stall_and_never_executes_an_embedded_frame(served, stall_s):
    """A client pausing 0.5 s inside a frame (past the server's 0.2 s poll) gets its whole frame read: the move
    frame inside the read's body is never executed."""
    server, arm = served()
    outer, cut = _read_with_embedded_move()
    with connect(server) as sock:
        sock.sendall(outer[:cut])
        time.sleep(stall_s)
        sock.sendall(outer[cut:])
        reply = recv_message(sock)
        assert arm.moves == [], "the move inside the read's body was executed"
        assert reply["ok"] is True and reply.get("id") == 1 and "q" in reply
        send_message(sock, {"op": "read", "id": 2})
        assert recv_message(sock)["id"] == 2  # still in step: the next frame is the next request
    assert arm.moves == [] and np.all(arm.q == 0)


@pytest.mark.slow
def test_server_drops_a_client_that_stalls_past_the_frame_deadline(served):
    server, arm = served(frame_timeout_s=0.3)
    outer, cut = _read_with_embedded_move()
    with connect(server) as sock:
        sock.sendall(outer[:cut])
        time.sleep(0.8)
        try:
            sock.sendall(outer[cut:])
            dropped = sock.recv(1) == b""
        except OSError:  # reset by the server
            dropped = True
        assert dropped
    assert arm.moves == []
    with connect(server) as sock:  # the serve loop lives on for the next client
        send_message(sock, {"op": "read", "id": 5})
        assert recv_message(sock)["id"] == 5
    assert arm.moves == []


@pytest.mark.parametrize(("target", "error"), [
    ([math.nan, 0.0, 0.0], r"target\[0\] is nan"),
    ([0.0, math.inf, 0.0], r"target\[1\] is inf"),
    ([0.0, 0.0, -math.inf], r"target\[2\] is -inf"),
    ([0.05, 1.5, 0.0], r"target\[1\] = 1.5 is outside the limits"),
    ([0.0, 0.0, 0.5], "actuator 2 would step 0.5 from 0, more than max_step 0.1"),
    ([0.05, 0.05], "target has 2 entries, the robot has 3 actuators"),
    ([0.0, 0.0, 0.0, 0.0], "target has 4 entries"),
    ([], "target has 0 entries"),
    (["0.0", 0.0, 0.0], "a list of numbers"),
    ([True, 0.0, 0.0], "a list of numbers"),
    ("x", "a list of numbers"),
    (None, "a list of numbers"),
])
def test_server_refuses_bad_moves_before_the_driver_sees_them(served, target, error):
    server, arm = served()
    with connect(server) as sock:
        send_message(sock, {"op": "move", "id": 3, "target": target})
        reply = recv_message(sock)
    assert reply["ok"] is False and reply["id"] == 3
    assert re.search(error, reply["error"]), reply["error"]
    assert arm.moves == [] and np.all(arm.q == 0)
    robot = RemoteRobot("127.0.0.1", server.port, timeout_s=2.0)  # the serve thread lives on
    robot.move(np.array([0.05, -0.05, 0.1]))
    assert len(arm.moves) == 1 and np.allclose(robot.read().q, [0.05, -0.05, 0.1])
    robot.close()


def test_remote_robot_gets_a_refused_move_as_robot_error_and_nothing_moves(served):
    server, arm = served()
    robot = RemoteRobot("127.0.0.1", server.port, timeout_s=2.0)
    assert np.all(robot.limits().max_step == MAX_STEP)
    with pytest.raises(RobotError, match="move refused: target") as info:
        robot.move(np.array([0.0, np.nan, 0.0]))
    assert not isinstance(info.value, RobotConnectionError)
    with pytest.raises(RobotError, match="more than max_step"):
        robot.move(np.array([0.0, 0.2, 0.0]))
    assert arm.moves == []
    robot.move(np.array([0.0, 0.1, 0.0]))  # exactly max_step: accepted
    robot.move(np.array([0.0, 0.2, 0.0]))  # max_step from the new position
    assert len(arm.moves) == 2
    robot.close()


def test_server_answers_a_driver_exception_with_an_error_reply(served):
    server, arm = served()
    arm.fail_read = ValueError("vendor SDK: bad packet")
    with connect(server) as sock:
        send_message(sock, {"op": "read", "id": 1})
        reply = recv_message(sock)
        assert reply == {"ok": False, "kind": "robot", "error": "ValueError: vendor SDK: bad packet", "id": 1}
        arm.fail_read = None
        send_message(sock, {"op": "read", "id": 2})
        assert recv_message(sock)["ok"] is True


def test_round_trip_against_the_server(served):
    server, arm = served(info={"name": "arm"})
    robot = RemoteRobot("127.0.0.1", server.port, timeout_s=2.0)
    assert robot.info == {"name": "arm"}
    lim = robot.limits()
    assert lim.lower.tolist() == [-1.0] * N
    robot.move(np.array([0.1, 0.0, -0.1]))
    o = robot.read()
    assert o.valid is True and o.q.tolist() == [0.1, 0.0, -0.1] and o.position.shape == (3,)
    robot.close()
    robot.close()
    with pytest.raises(RobotConnectionError, match="closed"):
        robot.read()
