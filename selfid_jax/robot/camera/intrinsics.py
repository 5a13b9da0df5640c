"""Camera intrinsics files: OpenCV's calibration YAML and ROS's camera_info YAML in, OpenCV's (or ROS's) out.

Two formats, told apart by their text:

* **OpenCV** (what ``cv2.FileStorage`` writes: a ``%YAML:1.0`` (OpenCV 4) or
  ``%YAML 1.2`` (OpenCV 5) line and ``!!opencv-matrix`` nodes; read with ``cv2.FileStorage``, not parsed by hand):
  ``camera_matrix`` (3x3), ``distortion_coefficients`` (1xk or kx1),
  ``image_width``, ``image_height`` (pixels).
* **ROS** (``camera_calibration_parsers``' camera_info YAML, read with
  ``yaml.safe_load``): ``image_width``, ``image_height``,
  ``camera_matrix: {rows: 3, cols: 3, data: [9 numbers]}``,
  ``distortion_coefficients: {rows: 1, cols: k, data: [...]}`` and
  ``distortion_model`` (``plumb_bob`` or ``rational_polynomial``; the fisheye
  ``equidistant`` model is refused, it is not the pinhole model ``cv2.solvePnP``
  uses); ``rectification_matrix`` and ``projection_matrix`` are ignored on
  reading (the tracker works on raw, distorted frames).

The distortion is OpenCV's: ``k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]``
(4, 5, 8, 12 or 14 numbers). A file that cannot be used raises
:class:`IntrinsicsError`, one line naming the file and the key.
:func:`camera_info_intrinsics` reads the same fields from a bag's
``sensor_msgs/CameraInfo`` message.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
import yaml

__all__ = ["DISTORTION_SIZES", "FORMATS", "Intrinsics", "IntrinsicsError", "camera_info_intrinsics", "check_intrinsics",
           "read_intrinsics", "write_intrinsics"]

#: The lengths of OpenCV's distortion vector.
DISTORTION_SIZES = (4, 5, 8, 12, 14)
#: The file formats :func:`write_intrinsics` writes (and :func:`read_intrinsics` recognises).
FORMATS = ("opencv", "ros")
_ROS_MODELS = {"plumb_bob": (5,), "rational_polynomial": (8, 12, 14), "": DISTORTION_SIZES}
_KEYS = ("camera_matrix", "distortion_coefficients", "image_width", "image_height")


class IntrinsicsError(ValueError):
    """An intrinsics file or value that cannot be used; the one-line message names the file and the key."""


class Intrinsics(NamedTuple):
    """A pinhole camera with OpenCV's distortion model, at the resolution it was calibrated at."""

    K: np.ndarray  # (3, 3) float64 camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]], pixels
    dist: np.ndarray  # (k,) float64 distortion coefficients, k in DISTORTION_SIZES (zeros: none)
    width: int  # image width, pixels
    height: int  # image height, pixels


