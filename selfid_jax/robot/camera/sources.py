"""Camera frames for a fit: a video, a folder of images or a bag's image topic, one tag tracker behind them all.

A source is a :class:`FrameSource`: frames ``(H, W)`` grey uint8 with their
capture times (s, on the joint log's clock), read lazily, one at a time:

* :func:`video_source`: a video file (``cv2.VideoCapture``) or a folder of
  images (:func:`image_files`: sorted by file name), with a CSV of frame times
  (:func:`read_frame_times`: a ``t`` column, one row per frame, in the joint
  log's ``--time`` unit);
* :func:`bag_source`: a ROS 1/2 bag's or an MCAP file's ``sensor_msgs/Image``
  (:data:`ENCODINGS`) or ``sensor_msgs/CompressedImage`` topic, stamped by
  ``header.stamp``, with the intrinsics of the ``camera_info`` topic beside it
  (:func:`camera_info_topic`) or of a file.

:func:`track_frames` runs one :class:`~selfid_jax.robot.camera.tracker.TagTracker`
over a source: the valid poses as tracker columns, the dropouts counted by
reason in a :class:`CameraReport`, and a :class:`~selfid_jax.robot.log.LogError`
when the tag is never seen (naming its family and id, and the ids that were)
or fewer than :data:`MIN_VALID_FRAMES` frames give a pose. :func:`bag_camera_table`
and :func:`video_camera_table` turn a fit's options into the joint log's table
with those columns, matched to the joints by time with the bags' one matcher
(:func:`selfid_jax.robot.bags.match_to_joints`); :func:`selfid_jax.robot.read.read_log`
calls them. :func:`read_images` reads a folder or a video whole, for calibration.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

from selfid_jax.robot.camera.intrinsics import Intrinsics, camera_info_intrinsics, read_intrinsics
from selfid_jax.robot.camera.tracker import TagTracker, TrackerSettings, check_tracker_settings
from selfid_jax.robot.fit_options import ReadOptions, parse_tag
from selfid_jax.robot.log import LogError, parse_task

__all__ = ["CAMERA_INFO_TYPE", "COMPRESSED_TYPE", "CameraReport", "ENCODINGS", "FrameSource", "IMAGE_SUFFIXES",
           "IMAGE_TYPE", "MIN_VALID_FRAMES", "Tracked", "bag_camera_table", "bag_source", "camera_info_topic",
           "image_files", "read_frame_times", "read_images", "tag_settings", "track_frames", "video_camera_table",
           "video_source"]

#: Image files a folder source reads, by suffix (any case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
#: ``sensor_msgs/Image`` encodings read -> OpenCV's conversion to grey (None: already grey); 8UC3 is taken as BGR.
ENCODINGS = {"mono8": None, "8uc1": None, "bgr8": cv2.COLOR_BGR2GRAY, "rgb8": cv2.COLOR_RGB2GRAY,
             "bgra8": cv2.COLOR_BGRA2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY, "8uc3": cv2.COLOR_BGR2GRAY}
#: Fewer frames with a pose of the tag than this: no fit (a stream's rest needs 5 rows, a 6-D task 7 samples).
MIN_VALID_FRAMES = 10
_NS = 1_000_000_000
_TRANSPORTS = ("compressed", "compressedDepth", "theora", "zstd")  # image_transport's sub-topics


class FrameSource(NamedTuple):
    """Frames of one camera, read lazily, with what to call them in messages."""

    name: str  # the video file, the folder, or "BAG topic TOPIC"
    kind: str  # "video", "images", or the image topic's message type
    frame_count: int  # frames the source holds (-1: not known before reading)
    frames: Iterable[tuple[np.ndarray, float]]  # (H, W) grey uint8 frame, capture time (s, the joint log's clock)


class CameraReport(NamedTuple):
    """What a fit's camera gave (:func:`track_frames`): frames, tag poses, dropouts by reason, tag and intrinsics."""

    source: str  # the frames: a video file, a folder of images, or "BAG topic TOPIC"
    kind: str  # "video", "images", or the image topic's message type
    frames: int  # frames tracked
    poses: int  # frames that gave a pose of the tag (the tracker's rows)
    dropouts: dict[str, int]  # reason (selfid_jax.robot.camera.tracker.REASONS) -> frames
    other_ids: dict[int, int]  # other ids of the tag's family detected -> frames
    family: str  # the tag's family
    tag_id: int  # the tag's id
    edge: float  # the tag's edge (black square) used, m: every position scales with it
    rotation: bool  # a rotation task: frames with an unresolved planar ambiguity are dropouts
    intrinsics: str  # where the intrinsics came from: a file, or "BAG topic TOPIC"
    width: int  # frame width, pixels
    height: int  # frame height, pixels
    fx: float  # focal lengths and principal point used, pixels
    fy: float
    cx: float
    cy: float

    def lines(self) -> list[str]:
        """The report's lines: frames and dropouts, the tag size (and what a wrong one does), the intrinsics."""
        dropped = sum(self.dropouts.values())
        reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(self.dropouts.items()))
        stale = self.dropouts.get("stale", 0)
        out = [f"camera: {self.frames} frames of {self.source} ({self.kind}, {self.width}x{self.height}): "
               f"{self.poses} tag poses, {dropped} dropouts{f' ({reasons})' if dropped else ''}",
               f"tag: {self.family} id {self.tag_id}, edge {self.edge:g} m (every position scales with the edge: a "
               "wrong edge scales the estimate by true / given)",
               f"intrinsics: {self.intrinsics} (fx {self.fx:.1f}, fy {self.fy:.1f}, cx {self.cx:.1f}, "
               f"cy {self.cy:.1f} px)"]
        if stale:
            out.append(f"{stale} stale frames (identical to the frame before: a frozen camera or driver) dropped")
        return out


