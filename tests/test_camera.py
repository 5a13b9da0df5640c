"""The camera tracker on frames the simulated camera renders (MuJoCo headless, EGL), against its ground truth.

The arm is tests/helpers_camera.py's (3 hinges, a tag on the hand), not one the project ships. Rendering tests skip,
with the reason, only where no OpenGL context can be created. Bounds (640x480, fovy 45, a 50 mm tag at about 0.7 m, i.e.
about 42 px, read noise 2 grey levels): position within POSITION_TOL, rotation within ANGLE_TOL where the planar
ambiguity is resolved; measured (Mesa's EGL, software) at most 0.5 mm and 0.65 deg. The self-ID check's
||J J_hat - I||_F was 0.04-0.08 over three seeds (bound SELFID_TOL); the calibrated focal length within 0.04 %.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers_camera import CAMERA, Q0, TAG, open_sim  # tests/ is on the path

from selfid_jax.robot.camera.calibrate import CalibrationError, calibrate
from selfid_jax.robot.camera.intrinsics import Intrinsics, IntrinsicsError, read_intrinsics, write_intrinsics
from selfid_jax.robot.camera.measure import measure_tracker
from selfid_jax.robot.camera.render import RenderUnavailable, apply_sensor
from selfid_jax.robot.camera.sim import BoardCamera, board_views
from selfid_jax.robot.camera.tracker import (
    POSE_COLUMNS,
    TagTracker,
    TrackerSettings,
    pose_columns,
)

POSITION_TOL = 2e-3  # m, tag centre vs the simulator's, per frame
ANGLE_TOL = 2.0  # deg, per frame with rotation_ok
CORNER_OFFSET_TOL = 0.2  # px, mean detected-minus-projected corner over frames (the half-pixel convention)
FOCAL_TOL = 0.01  # relative, calibrated fx, fy vs the MuJoCo camera's
SELFID_TOL = 0.15  # ||J J_hat - I||_F, position task


@pytest.fixture(scope="module")
def sim():
    camera = open_sim(CAMERA)
    yield camera
    camera.close()


def _angle_deg(qa, qb):
    return np.degrees(2 * np.arccos(min(1.0, abs(float(np.dot(qa, qb))))))


def _configurations(n, seed=0, spread=0.25):
    rng = np.random.default_rng(seed)
    return [Q0 + rng.uniform(-spread, spread, size=3) for _ in range(n)]


@pytest.mark.slow
def test_tracker_recovers_the_pose(sim):
    tracker = TagTracker(sim.intrinsics, TAG)
    h = TAG.edge / 2
    square = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    offsets, angles = [], []
    for k, q in enumerate(_configurations(8)):
        pose = tracker.track(sim.render(q), 0.1 * k)
        truth = sim.truth(q)
        assert pose.valid, pose.reason
        assert pose.reason == "" and not pose.stale and pose.latency > 0
        assert np.linalg.norm(pose.position - truth.position) < POSITION_TOL
        assert pose.reprojection < TAG.max_reprojection and 0 <= pose.ambiguity <= 1
        if pose.rotation_ok:
            angles.append(_angle_deg(pose.quaternion, truth.quaternion))
        corners = (truth.rotation @ square.T).T + truth.position
        uv = (sim.intrinsics.K @ corners.T).T
        offsets.append((pose.corners - uv[:, :2] / uv[:, 2:]).mean(axis=0))
    assert len(angles) >= 4 and max(angles) < ANGLE_TOL
    # OpenCV's AprilTag refinement counts pixel centres at 0.5; the tracker's shift must keep corners unbiased
    assert np.all(np.abs(np.mean(offsets, axis=0)) < CORNER_OFFSET_TOL)
    assert tracker.frames == 8 and sum(tracker.dropouts.values()) == 0


@pytest.mark.slow
def test_pose_rows_feed_the_log_reader(sim):
    from selfid_jax.robot.log import samples_from_table

    tracker = TagTracker(sim.intrinsics, TAG)
    qs = _configurations(5, seed=1, spread=0.03)
    poses = list(tracker.track_source(sim.frames(qs, [0.1 * k for k in range(5)])))
    blank = np.full((CAMERA.height, CAMERA.width, 3), 90, np.uint8)
    poses.insert(2, tracker.track(blank, 0.15))  # a dropout row: NaN pose, dropped and counted by the reader
    qs.insert(2, qs[1])
    columns = pose_columns(poses)
    assert tuple(columns) == POSE_COLUMNS and columns["valid"].dtype == bool
    assert columns["valid"].tolist() == [True, True, False, True, True, True]
    assert np.isnan(columns["p_x"][2]) and poses[0].row()[0] == 0.0 and len(poses[0].row()) == 9
    table = {**columns, **{f"q_{i}": np.array([q[i] for q in qs]) for i in range(3)}}
    samples = samples_from_table(table, task="x,y,z", max_gap=None)
    assert samples.dtheta.shape == (4, 3) and np.isfinite(samples.V).all()  # 5 poses: 4 pairs
    assert [r.count for r in samples.rejected if "non-finite" in r.reason] == [1]  # the dropout row
    assert np.allclose(samples.V[0], poses[1].position - poses[0].position)


def _tag_box(pose, pad):
    x0, y0 = np.floor(pose.corners.min(axis=0) - pad).astype(int)
    x1, y1 = np.ceil(pose.corners.max(axis=0) + pad).astype(int)
    return x0, y0, x1, y1


@pytest.mark.slow
def test_dropouts_have_reasons(sim):
    frame = sim.render(Q0)
    tracker = TagTracker(sim.intrinsics, TAG)
    good = tracker.track(frame, 0.0)
    assert good.valid
    x0, y0, x1, y1 = _tag_box(good, pad=8)
    height, width = frame.shape[:2]

    no_tag = frame.copy()
    no_tag[y0:y1, x0:x1] = 120
    shift = x0 + 8 - 5  # the tag's leftmost corner about 5 px from the left border, its quiet zone kept
    at_border = np.zeros_like(frame)
    at_border[:, :width - shift] = frame[:, shift:]
    cut = np.zeros_like(frame)
    half = (x0 + x1) // 2
    cut[:, :width - half] = frame[:, half:]
    twice = frame.copy()
    dx = -(x1 - x0) - 40 if x0 - (x1 - x0) - 40 > 0 else (x1 - x0) + 40
    twice[y0:y1, x0 + dx:x1 + dx] = frame[y0:y1, x0:x1]
    blurred = cv2.GaussianBlur(frame, (0, 0), 6.0)
    dark = apply_sensor(frame, CAMERA._replace(exposure=0.04, noise=1.0), np.random.default_rng(0))

    cases = {"no_tag": no_tag, "cut": cut, "duplicate": twice, "blur": blurred, "low_contrast": dark}
    expected = {"no_tag": "no_tag", "cut": "no_tag", "duplicate": "duplicate", "blur": "no_tag",
                "low_contrast": "low_contrast"}
    tracker = TagTracker(sim.intrinsics, TAG._replace(border_margin=8.0))
    for t, (name, image) in enumerate(cases.items()):
        pose = tracker.track(image, float(t))
        assert not pose.valid and pose.reason == expected[name], (name, pose.reason)
        assert np.isnan(pose.position).all() and np.isnan(pose.quaternion).all()
        assert np.isnan(pose.row()[1:8]).all() and pose.row()[8] == 0.0
    border = tracker.track(at_border, 10.0)
    assert not border.valid and border.reason == "border" and np.isfinite(border.corners).all()
    assert tracker.track(at_border, 11.0).reason == "stale"  # the identical frame again: a frozen camera
    assert tracker.track(at_border, 11.0).stale
    assert dict(tracker.dropouts) == {"no_tag": 3, "duplicate": 1, "low_contrast": 1, "border": 1, "stale": 2}
    assert tracker.frames == 8
    tracker.reset()
    assert tracker.frames == 0 and not tracker.dropouts and tracker.track(at_border, 12.0).reason == "border"

    # a reprojection bound nothing meets; an ambiguity bound nothing meets: dropped by a rotation task only
    assert TagTracker(sim.intrinsics, TAG._replace(max_reprojection=1e-6)).track(frame, 0.0).reason == "reprojection"
    strict = TAG._replace(max_ambiguity=1e-9)
    rotation = TagTracker(sim.intrinsics, strict._replace(rotation=True)).track(frame, 0.0)
    assert not rotation.valid and rotation.reason == "ambiguous"
    position = TagTracker(sim.intrinsics, strict).track(frame, 0.0)
    assert position.valid and not position.rotation_ok and np.isfinite(position.quaternion).all()
    row = position.row()
    assert np.isfinite(row[1:4]).all() and np.isnan(row[4:8]).all() and row[8] == 1.0

    with pytest.raises(ValueError, match="intrinsics are for 640x480"):
        tracker.track(frame[:240], 1.0)
    with pytest.raises(ValueError, match="uint8"):
        tracker.track(frame.astype(np.float32), 1.0)
    with pytest.raises(ValueError, match="tag_id"):
        TagTracker(sim.intrinsics, TAG._replace(tag_id=5000))
    with pytest.raises(ValueError, match="tag family"):
        TagTracker(sim.intrinsics, TAG._replace(family="tag99h1"))


@pytest.mark.slow
def test_position_selfid_from_camera(sim):
    """40 moves of 0.03 rad about Q0, tracked by the camera: the fitted inverse Jacobian inverts MuJoCo's."""
    from selfid_jax.robot.offline import fit_samples

    tracker = TagTracker(sim.intrinsics, TAG)
    start = tracker.track(sim.render(Q0), 0.0)
    assert start.valid
    rng = np.random.default_rng(4)
    dtheta, V = [], []
    for k in range(40):
        d = rng.choice([-0.03, 0.03], size=3) * rng.uniform(0.5, 1.0, size=3)
        pose = tracker.track(sim.render(Q0 + d), 0.1 * (k + 1))
        if pose.valid:
            dtheta.append(d)
            V.append(pose.position - start.position)
    assert len(V) >= 38
    trace = fit_samples(np.array(dtheta), np.array(V))
    J = sim.truth(Q0).jacobian[:3]
    error = np.linalg.norm(J @ np.asarray(trace.estimate) - np.eye(3))
    assert error <= SELFID_TOL, error


