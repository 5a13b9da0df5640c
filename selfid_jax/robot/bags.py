"""ROS bags -> the raw time-series table of :mod:`selfid_jax.robot.log` (``t``, ``q_*``, ``p_*``, quaternion).

Reads a ROS 1 ``.bag``, a ROS 2 bag folder (``metadata.yaml`` with sqlite3
``.db3`` or ``.mcap`` storage) or a single ROS 2 ``.mcap`` / ``.db3`` file
through ``rosbags`` (``pip install "selfid-jax[ros]"``). Two topics are used:

* the joint states (``sensor_msgs/JointState``): the actuator positions
  ``q_0 .. q_{n-1}`` are the ``position`` entries of the named joints, in the
  order asked for;
* the tracker: ``geometry_msgs/PoseStamped``, ``geometry_msgs/TransformStamped``
  or ``tf2_msgs/TFMessage`` (``/tf``, of which the transforms whose
  ``child_frame_id`` is ``child_frame`` are used). The pose is the message's
  own (the child frame in ``header.frame_id``), not composed through a TF
  tree: on ``/tf`` name a frame the tracker publishes relative to the world
  (a motion-capture body), not a link of the robot's own chain.

Both streams are matched by their **header stamps** (the time the data was
measured), never by the bag's receive times. One row per tracker pose, in
stamp order: ``t`` its stamp (s, float64; nothing subtracted, so at ~1.7e9 s a
row's time is exact to ~0.2 us), ``p_x, p_y, p_z`` and ``q_w, q_x, q_y, q_z``
its pose, and ``q_i`` the joint positions linearly interpolated at that stamp
between the two joint messages that bracket it (the interpolation runs on
integer nanoseconds, exact whatever the epoch). A pose outside the joint
messages' span, or between two joint messages more than ``max_skew`` apart
(a recording gap), is dropped and counted in :class:`BagInfo`. Rows are
not screened further here: non-finite values, zero quaternions, repeated
stamps and time gaps are :func:`selfid_jax.robot.log.samples_from_table`'s.

The pieces are public for the camera tracker (:mod:`selfid_jax.robot.camera.sources`),
which reads a bag's image topic instead of a pose topic and matches its tag
poses to the joints the same way: :func:`open_bag`, :func:`topic_type`,
:func:`messages`, :func:`stamp_ns`, :func:`read_joint_states` and
:func:`match_to_joints` (the one matcher, also used for a video's frame times
against a joint log's ``t``).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from selfid_jax.robot.log import LogError

__all__ = ["BagInfo", "DEFAULT_SKEW_FACTOR", "JOINT_TYPE", "STAMP_STEP_S", "TRACKER_TYPES", "JointStates", "Matched",
           "clock_steps", "match_to_joints", "messages", "open_bag", "read_bag", "read_joint_states",
           "received_messages", "screen_joint_clock", "stamp_ns", "stepped_stamp", "topic_type"]

#: The joint-state message type (rosbags names ROS 1 types the ROS 2 way too).
JOINT_TYPE = "sensor_msgs/msg/JointState"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
#: Tracker message types read.
TRACKER_TYPES = (POSE_STAMPED, TRANSFORM_STAMPED, TF_MESSAGE)
#: ``max_skew=None``: bracketing joint messages at most this many median joint periods apart.
DEFAULT_SKEW_FACTOR = 3.0
STAMP_STEP_S = 0.5
"""A message whose header stamp is off the bag's receive time by more than this many seconds beyond its topic's
median offset is dropped and counted (:func:`clock_steps`): its publisher's clock stepped back or jumped (an NTP
correction, a restarted driver) and its stamp no longer says when it was measured. A transport delays a message by
milliseconds to ~0.1 s (the tests' bags: 0-25 ms joints, 40-120 ms tracker), a clock that drifts 50 ppm moves 0.2 s
an hour; a step moves every later stamp by seconds. Sorting such stamps would pair poses with the wrong joints."""

_INSTALL = 'reading ROS bags needs the rosbags package: pip install "selfid-jax[ros]"'
_NS = 1_000_000_000


class BagInfo(NamedTuple):
    """What :func:`read_bag` read, matched and dropped."""

    source: str  # the bag (file or folder)
    joint_names: tuple[str, ...]  # joint of each column q_0, q_1, ..
    tracker_type: str  # e.g. "geometry_msgs/msg/PoseStamped"
    frame: str  # the poses' frame (header.frame_id; "" if unset)
    child_frame: str | None  # the tracked frame (TransformStamped / TFMessage), None for PoseStamped
    joint_messages: int  # joint messages naming the joints (duplicates included)
    duplicate_joint_stamps: int  # of which dropped for repeating an earlier message's stamp
    other_joint_messages: int  # joint messages naming none of the joints (another publisher), skipped
    tracker_messages: int  # tracker poses read (on /tf: transforms of child_frame)
    rows: int  # rows of the table: tracker poses matched to joint positions
    outside_span: int  # poses dropped: stamped before the first or after the last joint message
    skewed: int  # poses dropped: between joint messages more than max_skew apart
    max_skew: float  # bracket limit applied (s)
    joint_period: float  # median period of the joint messages' stamps (s)
    tracker_period: float  # median period of the poses' stamps (s); NaN with fewer than 2 distinct stamps
    clock_steps: int = 0  # poses dropped: stamp off the bag's receive time (a clock that stepped; clock_steps)
    joint_clock_steps: int = 0  # joint messages dropped for the same
    clock_step_first: str = ""  # the first one dropped (topic and stamp), "" if none

    def lines(self) -> list[str]:
        """A few lines for a terminal: the streams, their rates and what was dropped."""
        hz = lambda period: f"{1.0 / period:.4g} Hz" if period > 0 else "? Hz"
        what = f"{self.child_frame} in {self.frame or '(no frame)'}" if self.child_frame else self.frame or "(no frame)"
        out = [f"{self.source}: {self.rows} rows",
               f"  joints: {self.joint_messages} messages at {hz(self.joint_period)} ({', '.join(self.joint_names)})",
               f"  tracker: {self.tracker_messages} {self.tracker_type} poses at {hz(self.tracker_period)} ({what})"]
        dropped = [(self.outside_span, "outside the joint messages' span"),
                   (self.skewed, f"between joint messages more than {self.max_skew:.4g} s apart"),
                   (self.duplicate_joint_stamps, "joint messages repeating a stamp"),
                   (self.clock_steps, f"poses whose stamps step off the bag's clock by more than {STAMP_STEP_S:g} s "
                    f"(the tracker's clock stepped back or jumped; first: {self.clock_step_first})"),
                   (self.joint_clock_steps, f"joint messages whose stamps step off the bag's clock by more than "
                    f"{STAMP_STEP_S:g} s (the joints' clock stepped back or jumped; first: {self.clock_step_first})"),
                   (self.other_joint_messages, "joint messages naming none of the joints")]
        out += [f"  dropped: {k} {why}" for k, why in dropped if k]
        return out


class JointStates(NamedTuple):
    """The joint messages of a topic that name the joints (:func:`read_joint_states`), in bag order."""

    names: tuple[str, ...]  # joint of each column of positions
    stamps: np.ndarray  # (K,) int64 header stamps, ns
    positions: np.ndarray  # (K, n) float64 joint positions (rad, m)
    other: int  # messages naming none of the joints (another publisher), skipped
    received: np.ndarray | None = None  # (K,) int64 the bag's receive times, ns (None: not from a bag)


class Matched(NamedTuple):
    """What :func:`match_to_joints` matched and dropped."""

    rows: int  # poses matched to joint positions (rows of the table)
    outside_span: int  # poses dropped: stamped before the first or after the last joint message
    skewed: int  # poses dropped: between joint messages more than max_skew apart
    duplicate_joint_stamps: int  # joint messages dropped for repeating an earlier message's stamp
    max_skew: float  # bracket limit applied (s)
    joint_period: float  # median period of the joint stamps (s)
    tracker_period: float  # median period of the poses' stamps (s); NaN with fewer than 2 distinct stamps


def stamp_ns(msg: Any) -> int:
    """``msg.header.stamp`` in integer nanoseconds."""
    stamp = msg.header.stamp
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def _seconds(ns: int) -> str:
    return f"{ns // _NS}.{ns % _NS:09d} s"


def _frame(name: str) -> str:
    """A frame id without the leading ``/`` that ROS 1's tf allowed."""
    return name.lstrip("/")


def _median_period(stamps: np.ndarray) -> float:
    """Median positive step (s) of sorted integer-nanosecond ``stamps``; NaN with fewer than 2 distinct."""
    steps = np.diff(stamps)
    steps = steps[steps > 0]
    return float(np.median(steps)) / _NS if steps.size else float("nan")


def read_bag(
    path: str | Path,
    *,
    joints: str,
    tracker: str,
    joint_names: Sequence[str] | str | None = None,
    child_frame: str | None = None,
    max_skew: float | None = None,
) -> tuple[dict[str, np.ndarray], BagInfo]:
    """The raw time-series table of a ROS bag (one row per tracker pose) and a :class:`BagInfo`.

    Args:
      path: a ROS 1 ``.bag``, a ROS 2 bag folder (sqlite3 or mcap storage), or
        a ROS 2 ``.mcap`` or ``.db3`` file.
      joints: the ``sensor_msgs/JointState`` topic, e.g. ``"/joint_states"``.
      tracker: the pose topic: ``geometry_msgs/PoseStamped``,
        ``geometry_msgs/TransformStamped`` or ``tf2_msgs/TFMessage``.
      joint_names: the joints, in column order (a sequence or a comma-separated
        string); default: those of the first joint message, in its order.
        Messages naming none of them (another publisher on the topic) are skipped.
      child_frame: the tracked frame (``child_frame_id``); required for a
        ``TFMessage`` topic, and for a ``TransformStamped`` one carrying several.
      max_skew: drop a pose whose bracketing joint messages are more than this
        many seconds apart; default :data:`DEFAULT_SKEW_FACTOR` median joint periods.

    Returns:
      ``(table, info)``: ``table`` maps ``t`` (T,) s, ``q_0 .. q_{n-1}`` (T,)
      joint units (rad, m), ``p_x, p_y, p_z`` (T,) m and ``q_w, q_x, q_y, q_z``
      (T,) to float64 arrays, rows in stamp order; feed it to
      :func:`selfid_jax.robot.log.samples_from_table`.

    Raises:
      LogError: rosbags missing, an unreadable bag, a missing, empty or
        wrongly typed topic, a joint missing from a message, an unknown child
        frame, or no pose left after matching (one line naming the file and topic).
      ValueError: ``max_skew`` not a positive number.
    """
    source = str(path)
    if max_skew is not None and not (np.isfinite(max_skew) and max_skew > 0):
        raise ValueError(f"max_skew must be a positive number of seconds, got {max_skew!r}")
    joint_names = _joint_names_list(joint_names)
    reader = open_bag(path)
    try:
        topics = dict(reader.topics)
        topic_type(source, topics, joints, "joint states", (JOINT_TYPE,))
        tracker_type = topic_type(source, topics, tracker, "tracker", TRACKER_TYPES)
        if tracker_type == POSE_STAMPED and child_frame is not None:
            raise LogError(f"{source}: topic {tracker} is a {POSE_STAMPED}, which has no child frame; "
                           f"drop child_frame={child_frame!r}")
        states = read_joint_states(reader, source, joints, joint_names)
        t_stamps, poses, frame, child, received = _poses(
            source, tracker, tracker_type, received_messages(reader, topics[tracker].connections, source, tracker),
            child_frame)
    finally:
        reader.close()
    columns = ("p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z")
    first: list[str] = []
    states, joint_steps = screen_joint_clock(states, joints, first)
    ok = clock_steps(t_stamps, received)
    pose_steps = int((~ok).sum())
    if pose_steps:
        first.append(stepped_stamp(t_stamps, ok, tracker))
        t_stamps, poses = t_stamps[ok], poses[ok]
    table, m = match_to_joints(source, joints, tracker, states, t_stamps,
                               {c: poses[:, k] for k, c in enumerate(columns)}, max_skew=max_skew)
    info = BagInfo(source=source, joint_names=states.names, tracker_type=tracker_type, frame=frame, child_frame=child,
                   joint_messages=int(states.stamps.size), duplicate_joint_stamps=m.duplicate_joint_stamps,
                   other_joint_messages=states.other, tracker_messages=int(t_stamps.size), rows=m.rows,
                   outside_span=m.outside_span, skewed=m.skewed, max_skew=m.max_skew, joint_period=m.joint_period,
                   tracker_period=m.tracker_period, clock_steps=pose_steps, joint_clock_steps=joint_steps,
                   clock_step_first="; ".join(first))
    return table, info


def screen_joint_clock(states: JointStates, topic: str, first: list[str]) -> tuple[JointStates, int]:
    """``states`` without the messages whose stamps step off the bag's clock (:func:`clock_steps`), and how many
    were dropped; the first such stamp is appended to ``first`` as ``"TOPIC stamp S"``."""
    if states.received is None:
        return states, 0
    ok = clock_steps(states.stamps, states.received)
    dropped = int((~ok).sum())
    if dropped:
        first.append(f"{topic} stamp {_seconds(int(states.stamps[np.argmin(ok)]))}")
        states = states._replace(stamps=states.stamps[ok], positions=states.positions[ok],
                                 received=states.received[ok])
    return states, dropped


def stepped_stamp(stamps: np.ndarray, ok: np.ndarray, topic: str) -> str:
    """``"TOPIC stamp S"`` of the first stamp :func:`clock_steps` flagged (``ok`` False)."""
    return f"{topic} stamp {_seconds(int(stamps[np.argmin(ok)]))}"


def clock_steps(stamps: np.ndarray, received: np.ndarray) -> np.ndarray:
    """Mask ``(K,)`` of the messages whose header ``stamps`` (int ns) keep pace with the bag's ``received`` times
    (int ns): the offset ``stamp - received`` within :data:`STAMP_STEP_S` of its median. False where the
    publisher's clock stepped back or jumped. All True where the receive times cannot tell (a bag written with
    one receive time for all, or receive times spanning less than half the stamps': a converted log)."""
    stamps, received = np.asarray(stamps, np.int64), np.asarray(received, np.int64)
    keep = np.ones(stamps.size, bool)
    if stamps.size < 3 or np.ptp(received) < 0.5 * np.ptp(stamps):
        return keep
    offset = stamps - received
    median = int(np.median(offset))
    return np.abs(offset - median) <= STAMP_STEP_S * _NS


def _tap(items: Iterator[tuple[int, Any]], sink: list[int]) -> Iterator[Any]:
    """The messages of ``(received, msg)`` pairs, their receive times appended to ``sink``."""
    for received, msg in items:
        sink.append(received)
        yield msg


def open_bag(path: str | Path) -> Any:
    """An opened ``rosbags.highlevel.AnyReader`` of a ROS 1 ``.bag``, a ROS 2 bag folder or a ``.mcap``/``.db3``
    file (close it); :class:`LogError` naming the file if it is none of these, cannot be read or rosbags is missing."""
    source = str(path)
    path = Path(path)
    if not path.exists():
        raise LogError(f"{source}: no such file or folder")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise LogError(f"{source}: a folder without metadata.yaml is not a ROS 2 bag")
    if path.is_file() and path.suffix not in (".bag", ".mcap", ".db3"):  # rosbags goes by these exact suffixes
        raise LogError(f"{source}: not a ROS bag: expected a ROS 1 .bag, a ROS 2 bag folder or a .mcap/.db3 file, "
                       f"got {path.suffix or '(no suffix)'!r}")
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise LogError(f"{source}: {_INSTALL}") from None

    # A bag without embedded definitions (older ROS 2 sqlite3 bags) is read with these types; the message types
    # used are the same in every ROS distribution.
    store = get_typestore(Stores.ROS1_NOETIC if path.suffix == ".bag" else Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except Exception as err:  # noqa: BLE001 - rosbags raises many types for a corrupt or foreign file
        raise LogError(f"{source}: cannot read as a ROS bag: {_detail(err)}") from None
    return reader


def _detail(err: BaseException) -> str:
    return " ".join(str(err).split())[:200] or type(err).__name__


def topic_type(source: str, topics: dict[str, Any], topic: str, role: str, accepted: Sequence[str]) -> str:
    """The message type of ``topic``; :class:`LogError` if it is missing or of a type not ``accepted``."""
    if topic not in topics:
        have = ", ".join(f"{name} ({info.msgtype or 'several types'})" for name, info in sorted(topics.items()))
        raise LogError(f"{source}: no topic {topic} (the {role}); the bag has: {have or 'no topics'}")
    info = topics[topic]
    types = sorted({c.msgtype for c in info.connections})
    want = accepted[0] if len(accepted) == 1 else "one of " + ", ".join(accepted)
    if len(types) != 1 or types[0] not in accepted:
        raise LogError(f"{source}: topic {topic} is {' and '.join(types)}; the {role} must be {want}")
    return types[0]


def messages(reader: Any, connections: Sequence[Any], source: str, topic: str) -> Iterator[Any]:
    """The deserialised messages of ``connections`` in bag order; :class:`LogError` where rosbags fails."""
    for _, msg in received_messages(reader, connections, source, topic):
        yield msg


def received_messages(reader: Any, connections: Sequence[Any], source: str, topic: str
                      ) -> Iterator[tuple[int, Any]]:
    """``(receive time ns, message)`` of ``connections`` in bag order (:func:`messages` with the bag's times)."""
    items = reader.messages(connections=connections)
    while True:
        try:
            connection, received, raw = next(items)
            msg = reader.deserialize(raw, connection.msgtype)
        except StopIteration:
            return
        except Exception as err:  # noqa: BLE001 - rosbags raises many types for a corrupt message or chunk
            raise LogError(f"{source}: topic {topic}: cannot read a message: {_detail(err)}") from None
        yield int(received), msg


def read_joint_states(reader: Any, source: str, topic: str, joint_names: Sequence[str] | str | None = None
                      ) -> JointStates:
    """The ``sensor_msgs/JointState`` messages of ``topic`` in an open bag (:func:`open_bag`) that name the joints
    (a sequence or a comma-separated string; default: those of the first message, in its order).

    Raises :class:`LogError` naming the file and topic (see :func:`read_bag`),
    ValueError for ``joint_names`` empty or naming a joint twice."""
    names_asked = _joint_names_list(joint_names)
    topics = dict(reader.topics)
    topic_type(source, topics, topic, "joint states", (JOINT_TYPE,))
    received: list[int] = []
    stream = _tap(received_messages(reader, topics[topic].connections, source, topic), received)
    names, stamps, positions, other, kept = _joint_states(source, topic, stream, names_asked)
    return JointStates(names, stamps, positions, other, np.asarray(received, np.int64)[kept])


def _joint_names_list(joint_names: Sequence[str] | str | None) -> list[str] | None:
    """``joint_names`` as a list (a comma-separated string split); ValueError if empty or naming a joint twice."""
    if isinstance(joint_names, str):
        joint_names = [s.strip() for s in joint_names.split(",") if s.strip()]
    if joint_names is None:
        return None
    names = list(joint_names)
    if not names:
        raise ValueError("joint_names is empty: name at least one joint")
    if len(set(names)) != len(names):
        twice = next(j for j in names if names.count(j) > 1)
        raise ValueError(f"joint_names names {twice} twice")
    return names


def _joint_states(source: str, topic: str, messages: Iterator[Any], joint_names: list[str] | None,
                  ) -> tuple[tuple[str, ...], np.ndarray, np.ndarray, int, list[int]]:
    """``(names, stamps (K,) int ns, positions (K, n), skipped, kept)`` of the joint messages, in bag order
    (``kept``: the 0-based index among the messages of each row)."""
    columns: dict[tuple[str, ...], np.ndarray | None] = {}  # a message's name list -> its entries of the joints
    stamps: list[int] = []
    rows: list[np.ndarray] = []
    skipped = 0
    kept: list[int] = []
    names_seen: set[str] = set()
    k = 0
    for k, msg in enumerate(messages, start=1):
        names = tuple(str(s) for s in msg.name)
        position = np.asarray(msg.position, np.float64)
        if position.shape != (len(names),):
            raise LogError(f"{source}: topic {topic}: message {k} (stamp {_seconds(stamp_ns(msg))}) has "
                           f"{len(names)} names but {position.size} positions")
        if joint_names is None:
            if not names:
                raise LogError(f"{source}: topic {topic}: message {k} names no joints; give joint_names")
            joint_names = list(names)
        if names not in columns:
            index = {name: i for i, name in enumerate(names)}
            have = [j in index for j in joint_names]
            if all(have):
                columns[names] = np.array([index[j] for j in joint_names], np.intp)
            elif any(have):
                missing = joint_names[have.index(False)]
                raise LogError(f"{source}: topic {topic}: joint {missing} is not in message {k} "
                               f"(stamp {_seconds(stamp_ns(msg))}), whose joints are {', '.join(names) or '(none)'}")
            else:
                columns[names] = None
        idx = columns[names]
        names_seen.update(names)
        if idx is None:
            skipped += 1
            continue
        kept.append(k - 1)
        stamps.append(stamp_ns(msg))
        rows.append(position[idx])
    if k == 0:
        raise LogError(f"{source}: topic {topic} (the joint states) has no messages")
    assert joint_names is not None  # the first message sets them
    if not rows:
        raise LogError(f"{source}: topic {topic}: no message names the joints {', '.join(joint_names)}; "
                       f"the messages name {', '.join(sorted(names_seen)) or '(none)'}")
    return tuple(joint_names), np.array(stamps, np.int64), np.stack(rows), skipped, kept


def _poses(source: str, topic: str, msgtype: str, messages: Iterator[tuple[int, Any]], child_frame: str | None,
           ) -> tuple[np.ndarray, np.ndarray, str, str | None, np.ndarray]:
    """``(stamps (T,) int ns, poses (T, 7) [p_x, p_y, p_z, q_w, q_x, q_y, q_z], frame, child, received (T,) int ns)``
    in bag order, of ``(receive time, message)`` pairs (a TFMessage's poses take its receive time)."""
    want = None if child_frame is None else _frame(child_frame)
    stamps: list[int] = []
    poses: list[tuple[float, ...]] = []
    frames: set[str] = set()
    children: dict[str, int] = {}  # every child frame seen -> how many transforms
    received: list[int] = []  # the bag's receive time of each pose (its message's)

    def add(now: int, stamp: int, frame: str, p: Any, q: Any) -> None:
        received.append(now)
        stamps.append(stamp)
        poses.append((p.x, p.y, p.z, q.w, q.x, q.y, q.z))
        frames.add(_frame(frame))

    count = 0
    for now, msg in messages:
        count += 1
        if msgtype == POSE_STAMPED:
            add(now, stamp_ns(msg), msg.header.frame_id, msg.pose.position, msg.pose.orientation)
            continue
        for tf in msg.transforms if msgtype == TF_MESSAGE else [msg]:
            name = _frame(tf.child_frame_id)
            children[name] = children.get(name, 0) + 1
            if want is None or name == want:
                add(now, stamp_ns(tf), tf.header.frame_id, tf.transform.translation, tf.transform.rotation)
    if count == 0:
        raise LogError(f"{source}: topic {topic} (the tracker) has no messages")
    child: str | None = None
    if msgtype != POSE_STAMPED:
        seen = ", ".join(f"{c} ({k} transforms)" for c, k in sorted(children.items())) or "none"
        if want is None and (msgtype == TF_MESSAGE or len(children) > 1):
            raise LogError(f"{source}: topic {topic} is a {msgtype}: name the tracked frame with child_frame; "
                           f"its child frames are: {seen}")
        if want is not None and want not in children:
            raise LogError(f"{source}: topic {topic} has no transform of child frame {want}; its child frames "
                           f"are: {seen}")
        child = want if want is not None else next(iter(children))
    if len(frames) > 1:
        raise LogError(f"{source}: topic {topic}: the poses{f' of {child}' if child else ''} are in several frames "
                       f"({', '.join(sorted(frames))}); a log needs one")
    return (np.array(stamps, np.int64), np.array(poses, np.float64).reshape(-1, 7), frames.pop(), child,
            np.array(received, np.int64))


def _distinct_stamps(source: str, topic: str, stamps: np.ndarray, what: str) -> None:
    """:class:`LogError` if ``stamps`` (int ns) hold fewer than two distinct values (an unset header.stamp)."""
    if np.unique(stamps).size < 2:
        unset = " (header.stamp is 0: the publisher does not stamp its messages)" if not stamps.any() else ""
        raise LogError(f"{source}: topic {topic}: the {stamps.size} {what} all have the stamp "
                       f"{_seconds(int(stamps[0]))}{unset}; matching by stamp needs at least two distinct ones")


def match_to_joints(source: str, joints: str, tracker: str, states: JointStates, stamps: np.ndarray,
                    columns: dict[str, np.ndarray], *, max_skew: float | None = None, what: str = "pose",
                    ) -> tuple[dict[str, np.ndarray], Matched]:
    """Each pose with the joint positions interpolated at its stamp (integer-nanosecond weights): the table.

    ``states``: the joint stamps and positions (:class:`JointStates`, any
    order; a repeated stamp keeps its first message); ``stamps (T,)`` int64
    ns and ``columns`` (name -> ``(T,)``) the poses, any order. ``joints`` and
    ``tracker`` name the two streams in messages (topics, or files). Returns
    ``t`` (s), ``q_0 ..`` and the ``columns``, rows in stamp order, and a
    :class:`Matched`; a pose outside the joint stamps' span or between joint
    stamps more than ``max_skew`` s apart (default :data:`DEFAULT_SKEW_FACTOR`
    median joint periods) is dropped and counted.
    """
    j_stamps, positions = states.stamps, states.positions
    _distinct_stamps(source, joints, j_stamps, "joint messages")
    order = np.argsort(j_stamps, kind="stable")
    j_sorted = j_stamps[order]
    first = np.concatenate([[True], np.diff(j_sorted) > 0])  # the first received of each stamp is kept
    tj, qj = j_sorted[first], positions[order][first]
    duplicates = int((~first).sum())
    joint_period = _median_period(tj)
    skew = DEFAULT_SKEW_FACTOR * joint_period if max_skew is None else float(max_skew)

    t_stamps = np.asarray(stamps, np.int64)
    if not t_stamps.any():
        raise LogError(f"{source}: topic {tracker}: every {what} has the stamp 0 (header.stamp is unset: the "
                       "publisher does not stamp its messages); matching by stamp needs the measurement times")
    order = np.argsort(t_stamps, kind="stable")
    tt = t_stamps[order]
    tracker_period = _median_period(tt)
    K = tj.size
    i = np.searchsorted(tj, tt, side="right")  # tj[i - 1] <= tt < tj[i]
    lo, hi = np.clip(i - 1, 0, K - 1), np.clip(i, 0, K - 1)
    outside = (tt < tj[0]) | (tt > tj[-1])
    exact = ~outside & (tj[lo] == tt)  # at a joint message's stamp: no bracket needed
    span = tj[hi] - tj[lo]
    skewed = ~outside & ~exact & (span > skew * _NS)
    keep = ~outside & ~skewed
    if not keep.any():
        raise LogError(_no_rows(source, joints, tracker, tj, tt, int(outside.sum()), int(skewed.sum()), skew))
    w = np.where(exact, 0.0, (tt - tj[lo]) / np.where(span > 0, span, 1))
    q = (qj[lo] + w[:, None] * (qj[hi] - qj[lo]))[keep]

    table = {"t": tt[keep] / _NS}
    table.update({f"q_{k}": q[:, k].copy() for k in range(q.shape[1])})
    table.update({c: np.asarray(v, np.float64)[order][keep] for c, v in columns.items()})
    return table, Matched(rows=int(keep.sum()), outside_span=int(outside.sum()), skewed=int(skewed.sum()),
                          duplicate_joint_stamps=duplicates, max_skew=skew, joint_period=joint_period,
                          tracker_period=tracker_period)


def _no_rows(source: str, joints: str, tracker: str, tj: np.ndarray, tt: np.ndarray, outside: int, skewed: int,
             skew: float) -> str:
    """The one-line reason no pose could be matched."""
    span = lambda s: f"{_seconds(int(s.min()))} .. {_seconds(int(s.max()))}"
    head = f"{source}: no pose on {tracker} could be matched to the joint positions on {joints}"
    if outside == tt.size:
        return (f"{head}: the poses' stamps ({span(tt)}) lie outside the joint messages' ({span(tj)}); "
                "are the two stamped by different clocks?")
    return (f"{head}: {outside} outside the joint messages' span, {skewed} between joint messages more than "
            f"{skew:.4g} s apart (max_skew)")