class Tracked(NamedTuple):
    """Output of :func:`track_frames`: the valid poses as tracker columns, and the report."""

    stamps: np.ndarray  # (T,) int64 capture times of the valid poses, ns (round(t * 1e9))
    columns: dict[str, np.ndarray]  # p_x, p_y, p_z (m, camera frame) and, for a rotation task, q_w, q_x, q_y, q_z
    report: CameraReport
    frame_index: np.ndarray  # (T,) int64 each pose's frame, 0-based in the source's order

def open_video(path: Path, flag: str = "") -> cv2.VideoCapture:
    """An opened ``cv2.VideoCapture`` of the video file ``path``; LogError naming the file (and ``flag``, e.g.
    ``" (--video)"``) when there is no such file or OpenCV cannot decode it."""
    if not path.is_file():
        raise LogError(f"{path}{flag}: no such file or folder")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise LogError(f"{path}{flag}: OpenCV cannot open it as a video (or a folder of images)")
    return capture



def tag_settings(options: ReadOptions) -> TrackerSettings:
    """The tracker settings of a fit's ``tag`` (``FAMILY:ID:EDGE_M``) and task (a rotation axis: ``rotation``);
    ValueError naming ``tag`` (``--tag``) for a family or id OpenCV does not know."""
    assert options.tag is not None
    family, tag_id, edge = parse_tag(options.tag)
    axes = parse_task(options.task, options.task_dim) or ()
    settings = TrackerSettings(family=family, tag_id=tag_id, edge=edge, rotation=any(a >= 3 for a in axes))
    try:
        return check_tracker_settings(settings)
    except ValueError as err:
        raise ValueError(f"tag (--tag) {options.tag}: {err}") from None


# ------------------------------------------------------------------------------------------- files
def _natural(name: str) -> list[Any]:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def image_files(folder: str | Path) -> list[Path]:
    """The images of ``folder`` (:data:`IMAGE_SUFFIXES`), sorted by file name; :class:`LogError` if it holds none,
    or if its numbers are not zero-padded so that name order is not frame order (``f10`` before ``f2``)."""
    folder = Path(folder)
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise LogError(f"{folder}: no image files ({', '.join(IMAGE_SUFFIXES)})")
    natural = sorted(files, key=lambda p: _natural(p.name))
    if natural != files:
        k = next(i for i, (a, b) in enumerate(zip(files, natural)) if a != b)
        raise LogError(f"{folder}: frames are taken in file-name order, and {files[k].name} sorts before "
                       f"{natural[k].name}: number the files with zero padding (frame_0002.png)")
    return files