@pytest.mark.slow
def test_calibration_recovers_the_focal_length():
    camera = CAMERA._replace(fovy=50.0, position=(0.0, 0.0, 1.0), look_at=(1.0, 0.0, 1.0), noise=1.0)
    board = (8, 6, 0.03)
    try:
        scene = BoardCamera(board, camera)
    except RenderUnavailable as err:
        pytest.skip(f"no OpenGL backend for headless rendering: {err}")
    with scene:
        images = [scene.render(p, q) for p, q in board_views(camera, 10, distance=0.5, tilt=35, spread=0.1)]
        blank = np.full_like(images[0], 128)
        truth = scene.intrinsics
    result = calibrate(images, board)
    K = result.intrinsics.K
    assert abs(K[0, 0] / truth.K[0, 0] - 1) < FOCAL_TOL and abs(K[1, 1] / truth.K[1, 1] - 1) < FOCAL_TOL
    assert np.abs(K[:2, 2] - truth.K[:2, 2]).max() < 3.0
    assert result.rms < 0.5 and result.used.sum() >= 8
    assert (result.intrinsics.width, result.intrinsics.height) == (camera.width, camera.height)
    assert np.isnan(result.per_view_error[~result.used]).all() and (result.per_view_error[result.used] < 1).all()

    with pytest.raises(CalibrationError, match="no image"):
        calibrate([], board)
    with pytest.raises(CalibrationError, match=r"found in 2 of 4 images, fewer than 6; not found in: b0.png, b1.png"):
        calibrate([blank, blank, images[0], images[1]], board, names=["b0.png", "b1.png", "c.png", "d.png"])
    with pytest.raises(CalibrationError, match="one camera, one resolution"):
        calibrate([images[0], images[0][:200]], board)


