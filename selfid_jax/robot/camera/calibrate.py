"""Camera calibration from checkerboard views: OpenCV's corner finder and ``calibrateCamera``, nothing of our own.

:func:`calibrate` finds the board in each image (``cv2.findChessboardCorners``
then ``cv2.cornerSubPix``), fits the pinhole model with OpenCV's 5-number
distortion (``cv2.calibrateCamera``) and returns the
:class:`~selfid_jax.robot.camera.intrinsics.Intrinsics`, the RMS reprojection
error and which images were used. Write the result with
:func:`~selfid_jax.robot.camera.intrinsics.write_intrinsics`.

The board is ``(cols, rows, square_m)``: ``cols x rows`` *inner* corners, as
OpenCV counts them (a board of 10 x 7 squares has 9 x 6 inner corners), and
the edge of a square in metres (it scales the extrinsics only; the
intrinsics do not depend on it). :func:`parse_board` reads the command line's
``checkerboard:COLSxROWS:SQUARE_M``; :func:`calibrate_path` calibrates from a
folder of images or a video (``selfid-jax calibrate``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from selfid_jax.robot.camera.intrinsics import Intrinsics, check_intrinsics

__all__ = ["BOARD_KINDS", "Calibration", "CalibrationError", "MAX_IMAGES", "MIN_VIEWS", "calibrate",
           "calibrate_path", "parse_board"]

#: The fewest views with the board found that :func:`calibrate` accepts by default.
MIN_VIEWS = 6
#: :func:`calibrate_path` uses at most this many images by default, evenly spaced (a video holds hundreds of
#: nearly equal frames; OpenCV's fit takes each view's corners, so more add time, not information).
MAX_IMAGES = 60
#: Calibration targets :func:`parse_board` reads.
BOARD_KINDS = ("checkerboard",)
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)


class CalibrationError(ValueError):
    """Calibration cannot proceed: no images, images of different sizes, too few views with the board."""


class Calibration(NamedTuple):
    """Output of :func:`calibrate`."""

    intrinsics: Intrinsics  # the camera at the images' resolution
    rms: float  # RMS reprojection error over every used corner, pixels
    used: np.ndarray  # (N,) bool: the board was found in image i (and the image was used)
    per_view_error: np.ndarray  # (N,) RMS reprojection error of each used view, pixels; NaN where unused
    names: tuple[str, ...]  # (N,) the images' names (given, or "image 0", "image 1", ...)


def _gray(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)):
        raise CalibrationError(f"{name}: expected an (H, W) or (H, W, 3) uint8 image, got {image.dtype} "
                               f"{image.shape}")
    if image.ndim == 2:
        return image
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY if image.shape[2] == 3 else cv2.COLOR_RGBA2GRAY)


def calibrate(images: Sequence[np.ndarray], board: tuple[int, int, float], *, names: Sequence[str] | None = None,
              min_views: int = MIN_VIEWS) -> Calibration:
    """Intrinsics from ``images`` (each ``(H, W)`` grey or ``(H, W, 3)`` RGB uint8, all one size) of a checkerboard.

    ``board = (cols, rows, square_m)``: inner corners as OpenCV counts them
    and the square's edge (m). ``names`` label the images in errors and in
    :attr:`Calibration.names` (file names, say). Raises :class:`CalibrationError`
    when there is no image, the sizes differ, or the board is found in fewer
    than ``min_views`` images (naming those where it was not).
    """
    cols, rows, square = board
    if isinstance(cols, bool) or isinstance(rows, bool) or not isinstance(cols, (int, np.integer)) \
            or not isinstance(rows, (int, np.integer)) or cols < 2 or rows < 2:
        raise CalibrationError(f"board: expected (cols, rows, square_m) with at least 2 x 2 inner corners, "
                               f"got {board!r}")
    if not (math.isfinite(float(square)) and float(square) > 0):
        raise CalibrationError(f"board: square_m must be a length > 0 in metres, got {square!r}")
    images = list(images)
    if not images:
        raise CalibrationError("calibrate: no image given")
    names = tuple(names) if names is not None else tuple(f"image {i}" for i in range(len(images)))
    if len(names) != len(images):
        raise CalibrationError(f"calibrate: {len(names)} names for {len(images)} images")
    grays = [_gray(img, name) for img, name in zip(images, names)]
    size = grays[0].shape
    for gray, name in zip(grays, names):
        if gray.shape != size:
            raise CalibrationError(f"{name}: {gray.shape[1]}x{gray.shape[0]} pixels, but {names[0]} is "
                                   f"{size[1]}x{size[0]} (one camera, one resolution)")
    pattern = (int(cols), int(rows))
    obj = np.zeros((pattern[0] * pattern[1], 3), np.float32)
    obj[:, :2] = np.mgrid[0:pattern[0], 0:pattern[1]].T.reshape(-1, 2) * float(square)
    object_points, image_points, used = [], [], np.zeros(len(grays), dtype=bool)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE
    for i, gray in enumerate(grays):
        found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
        if not found:
            continue
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), _SUBPIX_CRITERIA)
        object_points.append(obj)
        image_points.append(corners)
        used[i] = True
    if used.sum() < min_views:
        missing = [name for name, u in zip(names, used) if not u]
        raise CalibrationError(f"calibrate: the {cols}x{rows} board (inner corners) was found in {int(used.sum())} "
                               f"of {len(grays)} images, fewer than {min_views}; not found in: {', '.join(missing)}")
    h, w = size
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(object_points, image_points, (w, h), None, None)
    except cv2.error as err:  # degenerate views (all alike, the board edge-on): OpenCV's assertion, as one line
        detail = " ".join(str(err).split())[-200:]
        raise CalibrationError(f"calibrate: OpenCV's calibrateCamera failed on the {int(used.sum())} views with the "
                               f"board (vary their distance and tilt): {detail}") from None
    per_view = np.full(len(grays), np.nan)
    for k, i in enumerate(np.flatnonzero(used).tolist()):
        projected, _ = cv2.projectPoints(object_points[k], rvecs[k], tvecs[k], K, dist)
        residual = projected.reshape(-1, 2) - image_points[k].reshape(-1, 2)  # (N, 1, 2) in OpenCV 4, (N, 2) in 5
        per_view[i] = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    return Calibration(check_intrinsics(K, dist, w, h, source="calibrate"), float(rms), used, per_view, names)


def parse_board(text: str) -> tuple[int, int, float]:
    """``"checkerboard:COLSxROWS:SQUARE_M"`` (e.g. ``"checkerboard:9x6:0.025"``: inner corners, as OpenCV counts
    them, and the square's edge in m) -> ``(cols, rows, square_m)``; :class:`CalibrationError` naming ``--board``."""
    form = ("--board: expected checkerboard:COLSxROWS:SQUARE_M (inner corners as OpenCV counts them, the square's "
            f"edge in metres), e.g. checkerboard:9x6:0.025, got {text!r}")
    parts = [p.strip() for p in str(text).split(":")]
    if len(parts) != 3 or parts[0] not in BOARD_KINDS:
        raise CalibrationError(form)
    size = parts[1].lower().split("x")
    try:
        cols, rows = (int(v) for v in size) if len(size) == 2 else (0, 0)
        square = float(parts[2])
    except ValueError:
        raise CalibrationError(form) from None
    if cols < 2 or rows < 2 or not (math.isfinite(square) and square > 0):
        raise CalibrationError(form)
    return cols, rows, square


def calibrate_path(path: str | Path, board: tuple[int, int, float], *, max_images: int | None = MAX_IMAGES,
                   min_views: int = MIN_VIEWS) -> Calibration:
    """:func:`calibrate` from a folder of images (sorted by file name) or a video's frames
    (:func:`selfid_jax.robot.camera.sources.read_images`), at most ``max_images`` of them, evenly spaced (None: all).

    The names in :attr:`Calibration.names` are the file names (``VIDEO frame k`` for a video). Raises
    :class:`CalibrationError` (as :func:`calibrate`) or :class:`~selfid_jax.robot.log.LogError` for a missing,
    unreadable or empty source.
    """
    from selfid_jax.robot.camera.sources import read_images

    if max_images is not None and max_images < min_views:
        raise CalibrationError(f"max_images (--max-images): {max_images} is fewer than the {min_views} views needed")
    images, names = read_images(path, max_images=max_images)
    return calibrate(images, board, names=names, min_views=min_views)
