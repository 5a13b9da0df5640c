"""The gap study's tracker noise per robot, measured on a simulated camera like the paper's (issue 53 item 3).

The paper tracks each robot's point of manipulation with an AprilTag and an external camera (seed 000, Sec. V,
Fig. 4a) and states nothing else about the camera: not its resolution, field of view, distance or the tag's size.
Those are our assumptions, one camera per robot's scale (:data:`CAMERAS`), each stated with its reason. For each,
:func:`measure` renders the tag before that camera (:func:`selfid_jax.robot.camera.measure.measure_tracker`: the tag
moved sideways within the central half of the view, rolled at random, tilted by each of :data:`ANGLES`, read noise
of 2 grey levels) and tracks it with the library's tracker against the simulator's ground truth.

The gap configs' tracker noise is one number, ``realism.noise_pos``: the standard deviation per axis [m] of an
isotropic Gaussian added to each tracked position. The camera's error is neither isotropic (most of it is depth)
nor zero-mean (a small bias), so :func:`per_axis_sd` turns a measured condition into the isotropic sd with the
same total variance about the mean, ``sqrt((RMS^2 - |bias|^2) / 3)``, and the robot's value is the root mean square
over the tilts. :data:`NOISE_POS` holds the values the configs use, rounded to 0.01 mm; ``main`` prints the
measurement beside them and exits 1 if a value no longer rounds to the one in the configs.

    MUJOCO_GL=egl python scripts/gap_camera_noise.py [--frames 40]

Rendering needs an OpenGL backend (``MUJOCO_GL=egl``); about a minute on 2 shared cores.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import NamedTuple

#: Tilts of the tag away from facing the camera [deg]: a tag on a moving body does not always face it.
ANGLES = (0.0, 30.0)
FRAMES = 40  # rendered frames per (camera, tilt)
SEED = 0


class Camera(NamedTuple):
    """One robot's assumed camera and tag (none of it is stated by the paper)."""

    width: int  # pixels
    height: int  # pixels
    fovy: float  # vertical field of view, degrees
    distance: float  # camera centre to the tag, m
    edge: float  # the tag's black square, m
    why: str  # the reason for these values


#: One camera per robot scale. The arm's camera must see the 150 mm cube (and the 50 mm star, and the peg's
#: layouts) with room to spare; the hands' camera sees a hand-held object a few cm across.
CAMERAS = {
    "ur5e": Camera(1280, 720, 45.0, 0.75, 0.05,
                   "a 1280x720 camera with a 45 deg vertical field of view (f = 869 px) 0.75 m from a 50 mm tag on "
                   "the UR5e's flange (63 mm across): the view there is 0.62 m x 1.10 m, room for the 150 mm cube "
                   "and the peg's layouts; the tag is 58 px across"),
    "hand": Camera(1280, 720, 45.0, 0.30, 0.02,
                   "the same camera 0.30 m from a 20 mm tag on the grasped object (the paper's objects are a few cm "
                   "across, Fig. 4b): the view there is 0.25 m x 0.44 m; the tag is 58 px across"),
}
#: Which camera each gap config's robot sees through. The peg-in-hole run has one noise level for the arm and the
#: hand; its table reports the arm's waypoint error, so it takes the arm's camera.
ROBOTS = {
    "gap_valid_region_ur5e": "ur5e",
    "gap_tracking_ur5e_cube": "ur5e",
    "gap_peg_in_hole": "ur5e",
    "gap_tracking_model_o_grablab": "hand",
    "gap_tracking_stewart_e": "hand",
}
#: ``realism.noise_pos`` [m] per camera as measured by :func:`measure` (``FRAMES`` frames, seed ``SEED``), rounded
#: to 0.01 mm; the gap configs' nonzero noise level.
NOISE_POS = {"ur5e": 0.00037, "hand": 0.00015}