def test_measure_tracker_rows():
    try:
        rows = measure_tracker(resolutions=((320, 240),), distances=(0.4,), angles=(30.0,), frames=4,
                               tag=TrackerSettings(edge=0.05))
    except RenderUnavailable as err:
        pytest.skip(f"no OpenGL backend for headless rendering: {err}")
    (row,) = rows
    assert (row.width, row.height, row.distance, row.angle, row.frames) == (320, 240, 0.4, 30.0, 4)
    assert row.dropout_rate == 0.0 and row.dropouts == ""
    assert 0 < row.position_rms_mm < 5 and row.angle_rms_deg < 5 and row.latency_ms > 0
    assert set(row._asdict()) >= {"bias_x_mm", "bias_y_mm", "bias_z_mm", "tag_px", "latency_max_ms"}


# ------------------------------------------------------------------------------------------- intrinsics files
K_TRUE = np.array([[612.5, 0.0, 319.2], [0.0, 611.0, 241.7], [0.0, 0.0, 1.0]])
DIST = np.array([0.11, -0.23, 0.001, -0.002, 0.05])


def test_intrinsics_round_trip(tmp_path: Path):
    intrinsics = Intrinsics(K_TRUE, DIST, 640, 480)
    for fmt in ("opencv", "ros"):
        path = write_intrinsics(tmp_path / f"{fmt}.yaml", intrinsics, format=fmt)
        back = read_intrinsics(path)
        assert np.allclose(back.K, K_TRUE) and np.allclose(back.dist, DIST) and (back.width, back.height) == (640, 480)
    assert (tmp_path / "opencv.yaml").read_text().startswith("%YAML")  # %YAML:1.0 (OpenCV 4), %YAML 1.2 (5)
    assert "!!opencv-matrix" in (tmp_path / "opencv.yaml").read_text()

    # as OpenCV's own calibration sample writes it (cv2.FileStorage, 5x1 distortion)
    fs = cv2.FileStorage(str(tmp_path / "sample.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "today")
    fs.write("image_width", 1280)
    fs.write("image_height", 720)
    fs.write("camera_matrix", np.array([[900.0, 0, 640], [0, 901.0, 360], [0, 0, 1]]))
    fs.write("distortion_coefficients", DIST.reshape(5, 1))
    fs.release()
    sample = read_intrinsics(tmp_path / "sample.yml")
    assert sample.K[1, 1] == 901.0 and sample.dist.shape == (5,) and sample.width == 1280

    # ROS's camera_calibration_parsers output
    (tmp_path / "ros.yaml").write_text(textwrap.dedent("""\
        image_width: 640
        image_height: 480
        camera_name: narrow_stereo
        camera_matrix:
          rows: 3
          cols: 3
          data: [612.5, 0, 319.2, 0, 611, 241.7, 0, 0, 1]
        distortion_model: plumb_bob
        distortion_coefficients:
          rows: 1
          cols: 5
          data: [0.11, -0.23, 0.001, -0.002, 0.05]
        rectification_matrix:
          rows: 3
          cols: 3
          data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
        projection_matrix:
          rows: 3
          cols: 4
          data: [612.5, 0, 319.2, 0, 0, 611, 241.7, 0, 0, 0, 1, 0]
        """))
    ros = read_intrinsics(tmp_path / "ros.yaml")
    assert np.allclose(ros.K, K_TRUE) and np.allclose(ros.dist, DIST)


def test_bad_intrinsics_files(tmp_path: Path):
    ros = (tmp_path / "ros.yaml")
    base = "image_width: 640\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, data: [600, 0, 320, 0, 600, 240, " \
           "0, 0, 1]}\n"
    cases = {
        "image_width: 640\nimage_height: 480\n": r"ros.yaml: key camera_matrix is missing",
        base: r"ros.yaml: key distortion_coefficients is missing",
        base.replace("rows: 3, cols: 3", "rows: 3, cols: 2"): r"ros.yaml: key camera_matrix: rows x cols = 3 x 2",
        base + "distortion_model: equidistant\ndistortion_coefficients: {rows: 1, cols: 4, data: [0, 0, 0, 0]}\n":
            r"ros.yaml: distortion_model 'equidistant' is not a pinhole model",
        base + "distortion_coefficients: {rows: 1, cols: 3, data: [0, 0, 0]}\n":
            r"ros.yaml: distortion_coefficients must be \(4, 5, 8, 12, 14\)",
        base.replace("image_width: 640\n", "") + "distortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}":
            r"ros.yaml: key image_width is missing",
        base.replace("320", "2000") + "distortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}":
            r"ros.yaml: the principal point \(2000.0, 240.0\) is outside the 640x480 image",
        "camera_matrix: [1, 2\n": r"ros.yaml: not valid YAML",
        "- 1\n- 2\n": r"ros.yaml: expected a mapping",
    }
    for text, message in cases.items():
        ros.write_text(text)
        with pytest.raises(IntrinsicsError, match=message):
            read_intrinsics(ros)

    fs = cv2.FileStorage(str(tmp_path / "cv.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K_TRUE)
    fs.release()
    with pytest.raises(IntrinsicsError, match=r"cv.yml: key distortion_coefficients is missing"):
        read_intrinsics(tmp_path / "cv.yml")
    (tmp_path / "broken.yml").write_text("%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: [\n")
    with pytest.raises(IntrinsicsError, match=r"broken.yml: not a readable OpenCV YAML file"):
        read_intrinsics(tmp_path / "broken.yml")
    with pytest.raises(IntrinsicsError, match=r"missing.yaml: cannot read"):
        read_intrinsics(tmp_path / "missing.yaml")
    with pytest.raises(IntrinsicsError, match="focal lengths"):
        write_intrinsics(tmp_path / "w.yaml", Intrinsics(np.diag([0.0, 600.0, 1.0]), np.zeros(5), 640, 480))
