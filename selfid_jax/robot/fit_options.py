"""The options of a fit from a log: plain values with their defaults, read by ``sj.fit`` and ``selfid-jax fit``.

:class:`ReadOptions` (how a log is read: layout, units, a continuous stream,
a bag's topics; :func:`selfid_jax.robot.read.read_log`) and :class:`FitOptions`
(the estimator's thresholds and refinement; :func:`selfid_jax.robot.offline.fit`)
are the one place each default of an offline fit is written: ``sj.fit``'s
keywords and the ``selfid-jax fit`` flags (keyword ``x_y`` is flag ``--x-y``)
take theirs from here. Importing this module loads neither numpy nor JAX
(the command line builds its flags from it).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

__all__ = ["LATENCY_CHOICES", "MAX_TAG_EDGE_M", "MODES", "FitOptions", "ReadOptions", "parse_tag"]

MODES = ("auto", "stream", "windows", "moves")
"""How a raw time series is read (:func:`selfid_jax.robot.streams.reduce_stream`)."""
LATENCY_CHOICES = ("auto", "none")
"""The tracker latency's named settings besides a number of seconds."""
MAX_TAG_EDGE_M = 2.0
"""A ``--tag`` edge longer than this many metres is refused: it was given in mm or cm (the edge scales every tracked
position, and so the estimate)."""


def _flag(name: str) -> str:
    """``latency (--latency)``: a keyword and the command's flag, for messages."""
    return f"{name} (--{name.replace('_', '-')})"


