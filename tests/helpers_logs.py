"""Synthetic logs the tests share: a 100 Hz stream of a UR5e making random moves (tests/test_streams.py, test_fit_api)
and ROS 1 / ROS 2 / MCAP bags of a linear arm written with rosbags' own writers (tests/test_bags.py, test_fit_api).

The bags come from one synthetic recording: a linear arm ``p = p0 + A q`` (constant orientation) whose three joints
(ROS names, published in another order than the model's) hold still and step by up to 0.03 rad every 0.5 s. Joint
states at 100 Hz with stamp jitter and a 0.2 s recording gap, a gripper publishing other joints on the same topic, one
repeated stamp; the tracker at 50 Hz, 3 ms off the joints' grid and starting before / ending after them. Receive
times carry random latencies (0-25 ms joints, 40-120 ms tracker), so the bag's order is not the stamps' and matching
by arrival would pair poses with the wrong joints.
"""

import functools

import jax
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from selfid_jax.systems.ur5e import UR5E_HOME, ur5e

EXAMPLE = "selfid_jax/robot/data/ur5e_example_log.csv"
Q_COLS = [f"q_{i}" for i in range(6)]
POS_COLS = ["p_x", "p_y", "p_z"]
QUAT_COLS = ["q_w", "q_x", "q_y", "q_z"]
RATE = 100.0  # Hz
PERIOD = 0.5  # s between commands
TAU = 0.02  # s, first-order servo lag
LATENCY = 0.01  # s, tracker one frame late
NOISE = 1e-4  # m
M_A = 0.03  # rad
MOVES = 40


@functools.cache
def _system():
    return ur5e(task_dim=3)


@functools.cache
def _poses():
    system = _system()
    return jax.jit(jax.vmap(system.pose))


def _J():
    """The UR5e's (3, 6) position Jacobian at its home pose (the stream's start)."""
    return np.asarray(_system().jacobian(np.asarray(UR5E_HOME, np.float64)))


def _stream(*, moves=MOVES, period=PERIOD, latency=LATENCY, jitter=0.0, seed=0, quaternion=False):
    """A UR5e logged at 100 Hz while it makes random moves ``uniform(-M_A, M_A)`` every ``period`` s.

    The joints follow each command through a first-order lag ``TAU`` (exact: the continuous response
    ``cmd + (q_k - cmd) exp(-(t - t_k) / TAU)``, evaluated at each row's time, so jittered stamps are exact too);
    the tracker logs at ``t`` the pose of ``t - latency``, with ``NOISE`` Gaussian position noise. Returns the table
    and the settled rows (the last row before each new command, and the last row)."""
    rng = np.random.default_rng(seed)
    q0 = np.asarray(UR5E_HOME, np.float64)
    cmd = q0 + np.concatenate([np.zeros((1, 6)), np.cumsum(rng.uniform(-M_A, M_A, (moves, 6)), axis=0)])
    # command k (1-based) at t_cmd[k - 1], half a frame after a row (which row is the last before it is clear)
    t_cmd = period * np.arange(1, moves + 1) + 0.5 / RATE
    start = [q0, q0]  # joint state when segment k starts (segment 0: since -inf; segment k at t_cmd[k - 1])
    for k in range(1, moves):
        start.append(cmd[k] + (start[k] - cmd[k]) * np.exp(-period / TAU))
    start = np.asarray(start)
    t_seg = np.concatenate([[-np.inf], t_cmd])

    def q_at(t):
        k = np.searchsorted(t_cmd, t, side="right")
        since = np.where(k == 0, 0.0, t - t_seg[k])
        return cmd[k] + (start[k] - cmd[k]) * np.exp(-since / TAU)[:, None]

    rows = int(round((t_cmd[-1] + period) * RATE))
    t = np.arange(rows) / RATE
    if jitter:
        t = t + rng.uniform(-jitter, jitter, rows)
    q = q_at(t)
    p, R = _poses()(q_at(t - latency))
    p = np.asarray(p) + NOISE * rng.normal(size=(rows, 3))
    table = {"t": t, **{c: q[:, i] for i, c in enumerate(Q_COLS)}, **{c: p[:, i] for i, c in enumerate(POS_COLS)}}
    if quaternion:
        xyzw = Rotation.from_matrix(np.asarray(R)).as_quat()
        wxyz = xyzw[:, [3, 0, 1, 2]] * rng.choice([-1.0, 1.0], size=(rows, 1))  # q and -q: one rotation
        table.update({c: wxyz[:, i] for i, c in enumerate(QUAT_COLS)})
    settled = np.append(np.searchsorted(t, t_cmd, side="left") - 1, rows - 1)
    return table, settled