def read_frame_times(path: str | Path, *, time: str = "s") -> np.ndarray:
    """The ``t`` column of a CSV (Parquet, NPZ) of frame times, one row per frame, in seconds: ``(N,)`` float64.

    ``time``: the column's unit (the joint log's ``--time``), unless a units
    row gives it. Raises :class:`LogError` naming the file (and line) for a
    missing ``t`` column, a non-finite time or times that do not increase.
    """
    from selfid_jax.robot.log import read_table_units
    from selfid_jax.robot.tables import Units, apply_units

    source = f"{path} (--frame-times)"
    if not Path(path).is_file():
        raise LogError(f"{source}: no such file")
    table, row_units = read_table_units(path)
    if "t" not in table:
        raise LogError(f"{source}: column t is missing (one row per frame, its capture time); found "
                       f"{', '.join(list(table)[:8])}")
    try:
        converted, _ = apply_units({"t": table["t"]}, Units(time=time), {k: v for k, v in row_units.items()
                                                                          if k == "t"}, source=source)
        t = np.asarray(converted["t"], np.float64).reshape(-1)
    except (TypeError, ValueError) as err:
        raise LogError(f"{source}: column t: {err}") from None
    header = 2 if row_units else 1  # the CSV's line of row 0: after the header (and the units row)
    bad = ~np.isfinite(t)
    if bad.any():
        raise LogError(f"{source}: line {int(np.argmax(bad)) + header + 1}: t is not a finite number")
    back = np.diff(t) <= 0
    if back.any():
        i = int(np.argmax(back)) + 1
        raise LogError(f"{source}: line {i + header + 1}: t = {t[i]:.9g} s does not come after {t[i - 1]:.9g} s; "
                       "frame times must increase")
    return t


def video_source(video: str | Path, frame_times: str | Path, *, time: str = "s") -> FrameSource:
    """A video file or a folder of images (sorted by file name) with their frame times (:func:`read_frame_times`):
    a :class:`FrameSource`. Raises :class:`LogError` for a missing or unreadable file and for a number of frames
    other than the times' rows."""
    video = Path(video)
    times = read_frame_times(frame_times, time=time)
    if video.is_dir():
        files = image_files(video)
        if len(files) != times.size:
            raise LogError(f"{video}: {len(files)} images but {frame_times} has {times.size} frame times (one row "
                           "per image, in file-name order)")
        return FrameSource(str(video), "images", len(files), _folder_frames(files, times))
    capture = open_video(video, " (--video)")
    return FrameSource(str(video), "video", times.size, _video_frames(capture, video, Path(frame_times), times))