def camera_table() -> str:
    """The assumed cameras, which gap configs see through each, and the noise level measured for each, Markdown."""
    lines = ["| camera | resolution, vertical field of view | distance | tag edge | tag in the image | "
             "noise_pos (measured, per axis) | gap configs |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, c in CAMERAS.items():
        f = 0.5 * c.height / math.tan(math.radians(c.fovy) / 2)
        configs = ", ".join(f"`{k}`" for k, v in ROBOTS.items() if v == name)
        lines.append(f"| {name} | {c.width}x{c.height}, {c.fovy:g} deg | {c.distance:g} m | {1e3 * c.edge:g} mm | "
                     f"{c.edge * f / c.distance:.0f} px | {1e3 * NOISE_POS[name]:.2f} mm | {configs} |")
    return "\n".join(lines)


def per_axis_sd(position_rms_mm: float, bias_mm: tuple[float, float, float]) -> float:
    """The isotropic per-axis sd [mm] with the same total variance about the mean as a measured condition:
    ``sqrt((rms^2 - |bias|^2) / 3)`` from the RMS of the error's norm and its mean per axis (both mm)."""
    var = position_rms_mm ** 2 - sum(b * b for b in bias_mm)
    return math.sqrt(max(var, 0.0) / 3.0)


def measure(camera: Camera, *, frames: int = FRAMES, seed: int = SEED) -> tuple[float, list]:
    """``(sd_mm, rows)``: the per-axis sd [mm] (RMS of :func:`per_axis_sd` over :data:`ANGLES`) and the
    :class:`~selfid_jax.robot.camera.measure.TrackerAccuracy` rows it comes from."""
    from selfid_jax.robot.camera.measure import measure_tracker
    from selfid_jax.robot.camera.render import CameraSettings
    from selfid_jax.robot.camera.tracker import TrackerSettings

    rows = measure_tracker(resolutions=((camera.width, camera.height),), distances=(camera.distance,),
                           angles=ANGLES, frames=frames, tag=TrackerSettings(edge=camera.edge),
                           camera=CameraSettings(fovy=camera.fovy, noise=2.0), seed=seed)
    sds = [per_axis_sd(r.position_rms_mm, (r.bias_x_mm, r.bias_y_mm, r.bias_z_mm)) for r in rows]
    return math.sqrt(sum(s * s for s in sds) / len(sds)), rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=FRAMES, help=f"frames per tilt (default {FRAMES})")
    args = ap.parse_args()
    if args.frames < 1:
        print(f"--frames: expected at least 1, got {args.frames}", file=sys.stderr)
        return 2
    print("| camera | assumptions | tilt (deg) | tag (px) | dropouts | position RMS (mm) | bias x / y / z (mm) | "
          "per-axis sd (mm) |")
    print("|---|---|---|---|---|---|---|---|")
    measured = {}
    for name, cam in CAMERAS.items():
        sd, rows = measure(cam, frames=args.frames)
        measured[name] = sd
        for r in rows:
            print(f"| {name} | {cam.width}x{cam.height}, {cam.fovy:g} deg, {cam.distance:g} m, "
                  f"{1e3 * cam.edge:g} mm tag | {r.angle:g} | {r.tag_px:.0f} | {100 * r.dropout_rate:.0f} % | "
                  f"{r.position_rms_mm:.2f} | {r.bias_x_mm:+.2f} / {r.bias_y_mm:+.2f} / {r.bias_z_mm:+.2f} | "
                  f"{per_axis_sd(r.position_rms_mm, (r.bias_x_mm, r.bias_y_mm, r.bias_z_mm)):.3f} |")
    print()
    stale = []
    for name, sd in measured.items():
        rounded = round(sd * 1e-3, 5)
        print(f"{name}: noise_pos {sd:.3f} mm per axis -> {rounded:g} m (configs: {NOISE_POS[name]:g} m)")
        if not math.isclose(rounded, NOISE_POS[name], abs_tol=1e-9):
            stale.append(name)
    for config, camera in ROBOTS.items():
        print(f"  configs/studies/gap/{config}.yaml: noise_pos [0.0, {NOISE_POS[camera]:g}]  ({camera} camera)")
    if stale:
        print(f"the measurement no longer gives NOISE_POS for {', '.join(stale)}: update NOISE_POS and the configs",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