NS = 1_000_000_000
T0 = 1_700_000_000 * NS + 123_456_789  # an epoch stamp: float64 seconds would lose the sub-microsecond part
ARM = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint")  # the model's order: q = (pan, lift, elbow)
PUBLISHED = ("elbow_joint", "shoulder_lift_joint", "shoulder_pan_joint")  # the driver's order, first half
A = np.array([[0.30, -0.10, 0.05], [0.08, 0.25, -0.12], [-0.04, 0.15, 0.20]])  # m/rad, cond(A) ~ 2
P0 = np.array([0.40, 0.10, 0.30])
QUAT = np.array([0.9, 0.1, -0.2, 0.3]) / np.linalg.norm([0.9, 0.1, -0.2, 0.3])  # (w, x, y, z), constant
GAP = range(612, 632)  # joint samples lost: a 0.2 s recording gap
DUPLICATE = 300  # this joint sample is recorded twice, the second copy garbage
TRACKER_TYPE = {"pose": "geometry_msgs/msg/PoseStamped", "transform": "geometry_msgs/msg/TransformStamped",
                "tf": "tf2_msgs/msg/TFMessage"}


def _recording(seed=0):
    """The synthetic recording: joint, gripper and tracker messages as (stamp ns, receive ns, payload)."""
    rng = np.random.default_rng(seed)
    k = np.array([i for i in range(1000) if i not in GAP])
    tj = T0 + k * 10_000_000 + rng.integers(-500_000, 500_000, k.size)  # 100 Hz with +-0.5 ms jitter
    steps = rng.uniform(-0.03, 0.03, size=(19, 3))
    step_at = T0 + np.arange(1, 20) * 500_000_000 + 5_000_000  # between two joint samples
    q0 = np.array([0.1, -1.2, 1.5])
    qj = q0 + np.array([steps[step_at < t].sum(axis=0) for t in tj])  # (K, 3) in the model's order
    tt = T0 - 97_000_000 + np.arange(516) * 20_000_000  # 50 Hz, -97 ms .. 10.203 s: past both ends
    rel = lambda s: (s - T0).astype(np.float64)
    qt = np.stack([np.interp(rel(tt), rel(tj), qj[:, i]) for i in range(3)], axis=1)  # joints ramp between samples
    pt = P0 + qt @ A.T
    joints = []
    for i, (s, q) in enumerate(zip(tj, qj)):
        names = PUBLISHED if i < len(tj) // 2 else ARM  # the driver changes its order half-way
        pos = [q[ARM.index(n)] for n in names]
        joints.append((int(s), int(s + rng.integers(0, 25_000_000)), names, pos))
        if k[i] == DUPLICATE:
            joints.append((int(s), joints[-1][1] + 1_000_000, names, [9.0, 9.0, 9.0]))
    gripper = [(int(T0 + 55_000_000 + i * 100_000_000), int(T0 + 56_000_000 + i * 100_000_000), ("finger_joint",),
                [0.04]) for i in range(100)]
    tracker = [(int(s), int(s + rng.integers(40_000_000, 120_000_000)), p) for s, p in zip(tt, pt)]
    return dict(tj=tj, qj=qj, tt=tt, joints=joints, gripper=gripper, tracker=tracker)


REC = _recording()


