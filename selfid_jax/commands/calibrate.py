"""``selfid-jax calibrate IMAGES``: a camera's intrinsics from checkerboard views, written as OpenCV's (or ROS's) YAML.

Usage::

    selfid-jax calibrate IMAGES --board checkerboard:COLSxROWS:SQUARE_M --out camera.yaml
                         [--format opencv|ros] [--max-images N]

IMAGES is a folder of images (sorted by file name) or a video. Parses the
flags, calls :func:`selfid_jax.robot.camera.calibrate.calibrate_path` (OpenCV's
corner finder and ``calibrateCamera``) and
:func:`selfid_jax.robot.camera.intrinsics.write_intrinsics`, and prints fx, fy,
cx, cy, the RMS reprojection error and which images were used. OpenCV is
imported inside :func:`run`, so the console script stays fast to start.
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["add_arguments", "command", "run"]

DESCRIPTION = (
    "Estimate a camera's intrinsics (focal lengths, principal point, OpenCV's 5-number distortion) from views of a "
    "printed checkerboard, with OpenCV's corner finder and calibrateCamera, and write them as the YAML that "
    "'selfid-jax fit --camera-info' reads. IMAGES is a folder of images (sorted by file name) or a video. Hold the "
    "board at several distances, tilted up to ~40 degrees, across the whole image; calibrate at the resolution "
    "you will track at. Needs the camera extra (pip install \"selfid-jax[camera]\")."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``calibrate`` subcommand's arguments (the library checks the values; OpenCV is not imported here)."""
    p.add_argument("images", type=Path, help="a folder of images (sorted by file name) or a video file")
    p.add_argument("--board", required=True, metavar="checkerboard:COLSxROWS:SQUARE_M",
                   help="the board: inner corners as OpenCV counts them (a board of 10 x 7 squares has 9x6) and the "
                   "square's edge in metres, e.g. checkerboard:9x6:0.025")
    p.add_argument("--out", type=Path, required=True, help="the intrinsics file to write, e.g. camera.yaml")
    p.add_argument("--format", default="opencv", metavar="opencv|ros",
                   help="opencv: cv2.FileStorage YAML (default); ros: camera_calibration_parsers' camera_info YAML")
    p.add_argument("--max-images", type=int, default=60, metavar="N",
                   help="use at most N images, evenly spaced (default 60; a video holds many near-equal frames)")


def run(args: argparse.Namespace) -> int:
    """Body of ``selfid-jax calibrate``: calibrate, write, print; bad input raises ``ConfigError`` (exit 2)."""
    from selfid_jax.runner.errors import ConfigError

    try:
        from selfid_jax.robot.camera.calibrate import calibrate_path, parse_board
        from selfid_jax.robot.camera.intrinsics import write_intrinsics
    except ImportError as err:  # cv2 missing
        raise ConfigError(f"calibrate needs OpenCV: pip install \"selfid-jax[camera]\" ({err})") from None
    try:
        board = parse_board(args.board)
        result = calibrate_path(args.images, board, max_images=args.max_images)
        written = write_intrinsics(args.out, result.intrinsics, format=args.format)
    except ValueError as err:  # CalibrationError, LogError, IntrinsicsError: one line naming the file or flag
        raise ConfigError(" ".join(str(err).split())) from None
    K, dist = result.intrinsics.K, result.intrinsics.dist
    used = [name for name, u in zip(result.names, result.used) if u]
    missed = [name for name, u in zip(result.names, result.used) if not u]
    cols, rows, square = board
    print(f"{args.images}: the {cols}x{rows} board ({square:g} m squares) found in {len(used)} of "
          f"{len(result.names)} images ({result.intrinsics.width}x{result.intrinsics.height})")
    print(f"fx {K[0, 0]:.2f}  fy {K[1, 1]:.2f}  cx {K[0, 2]:.2f}  cy {K[1, 2]:.2f}  (pixels)")
    print(f"distortion (k1, k2, p1, p2, k3): {', '.join(f'{d:.4g}' for d in dist)}")
    print(f"RMS reprojection error {result.rms:.3f} px")
    for name, error in zip(result.names, result.per_view_error):
        if error == error:  # used
            print(f"  used: {name} ({error:.3f} px)")
    if missed:
        print(f"  board not found in: {', '.join(missed)}")
    print(f"intrinsics ({args.format}): {written}")
    return 0


def command():
    """The ``calibrate`` subcommand for :func:`selfid_jax.runner.command_line.main`."""
    from selfid_jax.runner.command_line import Command

    return Command(help="a camera's intrinsics from checkerboard images or a video, for fit --camera-info",
                   description=DESCRIPTION, add_arguments=add_arguments, run=run)