def _grey(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def _folder_frames(files: list[Path], times: np.ndarray) -> Iterator[tuple[np.ndarray, float]]:
    for path, t in zip(files, times):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise LogError(f"{path}: OpenCV cannot read it as an image")
        yield image, float(t)


def _video_frames(capture: Any, video: Path, frame_times: Path, times: np.ndarray
                  ) -> Iterator[tuple[np.ndarray, float]]:
    try:
        k = 0
        while True:
            ok, image = capture.read()
            if not ok:
                break
            if k >= times.size:
                raise LogError(f"{video}: more frames than the {times.size} frame times of {frame_times}")
            yield _grey(image), float(times[k])
            k += 1
        if k != times.size:
            raise LogError(f"{video}: {k} frames but {frame_times} has {times.size} frame times (one row per frame)")
    finally:
        capture.release()


def _spaced(count: int, most: int | None) -> list[int]:
    """Indices of at most ``most`` of ``count`` items, evenly spaced, first and last included (None: all)."""
    if most is None or count <= most:
        return list(range(count))
    return np.unique(np.linspace(0, count - 1, most).round().astype(int)).tolist()


def read_images(path: str | Path, *, max_images: int | None = None) -> tuple[list[np.ndarray], list[str]]:
    """The images of a folder (by file name) or the frames of a video, grey ``(H, W)`` uint8, and their names
    (file names, or ``VIDEO frame k``); at most ``max_images``, evenly spaced (None: all).

    Raises :class:`LogError` for a missing, unreadable or empty source."""
    path = Path(path)
    if path.is_dir():
        every = image_files(path)
        files = [every[i] for i in _spaced(len(every), max_images)]
        return [frame for frame, _ in _folder_frames(files, np.zeros(len(files)))], [p.name for p in files]
    capture = open_video(path)
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))  # the container's count: 0 or approximate for some codecs
    wanted = set(_spaced(count, max_images)) if count > 0 else None
    images, names = [], []
    try:
        k = 0
        while True:
            ok, image = capture.read()
            if not ok:
                break
            if wanted is None or k in wanted:
                images.append(_grey(image))
                names.append(f"{path.name} frame {k}")
            k += 1
    finally:
        capture.release()
    if not images:
        raise LogError(f"{path}: no frame could be read")
    return images, names


# ------------------------------------------------------------------------------------------- bags
def camera_info_topic(image_topic: str) -> str:
    """The ``camera_info`` topic beside an image topic: ``/camera/image_raw`` (and its transports, e.g.
    ``/camera/image_raw/compressed``) -> ``/camera/camera_info``."""
    parts = image_topic.rstrip("/").split("/")
    if len(parts) > 2 and parts[-1] in _TRANSPORTS:
        parts = parts[:-1]
    return "/".join(parts[:-1] + ["camera_info"])


def bag_source(bag: str | Path, topic: str, *, camera_info: str | Path | None = None,
               received: list[tuple[int, int]] | None = None) -> tuple[FrameSource, Intrinsics, str]:
    """The frames of a bag's image topic (``sensor_msgs/Image`` or ``CompressedImage``, stamped by ``header.stamp``)
    and the camera's intrinsics: ``(source, intrinsics, where they came from)``.

    The intrinsics are ``camera_info``'s (a file, OpenCV's or ROS's YAML)
    where given, else the first message of the ``camera_info`` topic beside
    the image topic (:func:`camera_info_topic`). Raises :class:`LogError`
    naming the bag and topic: no such topic, another message type, no
    ``camera_info`` topic and no file, an uncalibrated ``camera_info``.
    ``received``: where given, each frame read appends ``(header stamp ns,
    the bag's receive time ns)`` to it (:func:`bag_camera_table` screens the
    camera's clock with them).
    """
    from selfid_jax.robot import bags

    source = str(bag)
    reader = bags.open_bag(bag)
    try:
        topics = dict(reader.topics)
        msgtype = bags.topic_type(source, topics, topic, "camera", (IMAGE_TYPE, COMPRESSED_TYPE))
        count = int(topics[topic].msgcount)
        if camera_info is not None:
            intrinsics, where = _intrinsics_file(camera_info), str(camera_info)
        else:
            info = camera_info_topic(topic)
            if info not in topics:
                raise LogError(f"{source}: topic {topic} has no camera_info beside it ({info} is not in the bag): "
                               "give the camera's intrinsics with --camera-info FILE (camera_info=), e.g. written by "
                               "selfid-jax calibrate")
            bags.topic_type(source, topics, info, "camera info", (CAMERA_INFO_TYPE,))
            msg = next(bags.messages(reader, topics[info].connections, source, info), None)
            if msg is None:
                raise LogError(f"{source}: topic {info} (the camera info) has no messages: give the camera's "
                               "intrinsics with --camera-info FILE (camera_info=)")
            k = msg.k if hasattr(msg, "k") else msg.K  # ROS 2 names the fields k, d; ROS 1 K, D
            d = msg.d if hasattr(msg, "d") else msg.D
            try:
                intrinsics = camera_info_intrinsics(k, d, msg.distortion_model, msg.width, msg.height,
                                                    source=f"{source}: topic {info}")
            except ValueError as err:
                raise LogError(f"{err} (or give --camera-info FILE)") from None
            where = f"{source} topic {info}"
    finally:
        reader.close()
    return FrameSource(f"{source} topic {topic}", msgtype, count, _bag_frames(bag, topic, msgtype, received)), \
        intrinsics, where


