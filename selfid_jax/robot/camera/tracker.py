"""The camera tracker: frames -> an AprilTag's pose in the camera frame, or a dropout with its reason.

A source yields ``(frame, capture_time)`` (a live camera, a video, a bag's
image topic, :class:`~selfid_jax.robot.camera.sim.SimCamera`); :meth:`TagTracker.track`
maps each to a :class:`TagPose`, whose :meth:`TagPose.row` is the log's pose row
``(t, p_x, p_y, p_z, q_w, q_x, q_y, q_z, valid)`` (:data:`POSE_COLUMNS`, read by
:mod:`selfid_jax.robot.log`; :func:`pose_columns` turns a list of poses into the
column mapping ``read_log`` takes). Position in metres, quaternion ``(w, x, y, z)``
of the tag frame in the camera frame, OpenCV's conventions throughout: camera x
right, y down, z forward; tag frame at the tag's centre, x to the right of the
printed tag, y up, z out of its face (towards the camera that sees it).

Detector: OpenCV's ``cv2.aruco.ArucoDetector`` with the AprilTag dictionary
(:data:`TAG_FAMILIES`) and ``CORNER_REFINE_APRILTAG`` (the AprilTag 2 quad
detector: threshold, segment, fit four lines). Why not ``CORNER_REFINE_SUBPIX``:
on rendered frames (:mod:`~selfid_jax.robot.camera.measure`, 640x480, fovy 45,
a 50 mm tag, read noise 2 grey levels) its ``cornerSubPix`` pulls each corner
0.2-0.25 px into the tag (the corner's blur rounds it), a depth bias of 0.4-1.5 %
of the distance: position RMS 1.9 mm at 0.5 m (58 px tag) and 13 mm at 1 m
(29 px), against 0.4 mm and 1.6 mm with ``CORNER_REFINE_APRILTAG``. OpenCV's
AprilTag refinement counts pixel centres at (0.5, 0.5); the tracker shifts its
corners by :data:`APRILTAG_PIXEL_SHIFT` into OpenCV's convention. Its weak
case: its lines are fitted to a thresholded boundary (OpenCV's port has no
gradient edge refinement), so an edge that runs along the pixel rows or
columns is quantised to whole pixels; with the tag square to the image
(tests/test_camera.py's arm, a 42 px tag at 0.67 m) the depth noise was 2.7 mm,
0.8 mm with the tag rolled 20 degrees in its plane. Mount the tag rolled
15-30 degrees against the camera's image axes. One well-kept dependency,
``opencv-python-headless``, which calibration
(:mod:`~selfid_jax.robot.camera.calibrate`) and video reading need anyway;
``corner_refine="subpix"`` selects the other refinement.

Pose: ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)`` gives both solutions
of the planar ambiguity with their RMS reprojection errors; the better is kept
and ``ambiguity = best / second`` (0: resolved, 1: the two explain the corners
equally well) is reported. Above ``max_ambiguity`` the rotation is unreliable:
a tracker for a rotation task (``rotation=True``) drops the frame (reason
``"ambiguous"``); a position task keeps it (the position of both solutions
agrees) with ``rotation_ok`` False and NaN quaternion columns in its row.

A frame is a dropout (``valid`` False, NaN pose), never a pose, with one
reason code (:data:`REASONS`), counted in :attr:`TagTracker.dropouts`:
``"stale"`` the identical frame again (a frozen camera or driver),
``"no_tag"`` the id not detected, ``"low_contrast"`` no tag and a frame almost
uniform (dark, overexposed, covered: its brightest 4x4-pixel patch less than
``min_contrast`` grey levels above its darkest), ``"duplicate"`` the id detected more than once,
``"border"`` a corner within ``border_margin`` pixels of the image border (a
tag partly out of frame), ``"reprojection"`` RMS reprojection error above
``max_reprojection`` pixels, ``"ambiguous"`` (rotation task) as above.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, NamedTuple

import cv2
import mujoco
import numpy as np

from selfid_jax.robot.camera.intrinsics import Intrinsics, check_intrinsics

__all__ = ["APRILTAG_PIXEL_SHIFT", "POSE_COLUMNS", "REASONS", "TAG_FAMILIES", "TagPose", "TagTracker",
           "TrackerSettings", "check_tracker_settings", "pose_columns", "tag_dictionary"]

#: Tag family names -> OpenCV's AprilTag dictionaries.
TAG_FAMILIES = {
    "tag36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "tag36h10": cv2.aruco.DICT_APRILTAG_36h10,
    "tag25h9": cv2.aruco.DICT_APRILTAG_25h9,
    "tag16h5": cv2.aruco.DICT_APRILTAG_16h5,
}
#: Dropout reason codes, in the order the checks run.
REASONS = ("stale", "no_tag", "low_contrast", "duplicate", "border", "reprojection", "ambiguous")
#: The columns of :meth:`TagPose.row`, as :mod:`selfid_jax.robot.log` names a time series' pose.
POSE_COLUMNS = ("t", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z", "valid")
#: Pixels subtracted from each corner coordinate that ``CORNER_REFINE_APRILTAG`` returns: its quad fit counts a
#: pixel's centre at (0.5, 0.5), OpenCV (solvePnP, the intrinsics) at (0, 0); measured on rendered frames the
#: corners sit +0.42..0.44 px off in x and y without it, -0.06..-0.08 px with it (tests/test_camera.py checks it).
APRILTAG_PIXEL_SHIFT = 0.5
_CORNER_REFINE = {"apriltag": cv2.aruco.CORNER_REFINE_APRILTAG, "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
                  "none": cv2.aruco.CORNER_REFINE_NONE}


class TrackerSettings(NamedTuple):
    """What to track and when to refuse a frame."""

    family: str = "tag36h11"  # tag family, a key of TAG_FAMILIES
    tag_id: int = 0  # the tracked tag's id in its family
    edge: float = 0.05  # edge of the tag's black square (OpenCV's marker length), m
    rotation: bool = False  # the task uses the rotation: ambiguous rotations are dropouts
    max_reprojection: float = 2.0  # RMS reprojection error above which a detection is refused, pixels
    max_ambiguity: float = 0.5  # best / second IPPE reprojection error above which the rotation is unreliable
    border_margin: float = 3.0  # a corner closer than this to the image border: the tag may be cut, pixels
    min_contrast: float = 20.0  # brightest minus darkest 4x4 patch (grey levels) below which a frame without
    #   the tag is low_contrast rather than no_tag
    corner_refine: str = "apriltag"  # "apriltag", "subpix" or "none" (OpenCV's cornerRefinementMethod)


class TagPose(NamedTuple):
    """One frame's result: the tag's pose in the camera frame, or a dropout (``valid`` False, NaN pose)."""

    t: float  # capture time of the frame, s (the source's clock)
    position: np.ndarray  # (3,) tag centre, m, camera frame (x right, y down, z forward); NaN on a dropout
    quaternion: np.ndarray  # (4,) (w, x, y, z), w >= 0, tag frame in the camera frame; NaN on a dropout
    valid: bool  # a pose the task may use
    reason: str  # "" when valid, else one of REASONS
    rotation_ok: bool  # the planar ambiguity is resolved (ambiguity <= max_ambiguity)
    ambiguity: float  # best / second IPPE reprojection error, in [0, 1]; NaN without a detection
    reprojection: float  # RMS reprojection error of the kept solution, pixels; NaN without a detection
    corners: np.ndarray  # (4, 2) detected corners (top-left, top-right, bottom-right, bottom-left), px; NaN
    stale: bool  # the frame is identical to the previous one
    latency: float  # wall time from the frame's arrival to this result (detection and pose), s

    def row(self) -> tuple[float, ...]:
        """``(t, p_x, p_y, p_z, q_w, q_x, q_y, q_z, valid)`` (:data:`POSE_COLUMNS`): NaN quaternion where the
        rotation is unreliable, NaN pose on a dropout, ``valid`` 1.0 or 0.0."""
        q = self.quaternion if self.rotation_ok else np.full(4, np.nan)
        return (float(self.t), *map(float, self.position), *map(float, q), float(self.valid))


def tag_dictionary(family: str) -> Any:
    """OpenCV's ``cv2.aruco.Dictionary`` of a tag family named in :data:`TAG_FAMILIES`."""
    if family not in TAG_FAMILIES:
        raise ValueError(f"tag family: expected one of {sorted(TAG_FAMILIES)}, got {family!r}")
    return cv2.aruco.getPredefinedDictionary(TAG_FAMILIES[family])