def check_intrinsics(K: Any, dist: Any, width: Any, height: Any, *, source: str = "intrinsics") -> Intrinsics:
    """Validate and copy the parts of an :class:`Intrinsics` (``K (3, 3)``, ``dist (k,)``, size in pixels).

    ``source`` prefixes every error (a file name). Refused: a non-finite or
    non-positive focal length, a last row other than ``[0, 0, 1]``, a
    principal point outside the image, a distortion of another length than
    :data:`DISTORTION_SIZES` or not finite, a size that is not a positive integer.
    """
    try:
        K = np.array(K, dtype=np.float64)
        dist = np.array(dist, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as err:
        raise IntrinsicsError(f"{source}: camera_matrix and distortion_coefficients must be numbers ({err})") from None
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise IntrinsicsError(f"{source}: camera_matrix must be a finite 3x3 matrix, got shape {K.shape}")
    if not np.allclose(K[2], (0.0, 0.0, 1.0)) or K[1, 0] != 0.0:
        raise IntrinsicsError(f"{source}: camera_matrix must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], "
                              f"got {K.tolist()}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise IntrinsicsError(f"{source}: camera_matrix focal lengths fx, fy must be > 0, got {K[0, 0]}, {K[1, 1]}")
    if dist.size not in DISTORTION_SIZES or not np.isfinite(dist).all():
        raise IntrinsicsError(f"{source}: distortion_coefficients must be {DISTORTION_SIZES} finite numbers "
                              f"(OpenCV's k1, k2, p1, p2[, k3, ...]), got {dist.size}")
    sizes = []
    for key, value in (("image_width", width), ("image_height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer, float)) or value != int(value) \
                or value <= 0:
            raise IntrinsicsError(f"{source}: {key} must be a positive whole number of pixels, got {value!r}")
        sizes.append(int(value))
    w, h = sizes
    if not (0 <= K[0, 2] <= w and 0 <= K[1, 2] <= h):
        raise IntrinsicsError(f"{source}: the principal point ({K[0, 2]}, {K[1, 2]}) is outside the {w}x{h} image "
                              "(a camera_matrix for another resolution?)")
    return Intrinsics(K, dist, w, h)


def read_intrinsics(path: str | Path) -> Intrinsics:
    """Read OpenCV's calibration YAML or ROS's camera_info YAML (told apart by the text) into :class:`Intrinsics`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        raise IntrinsicsError(f"{path}: cannot read the intrinsics file ({err.strerror or err})") from None
    if text.lstrip().startswith("%YAML") or "!!opencv-matrix" in text:
        return _read_opencv(path)
    return _read_ros(path, text)


def write_intrinsics(path: str | Path, intrinsics: Intrinsics, *, format: str = "opencv",
                     camera_name: str = "camera") -> Path:
    """Write ``intrinsics`` as OpenCV's calibration YAML (``cv2.FileStorage``) or ROS's camera_info YAML.

    ``camera_name`` is written to the ROS format only. Returns the path.
    """
    if format not in FORMATS:
        raise ValueError(f"format: expected one of {FORMATS}, got {format!r}")
    path = Path(path)
    K, dist, w, h = check_intrinsics(*intrinsics, source=str(path))
    if format == "opencv":
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise IntrinsicsError(f"{path}: cannot open for writing")
        try:
            fs.write("image_width", w)
            fs.write("image_height", h)
            fs.write("camera_matrix", K)
            fs.write("distortion_coefficients", dist.reshape(1, -1))
        finally:
            fs.release()
        return path
    coefficients = _pad_distortion(dist)
    P = np.zeros((3, 4))
    P[:, :3] = K
    doc = {
        "image_width": w, "image_height": h, "camera_name": camera_name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": [float(x) for x in K.reshape(-1)]},
        "distortion_model": "plumb_bob" if coefficients.size == 5 else "rational_polynomial",
        "distortion_coefficients": {"rows": 1, "cols": int(coefficients.size),
                                    "data": [float(x) for x in coefficients]},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": [float(x) for x in np.eye(3).reshape(-1)]},
        "projection_matrix": {"rows": 3, "cols": 4, "data": [float(x) for x in P.reshape(-1)]},
    }
    try:
        path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    except OSError as err:
        raise IntrinsicsError(f"{path}: cannot write ({err.strerror or err})") from None
    return path


def _pad_distortion(dist: np.ndarray) -> np.ndarray:
    """ROS's plumb_bob has 5 numbers (k3 = 0 where OpenCV's has 4); rational_polynomial keeps OpenCV's."""
    return np.concatenate([dist, np.zeros(1)]) if dist.size == 4 else dist


def _read_opencv(path: Path) -> Intrinsics:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:  # OpenCV 5's binding reports a parse error as a SystemError
        cause = err.__cause__ or err.__context__ or err
        message = str(cause).strip().splitlines()[-1] if str(cause).strip() else type(cause).__name__
        raise IntrinsicsError(f"{path}: not a readable OpenCV YAML file ({message})") from None
    if not fs.isOpened():
        raise IntrinsicsError(f"{path}: not a readable OpenCV YAML file")
    try:
        nodes = {key: fs.getNode(key) for key in _KEYS}
        for key, node in nodes.items():
            if node.empty() or node.isNone():
                raise IntrinsicsError(f"{path}: key {key} is missing (an OpenCV calibration file has "
                                      f"{', '.join(_KEYS)})")
        values: dict[str, Any] = {}
        for key in ("camera_matrix", "distortion_coefficients"):
            matrix = nodes[key].mat()
            if matrix is None:
                raise IntrinsicsError(f"{path}: key {key} is not an !!opencv-matrix")
            values[key] = matrix
        for key in ("image_width", "image_height"):
            if not nodes[key].isInt():
                raise IntrinsicsError(f"{path}: key {key} must be a whole number of pixels")
            values[key] = int(nodes[key].real())
    finally:
        fs.release()
    return check_intrinsics(values["camera_matrix"], values["distortion_coefficients"], values["image_width"],
                            values["image_height"], source=str(path))


def _ros_matrix(path: Path, doc: dict, key: str, shape: tuple[int, int] | None) -> np.ndarray:
    node = doc.get(key)
    if node is None:
        raise IntrinsicsError(f"{path}: key {key} is missing (a ROS camera_info file has {', '.join(_KEYS)})")
    if not isinstance(node, dict) or "data" not in node:
        raise IntrinsicsError(f"{path}: key {key} must be a mapping {{rows, cols, data}}")
    try:
        data = np.asarray(node["data"], dtype=np.float64).reshape(-1)
        rows, cols = int(node.get("rows", 1)), int(node.get("cols", data.size))
    except (TypeError, ValueError):
        raise IntrinsicsError(f"{path}: key {key}: rows, cols and data must be numbers") from None
    if rows * cols != data.size:
        raise IntrinsicsError(f"{path}: key {key}: rows x cols = {rows} x {cols} but data has {data.size} numbers")
    if shape is not None and (rows, cols) != shape:
        raise IntrinsicsError(f"{path}: key {key} must be {shape[0]}x{shape[1]}, got {rows}x{cols}")
    return data.reshape(rows, cols)


def _read_ros(path: Path, text: str) -> Intrinsics:
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise IntrinsicsError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise IntrinsicsError(f"{path}: expected a mapping with keys {', '.join(_KEYS)} (OpenCV's or ROS's "
                              "calibration YAML)")
    K = _ros_matrix(path, doc, "camera_matrix", (3, 3))
    dist = _ros_matrix(path, doc, "distortion_coefficients", None).reshape(-1)
    model = str(doc.get("distortion_model", "") or "")
    _check_ros_model(model, dist, str(path), "distortion_coefficients")
    for key in ("image_width", "image_height"):
        if key not in doc:
            raise IntrinsicsError(f"{path}: key {key} is missing (a ROS camera_info file has {', '.join(_KEYS)})")
    return check_intrinsics(K, dist, doc["image_width"], doc["image_height"], source=str(path))


def _check_ros_model(model: str, dist: np.ndarray, source: str, key: str) -> None:
    if model not in _ROS_MODELS:
        raise IntrinsicsError(f"{source}: distortion_model {model!r} is not a pinhole model OpenCV's solvePnP "
                              f"uses; expected one of {sorted(m for m in _ROS_MODELS if m)}")
    if model and dist.size not in _ROS_MODELS[model]:
        raise IntrinsicsError(f"{source}: distortion_model {model} has {_ROS_MODELS[model]} coefficients, "
                              f"{key} has {dist.size}")


def camera_info_intrinsics(k: Any, d: Any, distortion_model: str, width: Any, height: Any, *,
                           source: str) -> Intrinsics:
    """:class:`Intrinsics` from the fields of a ``sensor_msgs/CameraInfo`` message (``k`` (9,) row-major, ``d``,
    ``distortion_model``, ``width``, ``height``), as a bag records it; ``source`` (the bag and topic) prefixes
    every error.

    An all-zero ``k`` (a driver publishing an uncalibrated camera) and a
    non-pinhole ``distortion_model`` are refused; an empty ``d`` is no distortion.
    """
    K = np.asarray(k, dtype=np.float64).reshape(-1)
    if K.size != 9:
        raise IntrinsicsError(f"{source}: k has {K.size} numbers, a camera matrix 9")
    if not K.any():
        raise IntrinsicsError(f"{source}: k is all zero: the camera driver publishes no calibration; calibrate the "
                              "camera (selfid-jax calibrate) and give the file")
    dist = np.asarray(d, dtype=np.float64).reshape(-1)
    if dist.size == 0:
        dist = np.zeros(5)
    _check_ros_model(str(distortion_model or ""), dist, source, "d")
    return check_intrinsics(K.reshape(3, 3), dist, int(width), int(height), source=source)