class _Messages:
    """Message constructors of one typestore (ROS 1 headers carry a seq)."""

    def __init__(self, store):
        self.store, self.ros1 = store, store is STORES["ros1"]
        self.t = store.types

    def header(self, stamp, frame=""):
        extra = {"seq": 0} if self.ros1 else {}
        time = self.t["builtin_interfaces/msg/Time"](sec=stamp // NS, nanosec=stamp % NS)
        return self.t["std_msgs/msg/Header"](stamp=time, frame_id=frame, **extra)

    def joint_state(self, stamp, names, pos):
        empty = np.zeros(0)
        return self.t["sensor_msgs/msg/JointState"](header=self.header(stamp), name=list(names),
                                                     position=np.asarray(pos, np.float64), velocity=empty, effort=empty)

    def transform(self, stamp, p, child, frame="world"):
        v = self.t["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2])
        r = self.t["geometry_msgs/msg/Quaternion"](w=QUAT[0], x=QUAT[1], y=QUAT[2], z=QUAT[3])
        return self.t["geometry_msgs/msg/TransformStamped"](header=self.header(stamp, frame), child_frame_id=child,
                                                             transform=self.t["geometry_msgs/msg/Transform"](
                                                                 translation=v, rotation=r))

    def tracker(self, kind, stamp, p):
        if kind == "pose":
            point = self.t["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2])
            r = self.t["geometry_msgs/msg/Quaternion"](w=QUAT[0], x=QUAT[1], y=QUAT[2], z=QUAT[3])
            return self.t["geometry_msgs/msg/PoseStamped"](header=self.header(stamp, "world"),
                                                           pose=self.t["geometry_msgs/msg/Pose"](position=point,
                                                                                                 orientation=r))
        if kind == "transform":
            return self.transform(stamp, p, "tool_marker")
        other = self.transform(stamp, -np.asarray(p), "table_marker")  # another body in the same message
        return self.t["tf2_msgs/msg/TFMessage"](transforms=[other, self.transform(stamp, p, "tool_marker")])


STORES = {"ros1": get_typestore(Stores.ROS1_NOETIC), "ros2": get_typestore(Stores.ROS2_HUMBLE)}


def write_bag(path, fmt, *, tracker="pose", rec=REC, extra=()):
    """Write ``rec`` as a bag: ``fmt`` "ros1", "sqlite3" or "mcap"; ``extra``: (topic, type) connections left empty.

    Messages go in in receive-time order, the receive time as the bag's timestamp."""
    store = STORES["ros1" if fmt == "ros1" else "ros2"]
    make = _Messages(store)
    if fmt == "ros1":
        writer = Writer1(path)
        serialize = store.serialize_ros1
    else:
        plugin = StoragePlugin.SQLITE3 if fmt == "sqlite3" else StoragePlugin.MCAP
        writer = Writer2(path, version=Writer2.VERSION_LATEST, storage_plugin=plugin)
        serialize = store.serialize_cdr
    ttype = TRACKER_TYPE[tracker]
    items = [(r, "/joint_states", make.joint_state(s, n, q)) for s, r, n, q in [*rec["joints"], *rec["gripper"]]]
    items += [(r, "/tracker", make.tracker(tracker, s, p)) for s, r, p in rec["tracker"]]
    items.sort(key=lambda x: x[0])
    with writer:
        conn = {"/joint_states": writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store),
                "/tracker": writer.add_connection("/tracker", ttype, typestore=store)}
        for topic, msgtype in extra:
            writer.add_connection(topic, msgtype, typestore=store)
        for recv, topic, msg in items:
            writer.write(conn[topic], recv, serialize(msg, msg.__msgtype__))
    return path


def run_fit_command(tmp_path, log, *flags):
    """``selfid-jax fit LOG FLAGS`` in-process: ``(exit code, summary.json, estimate)`` (the estimate so far if it
    wrote no inverse_jacobian.npz: not converged, or --strict with a warning); tests/test_fit_api.py and
    tests/test_camera_fit.py set it beside ``sj.fit``."""
    import json

    from selfid_jax.cli import main

    out = tmp_path / "run"
    code = main(["fit", str(log), "--out", str(out), *flags])
    info = json.loads((out / "summary.json").read_text())
    est = np.load(out / "inverse_jacobian.npz")["inverse_jacobian"] if "estimate_so_far" not in info else \
        np.asarray(info["estimate_so_far"])
    return code, info, est
