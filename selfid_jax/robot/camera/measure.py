"""Measuring the camera tracker on the simulated camera: error, bias, dropouts and latency per condition.

:func:`measure_tracker` places a free-floating tag before a simulated camera
(:class:`~selfid_jax.robot.camera.sim.SimCamera`), sweeps resolution,
distance and viewing angle, tracks ``frames`` rendered frames per condition
(each with the tag moved sideways and, by default, rolled at random, so that the corners
fall at different sub-pixel phases, and with the camera's read noise and
blur) and compares each pose with the simulator's ground truth. One
:class:`TrackerAccuracy` row per condition (``row._asdict()`` for a table);
these are the numbers the realism profile's tracker noise, bias and latency
are set from.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import mujoco
import numpy as np

from selfid_jax.robot.camera.render import CameraSettings, camera_rotation
from selfid_jax.robot.camera.sim import SimCamera
from selfid_jax.robot.camera.tracker import TagTracker, TrackerSettings

__all__ = ["TrackerAccuracy", "measure_tracker"]

_TAG_XML = """<mujoco><worldbody><body name="tag"><freejoint/>
<inertial pos="0 0 0" mass="0.01" diaginertia="1e-6 1e-6 1e-6"/></body></worldbody></mujoco>"""


class TrackerAccuracy(NamedTuple):
    """The tracker on one condition of :func:`measure_tracker` (errors over the frames with a pose)."""

    width: int  # image width, pixels
    height: int  # image height, pixels
    distance: float  # camera centre to tag centre, m
    angle: float  # tilt of the tag away from facing the camera, degrees
    roll: float  # the tag's roll about its normal, degrees; NaN: random per frame
    tag_px: float  # the tag's edge in the image when facing the camera, pixels (edge f / distance)
    frames: int  # frames tracked
    dropout_rate: float  # fraction of frames without a pose (any reason)
    dropouts: str  # reasons and counts, "no_tag:2 border:1" ("" when none)
    rotation_unreliable: float  # fraction of the poses whose planar ambiguity was not resolved
    position_rms_mm: float  # RMS of the position error's norm, mm
    position_max_mm: float  # largest position error, mm
    bias_x_mm: float  # mean position error along the camera's x (right), mm
    bias_y_mm: float  # mean position error along y (down), mm
    bias_z_mm: float  # mean position error along z (depth), mm
    angle_rms_deg: float  # RMS rotation error (angle of R_est R_true^T) over the reliable rotations, degrees
    latency_ms: float  # median wall time of detection and pose per frame, ms
    latency_max_ms: float  # largest of them, ms


def _rotation_angle(qa: np.ndarray, qb: np.ndarray) -> float:
    return math.degrees(2.0 * math.acos(min(1.0, abs(float(np.dot(qa, qb))))))


def measure_tracker(*, resolutions: Sequence[tuple[int, int]] = ((320, 240), (640, 480)),
                    distances: Sequence[float] = (0.5, 1.0), angles: Sequence[float] = (0.0, 45.0),
                    frames: int = 20, tag: TrackerSettings = TrackerSettings(edge=0.05),
                    camera: CameraSettings = CameraSettings(noise=2.0), roll: float | None = None,
                    seed: int = 0) -> list[TrackerAccuracy]:
    """Track ``frames`` rendered frames per (resolution, distance, angle) and compare with the ground truth.

    ``camera`` gives the optics and sensor (fovy, noise, blur, exposure; its
    resolution and pose are replaced: the camera sits at the origin looking
    along world +x). ``tag`` gives the family, id, edge (m) and the tracker's
    bounds. The tag's centre is put at ``distance`` (m) from the camera, moved
    sideways at random within the central half of the view, rolled about its
    normal by ``roll`` degrees (None: at random; 0: edges along the pixel rows
    and columns, the tracker's worst case, see
    :mod:`~selfid_jax.robot.camera.tracker`), and tilted by ``angle`` (degrees)
    about a random in-plane axis.
    Returns one :class:`TrackerAccuracy` per condition, resolutions outermost.
    """
    if frames < 1:
        raise ValueError(f"frames: expected at least 1, got {frames}")
    rng = np.random.default_rng(seed)
    rows = []
    for width, height in resolutions:
        settings = camera._replace(width=int(width), height=int(height), position=(0.0, 0.0, 0.0),
                                   look_at=(1.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), seed=int(rng.integers(2**31)))
        R_wc = camera_rotation(settings.position, settings.look_at, settings.up)
        facing = np.empty(4)  # tag frame facing the camera: x right, y up (-y_cam), z towards it (-z_cam)
        mujoco.mju_mat2Quat(facing, (R_wc @ np.diag([1.0, -1.0, -1.0])).reshape(-1))
        with SimCamera(_TAG_XML, "tag", tag=tag, camera=settings) as sim:
            f = sim.intrinsics.K[1, 1]
            half_h = 0.5 * height / f  # tan of half the field of view
            half_w = 0.5 * width / f
            for distance in distances:
                for angle in angles:
                    tracker = TagTracker(sim.intrinsics, tag)
                    errors, angle_errors, latencies, unreliable = [], [], [], 0
                    for k in range(frames):
                        lateral = rng.uniform(-0.25, 0.25, size=2) * np.array([half_w, half_h]) * distance
                        position = R_wc @ np.array([lateral[0], lateral[1], distance])
                        axis = rng.uniform(0, 2 * np.pi)
                        tilt, rolled, q = np.empty(4), np.empty(4), np.empty(4)
                        mujoco.mju_axisAngle2Quat(tilt, np.array([np.cos(axis), np.sin(axis), 0.0]),
                                                  math.radians(angle))
                        spin = rng.uniform(-np.pi, np.pi) if roll is None else math.radians(roll)
                        mujoco.mju_axisAngle2Quat(rolled, np.array([0.0, 0.0, 1.0]), spin)
                        mujoco.mju_mulQuat(q, facing, tilt)
                        mujoco.mju_mulQuat(q, q.copy(), rolled)
                        qpos = np.concatenate([position, q])
                        pose = tracker.track(sim.render(qpos), float(k))
                        latencies.append(pose.latency)
                        if not pose.valid:
                            continue
                        truth = sim.truth(qpos)
                        errors.append(pose.position - truth.position)
                        if pose.rotation_ok:
                            angle_errors.append(_rotation_angle(pose.quaternion, truth.quaternion))
                        else:
                            unreliable += 1
                    rows.append(_row(width, height, distance, angle, math.nan if roll is None else float(roll),
                                     tag.edge * f / distance, frames, tracker, errors, angle_errors, latencies,
                                     unreliable))
    return rows


def _row(width: int, height: int, distance: float, angle: float, roll: float, tag_px: float, frames: int,
         tracker: TagTracker,
         errors: list[np.ndarray], angle_errors: list[float], latencies: list[float],
         unreliable: int) -> TrackerAccuracy:
    e = np.array(errors, dtype=np.float64).reshape(-1, 3) * 1e3
    norms = np.linalg.norm(e, axis=1)
    nan = math.nan
    bias = e.mean(axis=0) if len(e) else np.full(3, nan)
    dropouts = " ".join(f"{reason}:{count}" for reason, count in sorted(tracker.dropouts.items()))
    return TrackerAccuracy(
        int(width), int(height), float(distance), float(angle), roll, float(tag_px), int(frames),
        float(sum(tracker.dropouts.values()) / frames), dropouts,
        float(unreliable / len(e)) if len(e) else nan,
        float(np.sqrt(np.mean(norms**2))) if len(e) else nan, float(norms.max()) if len(e) else nan,
        float(bias[0]), float(bias[1]), float(bias[2]),
        float(np.sqrt(np.mean(np.square(angle_errors)))) if angle_errors else nan,
        float(np.median(latencies) * 1e3), float(np.max(latencies) * 1e3))