class ReadOptions(NamedTuple):
    """How to read a log: the options of ``sj.fit`` and ``selfid-jax fit`` (keyword ``x_y`` = flag ``--x-y``).

    The defaults here are the command's. :meth:`check` validates them (one
    message naming the keyword and flag) and returns them normalised.
    """

    task: str | Sequence[str | int] | None = None  # task axes, e.g. "x,y,z" or ("z", "rx"); None: the layout's default
    task_dim: int | None = None  # or the task dimension 2, 3 or 6 (not both)
    start: float | None = None  # ignore rows before this time (s, after unit conversion)
    stop: float | None = None  # ignore rows after this time (s)
    max_gap: float | str | None = "auto"  # time series: drop pairs of rows more than this many s apart;
    #   "auto": 3 median time steps; None or inf: no limit
    columns: str | Path | Mapping[str, str] | None = None  # log name -> fit name: a dict, "a=q_0,b=p_x" or a file
    joint_names: str | Sequence[str] | None = None  # these columns (in a bag: JointState names) are q_0.. in order
    length: str = "m"  # unit of the tracked positions: m, cm, mm
    time: str = "s"  # unit of t: s, ms, us, ns
    angle: str = "auto"  # unit of the actuator positions and rotation vectors: rad, deg; "auto" (not stated): rad,
    #   a joint beyond two turns refused as looking like degrees (a multi-turn joint needs "rad" stated)
    mode: str = "auto"  # a raw time series: "auto" (detect a stream; read by its rests, or by windows of its motion
    #   where it has none), "stream" (reduce it so), "windows" (reduce it by windows), "moves" (as it is)
    latency: str | float | None = "auto"  # a stream's tracker latency (s): "auto" (estimated), a number, None
    settle_speed: float | None = None  # a stream: joint speed below which the arm rests (actuator units / s)
    settle_time: float | None = None  # a stream: shortest rest that counts as settled (s)
    joints: str | None = None  # a bag: the sensor_msgs/JointState topic
    tracker: str | None = None  # a bag: the PoseStamped / TransformStamped / TFMessage topic
    child_frame: str | None = None  # a bag: on a tf topic, the tracked frame (child_frame_id)
    camera: str | None = None  # a bag: the camera's sensor_msgs/Image or CompressedImage topic (instead of tracker)
    video: str | Path | None = None  # a table log: the camera's frames, a video file or a folder of images (by name)
    frame_times: str | Path | None = None  # with video: a CSV with a t column, one row per frame (the --time unit)
    camera_info: str | Path | None = None  # the camera's intrinsics, OpenCV or ROS YAML (a bag: default the
    #   camera_info topic beside the image topic)
    tag: str | None = None  # with camera or video: the tracked AprilTag "FAMILY:ID:EDGE_M", e.g. tag36h11:7:0.05
    #   (EDGE_M: the black square's edge in metres; it scales every position, and so the estimate)

    def check(self) -> ReadOptions:
        """These options validated and normalised: ``columns`` a dict, ``joint_names`` a tuple (None if empty),
        ``latency`` ``"auto"``, seconds or None, ``max_gap`` ``"auto"``, seconds or None.

        Raises:
          ValueError: an option out of range or of the wrong kind; the message names the keyword and the flag.
        """
        from selfid_jax.robot.log import parse_task
        from selfid_jax.robot.tables import Units, parse_columns

        try:
            parse_task(self.task, self.task_dim)
        except ValueError as err:
            raise ValueError(f"{_flag('task')} / {_flag('task_dim')}: {err}") from None
        for name in ("start", "stop"):
            value = getattr(self, name)
            if value is not None and not (_is_number(value) and not math.isnan(value)):
                raise ValueError(f"{_flag(name)}: expected a number of seconds, got {value!r}")
        if self.start is not None and self.stop is not None and self.stop < self.start:
            raise ValueError(f"--stop {self.stop:g} is before --start {self.start:g} (stop < start)")
        max_gap = self.max_gap
        if isinstance(max_gap, str) and max_gap.strip().lower() != "auto":
            max_gap = _seconds("max_gap", max_gap)
        if isinstance(max_gap, str):
            max_gap = "auto"
        elif max_gap is not None:
            if not (_is_number(max_gap) and max_gap > 0):
                raise ValueError(f"{_flag('max_gap')} must be positive seconds (or auto, inf), got {max_gap!r}")
            max_gap = None if math.isinf(max_gap) else float(max_gap)
        Units(self.length, self.time, self.angle).check()
        if self.mode not in MODES:
            raise ValueError(f"{_flag('mode')}: expected one of {', '.join(MODES)}, got {self.mode!r}")
        latency: str | float | None
        if self.latency is None or (isinstance(self.latency, str) and self.latency.strip().lower() == "none"):
            latency = None
        elif isinstance(self.latency, str) and self.latency.strip().lower() == "auto":
            latency = "auto"
        else:
            latency = _seconds("latency", self.latency, "auto, none or")
            if not math.isfinite(latency):
                raise ValueError(f"{_flag('latency')}: expected auto, none or a finite number of seconds, "
                                 f"got {self.latency!r}")
        if self.settle_speed is not None and not (_is_number(self.settle_speed) and math.isfinite(self.settle_speed)
                                                  and self.settle_speed > 0):
            raise ValueError(f"{_flag('settle_speed')} must be a positive number (actuator units / s), got "
                             f"{self.settle_speed!r}")
        if self.settle_time is not None and not (_is_number(self.settle_time) and math.isfinite(self.settle_time)
                                                 and self.settle_time >= 0):
            raise ValueError(f"{_flag('settle_time')} must be a non-negative number of seconds, got "
                             f"{self.settle_time!r}")
        for name in ("joints", "tracker", "child_frame"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, str) and value.strip()):
                raise ValueError(f"{_flag(name)}: expected a topic or frame name, got {value!r}")
        self._check_camera()
        names = self.joint_names
        if isinstance(names, str):
            names = [x.strip() for x in names.split(",") if x.strip()]
        elif names is not None:
            names = list(names)
            if not all(isinstance(x, str) for x in names):
                raise ValueError(f"{_flag('joint_names')}: expected names (strings), got {self.joint_names!r}")
        return self._replace(columns=parse_columns(self.columns) or None, joint_names=tuple(names) if names else None,
                             latency=latency, max_gap=max_gap)

    def _check_camera(self) -> None:
        """The camera options: each needs its companions and excludes the pose tracker (ValueError naming the
        keyword and flag). Whether the log is a bag (``camera``) or a table (``video``) is the reader's to check."""
        if self.camera is not None and not (isinstance(self.camera, str) and self.camera.strip()):
            raise ValueError(f"{_flag('camera')}: expected an image topic name, got {self.camera!r}")
        for name in ("video", "frame_times", "camera_info"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (str, Path)) and str(value).strip()):
                raise ValueError(f"{_flag(name)}: expected a file or folder path, got {value!r}")
        if self.tag is not None:
            parse_tag(self.tag)
        frames = [name for name in ("camera", "video") if getattr(self, name) is not None]
        if len(frames) > 1:
            raise ValueError(f"{_flag('camera')} reads a bag's image topic, {_flag('video')} a video or folder "
                             "beside a table log: give one")
        if frames and (self.tracker is not None or self.child_frame is not None):
            other = "tracker" if self.tracker is not None else "child_frame"
            raise ValueError(f"{_flag(frames[0])} is the tracker: drop {_flag(other)} (one tracker per fit)")
        if frames and self.tag is None:
            raise ValueError(f"{_flag(frames[0])} needs {_flag('tag')}: the tracked AprilTag as FAMILY:ID:EDGE_M, "
                             "e.g. tag36h11:7:0.05")
        if not frames:
            given = [name for name in ("tag", "frame_times", "camera_info") if getattr(self, name) is not None]
            if given:
                raise ValueError(f"{_flag(given[0])} is for camera frames: give {_flag('video')} (a video or a folder "
                                 f"of images) or, for a bag, {_flag('camera')} (its image topic)")
        if self.video is not None and self.frame_times is None:
            raise ValueError(f"{_flag('video')} needs {_flag('frame_times')}: a CSV with a t column, one row per "
                             "frame, on the joint log's clock")
        if self.video is not None and self.camera_info is None:
            raise ValueError(f"{_flag('video')} needs {_flag('camera_info')}: the camera's intrinsics, an OpenCV "
                             "or ROS YAML file (selfid-jax calibrate writes one)")
        if self.camera is not None and self.frame_times is not None:
            raise ValueError(f"{_flag('frame_times')} is for {_flag('video')}; a bag's frames carry their stamps")
        if frames and self.length != "m":
            raise ValueError(f"{_flag('length')} {self.length}: the camera's positions are in metres (the unit of "
                             f"the {_flag('tag')} edge); --length is for a log's tracker columns")


