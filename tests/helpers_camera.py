"""The simulated camera scene the camera tests share (tests/test_camera.py, tests/test_camera_fit.py), and recordings
of it: a joint log and the frames of a camera watching the arm make random moves, written as a ROS 2 bag or as a CSV
beside a folder of images or a video.

The arm is written here (3 hinges, a tag on the hand), not one the project ships. Its tag is rolled 20 degrees in its
plane: edges along the pixel rows and columns quantise OpenCV's AprilTag corners (selfid_jax.robot.camera.tracker's
docstring). :data:`CAMERA` is tests/test_camera.py's (640x480, the tag about 0.67 m away, ~42 px); :data:`FIT_CAMERA`
is the fit tests' (320x240, half as far: ~44 px, a quarter of the pixels to render and track).

A recording (:func:`record`): the arm rests at ``Q0``, then every ``PERIOD`` s is commanded to ``Q0 + d_k``
(``d_k``: each joint +-0.015..0.03 rad, independent of the previous move, so every configuration stays within 0.03 rad
of ``Q0`` where the Jacobian is compared) and follows through a first-order servo lag ``TAU``. The joints are logged
at ``JOINT_RATE`` (a stream); the camera takes one frame at the end of each rest (``frames="rest"``: a triggered
camera) or runs at ``camera_rate`` throughout (``frames="stream"``), each frame rendered at the joint positions of its
capture time.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from selfid_jax.robot.camera.render import CameraSettings, RenderUnavailable
from selfid_jax.robot.camera.sim import SimCamera
from selfid_jax.robot.camera.tracker import TrackerSettings

ARM_XML = """
<mujoco model="camera_test_arm">
  <compiler angle="radian"/>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.01" rgba="0.35 0.4 0.45 1"/>
    <body name="base" pos="0 0 0.05">
      <joint name="yaw" axis="0 0 1" range="-3 3"/>
      <geom type="cylinder" size="0.05 0.05" rgba="0.6 0.6 0.6 1"/>
      <body name="upper" pos="0 0 0.05">
        <joint name="shoulder" axis="0 1 0" range="-2 2"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.3" size="0.025" rgba="0.8 0.5 0.2 1"/>
        <body name="fore" pos="0 0 0.3">
          <joint name="elbow" axis="0 1 0" range="-2.5 2.5"/>
          <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" rgba="0.8 0.5 0.2 1"/>
          <body name="hand" pos="0.25 0 0">
            <geom type="box" size="0.015 0.045 0.045" rgba="0.5 0.5 0.5 1"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""
JOINTS = ("yaw", "shoulder", "elbow")
Q0 = np.array([0.0, 0.3, -0.3])  # the hand's face (body +x) towards +x, about 0.69 m from CAMERA
TAG = TrackerSettings(family="tag36h11", tag_id=7, edge=0.05)
TAG_SPEC = "tag36h11:7:0.05"  # the same tag, as --tag / tag= write it


def rolled(quat, degrees):
    """``quat`` (wxyz) turned by ``degrees`` about its own z (a tag rolled in its plane)."""
    half = np.radians(degrees) / 2
    w, x, y, z = quat
    c, s = np.cos(half), np.sin(half)
    return (w * c - z * s, x * c + y * s, y * c - x * s, z * c + w * s)


# On the hand's +x face (tag x, y, z = body y, z, x), rolled 20 degrees in its plane.
TAG_POS, TAG_QUAT = (0.016, 0.0, 0.0), rolled((0.5, 0.5, 0.5, 0.5), 20.0)
CAMERA = CameraSettings(width=640, height=480, fovy=45.0, position=(1.0, 0.15, 0.5), look_at=(0.34, 0.0, 0.39),
                        noise=2.0, seed=3)
FIT_CAMERA = CAMERA._replace(width=320, height=240, position=(0.67, 0.075, 0.445))  # halfway to look_at

M_A = 0.03  # rad, largest move from Q0 per joint
PERIOD = 0.5  # s between commands
TAU = 0.03  # s, first-order servo lag
JOINT_RATE = 50.0  # Hz
NS = 1_000_000_000
T0 = 1_700_000_000 * NS + 123_456_789  # a bag's epoch stamp of t = 0


def open_sim(camera: CameraSettings = CAMERA) -> SimCamera:
    """The arm with its tag before ``camera``; skips the test, with the reason, where no OpenGL context can be made."""
    try:
        return SimCamera(ARM_XML, "hand", tag=TAG, tag_pos=TAG_POS, tag_quat=TAG_QUAT, camera=camera)
    except RenderUnavailable as err:
        pytest.skip(f"no OpenGL backend for headless rendering: {err}")