def check_tracker_settings(settings: TrackerSettings) -> TrackerSettings:
    """Validate a :class:`TrackerSettings` (a known family, an id it has, positive edge and bounds)."""
    dictionary = tag_dictionary(settings.family)
    count = dictionary.bytesList.shape[0]
    if isinstance(settings.tag_id, bool) or not isinstance(settings.tag_id, (int, np.integer)) \
            or not 0 <= settings.tag_id < count:
        raise ValueError(f"tag_id: family {settings.family} has ids 0..{count - 1}, got {settings.tag_id!r}")
    for key in ("edge", "max_reprojection", "max_ambiguity"):
        value = float(getattr(settings, key))
        if not math.isfinite(value) or value <= 0:
            raise ValueError(f"{key}: expected a finite number > 0, got {getattr(settings, key)!r}")
    for key in ("border_margin", "min_contrast"):
        value = float(getattr(settings, key))
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"{key}: expected a finite number >= 0, got {getattr(settings, key)!r}")
    if settings.corner_refine not in _CORNER_REFINE:
        raise ValueError(f"corner_refine: expected one of {sorted(_CORNER_REFINE)}, got {settings.corner_refine!r}")
    return settings


class TagTracker:
    """Frames of one calibrated camera -> :class:`TagPose` of one tag; counts frames and dropouts by reason.

    ``intrinsics``: the camera's :class:`~selfid_jax.robot.camera.intrinsics.Intrinsics`
    (frames must have its size). A tracker holds the previous frame's digest
    (the stale test) and the counts (:attr:`frames`, :attr:`dropouts` by
    reason, :attr:`other_ids`: frames showing each other id of the family);
    use one per camera stream.
    """

    def __init__(self, intrinsics: Intrinsics, settings: TrackerSettings = TrackerSettings()) -> None:
        self.settings = check_tracker_settings(settings)
        self.intrinsics = check_intrinsics(*intrinsics)
        parameters = cv2.aruco.DetectorParameters()
        parameters.cornerRefinementMethod = _CORNER_REFINE[settings.corner_refine]
        self._detector = cv2.aruco.ArucoDetector(tag_dictionary(settings.family), parameters)
        h = settings.edge / 2.0
        # IPPE_SQUARE's required object points, in the order ArUco returns the corners
        self._object = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        self._shift = APRILTAG_PIXEL_SHIFT if settings.corner_refine == "apriltag" else 0.0
        self._previous: bytes | None = None
        self.frames = 0  # frames seen
        self.dropouts: Counter[str] = Counter()  # dropouts by reason code
        self.other_ids: Counter[int] = Counter()  # ids of the family detected that are not tag_id -> frames

    def reset(self) -> None:
        """Forget the previous frame and zero the counts."""
        self._previous = None
        self.frames = 0
        self.dropouts.clear()
        self.other_ids.clear()

    def track(self, frame: np.ndarray, t: float) -> TagPose:
        """One frame ``(H, W)`` grey or ``(H, W, 3)`` colour uint8, captured at ``t`` (s) -> :class:`TagPose`.

        Colour is RGB or BGR alike (only its grey level is used). A frame of
        another size than the intrinsics', another dtype, or a non-finite
        ``t`` raises ``ValueError`` (a misconfigured source, not a dropout).
        """
        start = time.perf_counter()
        frame = np.asarray(frame)
        w, h = self.intrinsics.width, self.intrinsics.height
        if frame.dtype != np.uint8 or frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] != 3):
            raise ValueError(f"frame: expected (H, W) or (H, W, 3) uint8, got {frame.dtype} {frame.shape}")
        if frame.shape[:2] != (h, w):
            raise ValueError(f"frame: {frame.shape[1]}x{frame.shape[0]} pixels, but the intrinsics are for {w}x{h}")
        if not math.isfinite(t):
            raise ValueError(f"capture time: expected a finite number of seconds, got {t!r}")
        self.frames += 1
        digest = hashlib.blake2b(np.ascontiguousarray(frame).data, digest_size=16).digest()
        stale = digest == self._previous
        self._previous = digest
        if stale:
            return self._dropout(t, "stale", start, stale=True)
        gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
        corners, ids, _ = self._detector.detectMarkers(gray)
        ids = np.zeros(0, dtype=int) if ids is None else np.asarray(ids).reshape(-1)
        self.other_ids.update({int(i) for i in ids if i != self.settings.tag_id})  # a wrong --tag id says so
        found = [np.asarray(c, dtype=np.float64).reshape(4, 2) - self._shift for c, i in zip(corners, ids)
                 if i == self.settings.tag_id]
        if not found:
            # the brightest 4x4 patch against the darkest: a dark, washed-out or covered frame (read noise
            # averages out; a small tag in a dark scene still counts as contrast)
            patches = cv2.resize(gray, (max(1, w // 4), max(1, h // 4)), interpolation=cv2.INTER_AREA)
            spread = float(patches.max()) - float(patches.min())
            return self._dropout(t, "low_contrast" if spread < self.settings.min_contrast else "no_tag", start)
        if len(found) > 1:
            return self._dropout(t, "duplicate", start, corners=found[0])
        c = found[0]
        m = self.settings.border_margin
        if (c[:, 0] < m).any() or (c[:, 1] < m).any() or (c[:, 0] > w - 1 - m).any() or (c[:, 1] > h - 1 - m).any():
            return self._dropout(t, "border", start, corners=c)
        position, quaternion, reprojection, ambiguity = self._pose(c)
        if not reprojection <= self.settings.max_reprojection:
            return self._dropout(t, "reprojection", start, corners=c, reprojection=reprojection, ambiguity=ambiguity)
        rotation_ok = ambiguity <= self.settings.max_ambiguity
        if self.settings.rotation and not rotation_ok:
            return self._dropout(t, "ambiguous", start, corners=c, reprojection=reprojection, ambiguity=ambiguity)
        return TagPose(float(t), position, quaternion, True, "", bool(rotation_ok), float(ambiguity),
                       float(reprojection), c, False, time.perf_counter() - start)

    def track_source(self, source: Iterable[tuple[np.ndarray, float]]) -> Iterator[TagPose]:
        """:meth:`track` each ``(frame, capture_time)`` a source yields."""
        for frame, t in source:
            yield self.track(frame, t)

    def _pose(self, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
        """IPPE on the four corners: position (3,) m, quaternion (4,) wxyz, RMS error (px), ambiguity."""
        n, rvecs, tvecs, errors = cv2.solvePnPGeneric(self._object, corners, self.intrinsics.K, self.intrinsics.dist,
                                                      flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if n < 1:
            return np.full(3, np.nan), np.full(4, np.nan), math.inf, 1.0
        errors = np.asarray(errors, dtype=np.float64).reshape(-1)
        best = int(np.argmin(errors[:n]))
        if n > 1:
            second = float(np.min(np.delete(errors[:n], best)))
            ambiguity = float(errors[best] / second) if second > 0 else 1.0
        else:
            ambiguity = 0.0
        R, _ = cv2.Rodrigues(np.asarray(rvecs[best], dtype=np.float64))
        quaternion = np.empty(4)
        mujoco.mju_mat2Quat(quaternion, R.reshape(-1))
        if quaternion[0] < 0:
            quaternion = -quaternion
        return np.asarray(tvecs[best], dtype=np.float64).reshape(3), quaternion, float(errors[best]), ambiguity

    def _dropout(self, t: float, reason: str, start: float, *, stale: bool = False, corners: Any = None,
                 reprojection: float = math.nan, ambiguity: float = math.nan) -> TagPose:
        self.dropouts[reason] += 1
        corners = np.full((4, 2), np.nan) if corners is None else corners
        return TagPose(float(t), np.full(3, np.nan), np.full(4, np.nan), False, reason, False, float(ambiguity),
                       float(reprojection), corners, stale, time.perf_counter() - start)


def pose_columns(poses: Sequence[TagPose]) -> dict[str, np.ndarray]:
    """The poses as the columns :data:`POSE_COLUMNS` (1-D float64 arrays, ``valid`` bool), as ``read_log`` takes."""
    rows = np.array([p.row() for p in poses], dtype=np.float64).reshape(-1, len(POSE_COLUMNS))
    columns: dict[str, np.ndarray] = {name: rows[:, k].copy() for k, name in enumerate(POSE_COLUMNS)}
    columns["valid"] = columns["valid"] > 0.5
    return columns