def _intrinsics_file(path: str | Path) -> Intrinsics:
    try:
        return read_intrinsics(path)
    except ValueError as err:
        raise LogError(f"camera_info (--camera-info): {err}") from None


def _bag_frames(bag: str | Path, topic: str, msgtype: str, received: list[tuple[int, int]] | None
                ) -> Iterator[tuple[np.ndarray, float]]:
    from selfid_jax.robot import bags

    source = str(bag)
    reader = bags.open_bag(bag)
    try:
        stream = bags.received_messages(reader, dict(reader.topics)[topic].connections, source, topic)
        for k, (recv, msg) in enumerate(stream, start=1):
            where = f"{source}: topic {topic}: message {k}"
            image = _decode(msg, where) if msgtype == IMAGE_TYPE else _decompress(msg, where)
            stamp = bags.stamp_ns(msg)
            if received is not None:
                received.append((stamp, recv))
            yield image, stamp / _NS
    finally:
        reader.close()


def _decode(msg: Any, where: str) -> np.ndarray:
    """A ``sensor_msgs/Image`` (:data:`ENCODINGS`) as a grey ``(H, W)`` uint8 frame (row padding dropped)."""
    encoding = str(msg.encoding).lower()
    if encoding not in ENCODINGS:
        raise LogError(f"{where}: encoding {msg.encoding!r} is not read; expected one of {', '.join(ENCODINGS)}")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    channels = {None: 1, cv2.COLOR_BGRA2GRAY: 4, cv2.COLOR_RGBA2GRAY: 4}.get(ENCODINGS[encoding], 3)
    data = np.asarray(msg.data, np.uint8).reshape(-1)
    if h <= 0 or w <= 0 or step < w * channels or data.size < h * step:
        raise LogError(f"{where}: a {w}x{h} {encoding} image needs {h} rows of at least {w * channels} bytes, got "
                       f"step {step} and {data.size} bytes")
    rows = data[:h * step].reshape(h, step)[:, :w * channels]
    conversion = ENCODINGS[encoding]
    if conversion is None:
        return np.ascontiguousarray(rows)
    return cv2.cvtColor(np.ascontiguousarray(rows.reshape(h, w, channels)), conversion)