class Recording(NamedTuple):
    """A joint stream and the camera's frames of one session (times in s from the session's start)."""

    joint_t: np.ndarray  # (K,) joint log times, s
    joint_q: np.ndarray  # (K, 3) joint positions, rad (JOINTS order)
    frame_t: np.ndarray  # (F,) capture times, s
    frames: list  # (F,) RGB (H, W, 3) uint8 frames
    jacobian: np.ndarray  # (3, 3) MuJoCo's Jacobian of the tag centre at Q0, camera frame, m/rad
    intrinsics: object  # the camera's Intrinsics


def _servo(moves, seed):
    """Commands and the servo's joint positions as a function of time."""
    rng = np.random.default_rng(seed)
    cmd = np.array([Q0] + [Q0 + rng.choice([-1.0, 1.0], 3) * rng.uniform(0.5, 1.0, 3) * M_A for _ in range(moves)])
    t_cmd = PERIOD * np.arange(1, moves + 1)  # command k at t_cmd[k - 1]
    start = [Q0, Q0]  # position when segment k starts
    for k in range(1, moves):
        start.append(cmd[k] + (start[k] - cmd[k]) * np.exp(-PERIOD / TAU))

    def q_at(t):
        t = np.asarray(t, np.float64)
        k = np.searchsorted(t_cmd, t, side="right")
        since = np.where(k == 0, 0.0, t - np.concatenate([[0.0], t_cmd])[k])
        return cmd[k] + (np.asarray(start)[k] - cmd[k]) * np.exp(-since / TAU)[:, None]

    return q_at


def record(sim: SimCamera, *, moves: int = 30, seed: int = 0, frames: str = "rest", camera_rate: float = 15.0
           ) -> Recording:
    """A session of ``moves`` random moves before ``sim`` (see the module docstring)."""
    q_at = _servo(moves, seed)
    end = PERIOD * (moves + 1)
    joint_t = np.arange(int(round(end * JOINT_RATE))) / JOINT_RATE
    if frames == "rest":
        frame_t = PERIOD * np.arange(moves + 1) + PERIOD - 0.05  # the end of each rest
    else:
        frame_t = np.arange(0.013, end - 0.02, 1.0 / camera_rate)
    images = [sim.render(q) for q in q_at(frame_t)]
    return Recording(joint_t, q_at(joint_t), frame_t, images, sim.truth(Q0).jacobian[:3], sim.intrinsics)


# ------------------------------------------------------------------------------------------- files
def write_joint_csv(path: Path, rec: Recording) -> Path:
    """The joint stream as a CSV ``t, yaw, shoulder, elbow`` (ROS-like names: the fit maps them with --joint-names)."""
    rows = np.column_stack([rec.joint_t, rec.joint_q])
    np.savetxt(path, rows, delimiter=",", header="t," + ",".join(JOINTS), comments="", fmt="%.17g")
    return path


def write_frame_times(path: Path, times) -> Path:
    """A frame-times CSV: one ``t`` per frame."""
    np.savetxt(path, np.asarray(times, np.float64), header="t", comments="", fmt="%.17g")
    return path


def write_folder(folder: Path, frames) -> Path:
    """The frames as zero-padded PNGs (``frame_0000.png`` ..), colour as OpenCV writes it (BGR)."""
    folder.mkdir(parents=True, exist_ok=True)
    for k, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"frame_{k:04d}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    return folder


def write_video(path: Path, frames, fps: float = 2.0, fourcc: str = "MJPG") -> Path:
    """The frames as a video (cv2.VideoWriter): an MJPG ``.avi`` by default, ``fourcc="mp4v"`` for an ``.mp4``."""
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 100)
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


STORE = get_typestore(Stores.ROS2_HUMBLE)
ROS1_STORE = get_typestore(Stores.ROS1_NOETIC)