def parse_tag(text: str) -> tuple[str, int, float]:
    """``"FAMILY:ID:EDGE_M"`` (e.g. ``"tag36h11:7:0.05"``) -> ``(family, id, edge in m)``.

    The edge is the tag's black square, in metres (at most :data:`MAX_TAG_EDGE_M`).
    The family's name and id range are checked against OpenCV's dictionaries
    where the frames are read (:func:`selfid_jax.robot.camera.tracker.check_tracker_settings`).
    Raises ValueError naming the keyword ``tag`` and the flag ``--tag``.
    """
    form = f"{_flag('tag')}: expected FAMILY:ID:EDGE_M, e.g. tag36h11:7:0.05 (the black square's edge in metres)"
    if not isinstance(text, str):
        raise ValueError(f"{form}, got {text!r}")
    parts = [p.strip() for p in text.split(":")]
    if len(parts) != 3 or not parts[0]:
        raise ValueError(f"{form}, got {text!r}")
    family, id_text, edge_text = parts
    try:
        tag_id = int(id_text)
        edge = float(edge_text)
    except ValueError:
        raise ValueError(f"{form}, got {text!r}") from None
    if tag_id < 0:
        raise ValueError(f"{_flag('tag')}: the tag id must be >= 0, got {tag_id} in {text!r}")
    if not (math.isfinite(edge) and edge > 0):
        raise ValueError(f"{_flag('tag')}: the edge must be a length > 0 in metres, got {edge_text!r} in {text!r}")
    if edge > MAX_TAG_EDGE_M:
        raise ValueError(f"{_flag('tag')}: an edge of {edge:g} m is not a tag's; give it in metres (0.05 for "
                         f"50 mm): every tracked position, and so the estimate, scales with it")
    return family, tag_id, edge


def _is_number(value: Any) -> bool:
    """A real number (numpy's too), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _seconds(name: str, value: Any, named: str = "") -> float:
    """``value`` (a number or its text) as float seconds; ValueError naming the keyword and flag."""
    if _is_number(value):
        return float(value)
    try:
        out = float(str(value).strip())
    except ValueError:
        raise ValueError(f"{_flag(name)}: expected {named + ' ' if named else ''}a number of seconds, "
                         f"got {value!r}") from None
    if math.isnan(out):
        raise ValueError(f"{_flag(name)}: expected a number of seconds, got nan")
    return out


class FitOptions(NamedTuple):
    """The estimator's options of an offline fit (:func:`selfid_jax.robot.offline.fit_samples`); the defaults are
    ``sj.fit``'s and ``selfid-jax fit``'s."""

    eps: float = 0.0  # Sec. IV-D absolute threshold on ||J_t - J_{t-1}||_F (inverse-Jacobian units)
    eps_rel: float = 0.05  # relative threshold, times ||J_t||_F; converged when the change is at most
    #   eps + eps_rel ||J_t||_F twice in a row
    method: str = "closed_form"  # Eq. 14 refinement (selfid_jax.identify.refine.METHODS; flag --refine)