def _decompress(msg: Any, where: str) -> np.ndarray:
    image = cv2.imdecode(np.asarray(msg.data, np.uint8).reshape(-1), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise LogError(f"{where}: OpenCV cannot decode its {msg.format!r} image")
    return image


# ------------------------------------------------------------------------------------------- tracking
def track_frames(source: FrameSource, intrinsics: Intrinsics, settings: TrackerSettings, *,
                 intrinsics_source: str) -> Tracked:
    """One :class:`~selfid_jax.robot.camera.tracker.TagTracker` over every frame of ``source``: the valid poses as
    tracker columns (dropouts left out, counted by reason in the report).

    Raises :class:`LogError` naming the source: no frame, a frame of another
    size than the intrinsics', the tag never seen (naming its family and id
    and the family's ids that were seen), or fewer than :data:`MIN_VALID_FRAMES`
    frames with a pose (their dropouts by reason, a frozen camera's as stale).
    """
    tracker = TagTracker(intrinsics, settings)
    stamps: list[int] = []
    index: list[int] = []
    rows: list[tuple[float, ...]] = []
    frames = source.frames
    try:
        for k, (frame, t) in enumerate(frames):
            try:
                pose = tracker.track(frame, t)
            except ValueError as err:
                raise LogError(f"{source.name}: frame {tracker.frames + 1}: {err} (from {intrinsics_source})"
                               ) from None
            if pose.valid:
                stamps.append(int(round(t * _NS)))
                index.append(k)
                rows.append((*pose.position, *pose.quaternion))
    finally:
        close = getattr(frames, "close", None)  # a generator holding a video or a bag open
        if close is not None:
            close()
    K = intrinsics.K
    report = CameraReport(source.name, source.kind, tracker.frames, len(rows), dict(tracker.dropouts),
                          dict(tracker.other_ids), settings.family, int(settings.tag_id), float(settings.edge),
                          bool(settings.rotation), intrinsics_source, intrinsics.width, intrinsics.height,
                          float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    _check_poses(report)
    values = np.array(rows, np.float64).reshape(-1, 7)
    names = ("p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z")[:7 if settings.rotation else 3]
    return Tracked(np.array(stamps, np.int64), {c: values[:, k].copy() for k, c in enumerate(names)}, report,
                   np.array(index, np.int64))


def _check_poses(report: CameraReport) -> None:
    """:class:`LogError` for a source without frames, a tag never seen, or too few poses."""
    tag = f"tag {report.family} id {report.tag_id}"
    reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(report.dropouts.items()))
    if report.frames == 0:
        raise LogError(f"{report.source}: no frames")
    if report.poses == 0:
        seen = ", ".join(f"{i} ({n} frames)" for i, n in sorted(report.other_ids.items()))
        hint = (f"the frames show {report.family} ids {seen}: is --tag's id right?" if seen else
                f"no {report.family} tag was detected at all: is the tag in view, lit and of this family?")
        raise LogError(f"{report.source}: {tag} never seen in {report.frames} frames (dropouts: {reasons}); {hint}")
    if report.poses < MIN_VALID_FRAMES:
        stale = report.dropouts.get("stale", 0)
        frozen = f"; {stale} stale frames: a frozen camera or driver repeats its last frame" if stale else ""
        raise LogError(f"{report.source}: only {report.poses} of {report.frames} frames gave a pose of {tag} "
                       f"(dropouts: {reasons}){frozen}; a fit needs at least {MIN_VALID_FRAMES}")


# ------------------------------------------------------------------------------------------- tables
def bag_camera_table(bag: str | Path, options: ReadOptions) -> tuple[dict[str, np.ndarray], Any, CameraReport]:
    """A bag's joint states and its camera's tag poses (``options.camera``, ``options.tag``,
    ``options.camera_info``) as the raw time-series table, matched by stamp: ``(table, BagInfo, CameraReport)``.

    The table is :func:`selfid_jax.robot.bags.read_bag`'s, one row per
    frame with a pose: ``t`` (s), ``q_0 ..``, ``p_x, p_y, p_z`` (m, camera
    frame) and, for a rotation task, ``q_w, q_x, q_y, q_z``.
    """
    from selfid_jax.robot import bags

    assert options.joints is not None and options.camera is not None
    settings = tag_settings(options)
    source = str(bag)
    reader = bags.open_bag(bag)
    try:
        states = bags.read_joint_states(reader, source, options.joints, options.joint_names)
    finally:
        reader.close()
    received: list[tuple[int, int]] = []
    frames, intrinsics, where = bag_source(bag, options.camera, camera_info=options.camera_info, received=received)
    tracked = track_frames(frames, intrinsics, settings, intrinsics_source=where)
    first: list[str] = []  # as bags.read_bag screens its topics: messages whose clock stepped are dropped
    states, joint_steps = bags.screen_joint_clock(states, options.joints, first)
    pose_steps = 0
    if received:
        stamps, recv = (np.array(x, np.int64) for x in zip(*received))
        ok = bags.clock_steps(stamps, recv)
        if not ok.all():
            keep = ok[tracked.frame_index]  # received holds every frame read, in the source's order
            pose_steps = int((~ok).sum())
            first.append(bags.stepped_stamp(stamps, ok, options.camera))
            tracked = tracked._replace(stamps=tracked.stamps[keep], frame_index=tracked.frame_index[keep],
                                       columns={c: v[keep] for c, v in tracked.columns.items()})
    table, m = bags.match_to_joints(source, options.joints, options.camera, states, tracked.stamps, tracked.columns,
                                    what="frame")
    info = bags.BagInfo(source=source, joint_names=states.names, tracker_type=f"{frames.kind} tag",
                        frame="the camera frame", child_frame=None, joint_messages=int(states.stamps.size),
                        duplicate_joint_stamps=m.duplicate_joint_stamps, other_joint_messages=states.other,
                        tracker_messages=int(tracked.stamps.size), rows=m.rows, outside_span=m.outside_span,
                        skewed=m.skewed, max_skew=m.max_skew, joint_period=m.joint_period,
                        tracker_period=m.tracker_period, clock_steps=pose_steps, joint_clock_steps=joint_steps,
                        clock_step_first="; ".join(first))
    return table, info, tracked.report


def video_camera_table(table: Mapping[str, Any], options: ReadOptions, source: str
                       ) -> tuple[dict[str, np.ndarray], CameraReport, list[str]]:
    """A joint log's table (``t`` s, ``q_0 ..``, already in the fit's names and units) with the tag poses of
    ``options.video`` (frame times ``options.frame_times``, intrinsics ``options.camera_info``) as its tracker
    columns, matched by time: ``(table, CameraReport, notes)``.

    Each frame with a pose takes the joint positions interpolated at its time
    (:func:`selfid_jax.robot.bags.match_to_joints`: frames outside the log's
    time span, or between rows more than 3 median periods apart, are dropped
    and counted in the notes). Rows of the joint log with a non-finite ``t``
    or ``q`` are left out of the matching.
    """
    from selfid_jax.robot import bags

    assert options.video is not None and options.frame_times is not None and options.camera_info is not None
    settings = tag_settings(options)
    q_cols = sorted((c for c in table if c.startswith("q_") and c[2:].isdigit()), key=lambda c: int(c[2:]))
    if "t" not in table or not q_cols:
        raise LogError(f"{source}: --video needs a time series of joint positions (columns t, q_0, ..; others "
                       f"through --columns, --joint-names); found {', '.join(list(table)[:8])}")
    pose = [c for c in table if c in ("p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z", "r_x", "r_y", "r_z")]
    if pose:
        raise LogError(f"{source}: has tracker columns ({', '.join(pose)}) and --video: the camera is the tracker; "
                       "drop one")
    t = np.asarray(table["t"], np.float64)
    q = np.stack([np.asarray(table[c], np.float64) for c in q_cols], axis=1)
    ok = np.isfinite(t) & np.isfinite(q).all(axis=1)
    if np.unique(t[ok]).size < 2:
        raise LogError(f"{source}: {int(ok.sum())} rows with a finite t and q; matching frames by time needs at "
                       "least two distinct times")
    notes = [f"{int((~ok).sum())} joint rows with a non-finite t or q left out of the matching"] if not ok.all() else []
    intrinsics = _intrinsics_file(options.camera_info)
    frames = video_source(options.video, options.frame_times, time=options.time)
    tracked = track_frames(frames, intrinsics, settings, intrinsics_source=str(options.camera_info))
    states = bags.JointStates(tuple(q_cols), np.round(t[ok] * _NS).astype(np.int64), q[ok], 0)
    out, m = bags.match_to_joints(source, "its rows (t, q_..)", f"{options.video}", states, tracked.stamps,
                                  tracked.columns, what="frame")
    dropped = [(m.outside_span, "outside the joint log's time span"),
               (m.skewed, f"between joint rows more than {m.max_skew:.4g} s apart")]
    notes += [f"camera: {k} poses dropped: {why}" for k, why in dropped if k]
    if m.duplicate_joint_stamps:
        notes.append(f"{m.duplicate_joint_stamps} joint rows repeating a time left out of the matching")
    return out, tracked.report, notes