def _header(stamp, frame="", store=STORE):
    t = store.types["builtin_interfaces/msg/Time"](sec=int(stamp) // NS, nanosec=int(stamp) % NS)
    if store is ROS1_STORE:  # ROS 1's Header has a sequence number
        return store.types["std_msgs/msg/Header"](seq=0, stamp=t, frame_id=frame)
    return store.types["std_msgs/msg/Header"](stamp=t, frame_id=frame)


def image_message(stamp, frame, encoding="mono8", store=STORE):
    """A ``sensor_msgs/Image`` of an RGB ``frame`` in ``encoding`` (mono8, rgb8, bgr8, rgba8, bgra8), rows padded
    by 4 bytes (``step`` > width x channels, as some drivers align them)."""
    if encoding == "mono8":
        data = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
    else:
        code = {"rgb8": None, "bgr8": cv2.COLOR_RGB2BGR, "rgba8": cv2.COLOR_RGB2RGBA, "bgra8": cv2.COLOR_RGB2BGRA}
        data = frame if code[encoding] is None else cv2.cvtColor(frame, code[encoding])
    h, w = data.shape[:2]
    rows = data.reshape(h, -1)
    padded = np.zeros((h, rows.shape[1] + 4), np.uint8)
    padded[:, :rows.shape[1]] = rows
    return store.types["sensor_msgs/msg/Image"](header=_header(stamp, "camera_optical", store), height=h, width=w,
                                                encoding=encoding, is_bigendian=0, step=padded.shape[1],
                                                data=padded.reshape(-1))


def compressed_message(stamp, frame, store=STORE):
    """A ``sensor_msgs/CompressedImage`` (PNG) of an RGB ``frame``."""
    ok, data = cv2.imencode(".png", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    assert ok
    return store.types["sensor_msgs/msg/CompressedImage"](header=_header(stamp, "camera_optical", store),
                                                          format="png", data=np.asarray(data, np.uint8).reshape(-1))


def camera_info_message(stamp, intrinsics, store=STORE):
    """A ``sensor_msgs/CameraInfo`` of ``intrinsics`` (plumb_bob); ROS 1 names its matrices D, K, R, P."""
    K, dist, w, h = intrinsics
    P = np.zeros((3, 4))
    P[:, :3] = K
    t = store.types
    roi = t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    mats = dict(d=np.asarray(dist, np.float64), k=np.asarray(K, np.float64).reshape(-1), r=np.eye(3).reshape(-1),
                p=P.reshape(-1))
    if store is ROS1_STORE:
        mats = {name.upper(): value for name, value in mats.items()}
    return t["sensor_msgs/msg/CameraInfo"](header=_header(stamp, "camera_optical", store), height=h, width=w,
                                           distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **mats)


def joint_message(stamp, q, store=STORE):
    empty = np.zeros(0)
    return store.types["sensor_msgs/msg/JointState"](header=_header(stamp, "", store), name=list(JOINTS),
                                                     position=np.asarray(q, np.float64), velocity=empty, effort=empty)


def write_bag(path: Path, rec: Recording, *, encoding="mono8", camera_info=True, image_topic="/camera/image_raw",
              frames=None, storage="mcap", stamp_offset=None) -> Path:
    """``rec`` as a bag: /joint_states, ``image_topic`` (sensor_msgs/Image in ``encoding``, or CompressedImage for
    ``encoding="png"``) and, with ``camera_info``, /camera/camera_info (one message per frame). ``storage``: "mcap"
    or "sqlite3" (ROS 2), or "ros1" (a ROS 1 ``.bag``: give ``path`` that suffix). Stamps are ``T0`` + the
    recording's times; each frame is received 30 ms after its capture. ``frames`` replaces the recording's frames (a
    frozen or darkened camera); ``stamp_offset`` (s, one per frame) is added to each frame's header stamp, not to its
    receive time (a camera clock that stepped)."""
    frames = rec.frames if frames is None else frames
    store = ROS1_STORE if storage == "ros1" else STORE
    items = [(T0 + int(round(t * NS)), "/joint_states", joint_message(T0 + int(round(t * NS)), q, store))
             for t, q in zip(rec.joint_t, rec.joint_q)]
    offsets = np.zeros(len(frames)) if stamp_offset is None else stamp_offset
    for t, frame, offset in zip(rec.frame_t, frames, offsets):
        stamp = T0 + int(round(t * NS))
        header = stamp + int(round(offset * NS))
        image = (compressed_message(header, frame, store) if encoding == "png"
                 else image_message(header, frame, encoding, store))
        items.append((stamp + 30_000_000, image_topic, image))
        if camera_info:
            items.append((stamp + 30_000_000, "/camera/camera_info", camera_info_message(stamp, rec.intrinsics, store)))
    items.sort(key=lambda item: item[0])
    if storage == "ros1":
        writer, serialize = Writer1(path), store.serialize_ros1
    else:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer, serialize = Writer2(path, version=Writer2.VERSION_LATEST, storage_plugin=plugin), store.serialize_cdr
    with writer:
        types = {"/joint_states": "sensor_msgs/msg/JointState", "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
                 image_topic: "sensor_msgs/msg/CompressedImage" if encoding == "png" else "sensor_msgs/msg/Image"}
        conn = {topic: writer.add_connection(topic, msgtype, typestore=store) for topic, msgtype in types.items()
                if camera_info or topic != "/camera/camera_info"}
        for recv, topic, msg in items:
            writer.write(conn[topic], recv, serialize(msg, msg.__msgtype__))
    return path
