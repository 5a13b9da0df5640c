"""Self-ID with a camera and an AprilTag as the tracker, offline: a bag's image topic, or a video or a folder of images
beside a joint log, through ``selfid-jax fit`` and ``sj.fit``; ``selfid-jax calibrate``; bad camera inputs.

The frames are rendered (MuJoCo headless) from tests/helpers_camera.py's 3-hinge arm, which the project does not ship,
at 320x240 with the tag ~0.33 m away (~44 px): the arm makes 30 random moves of up to 0.03 rad per joint, its joints
logged at 50 Hz, the camera taking one frame at the end of each rest (the slow test: a 15 Hz camera throughout).
Each form must invert MuJoCo's Jacobian of the tag centre in the camera frame at the start, ``||J J_hat - I||_F <=
FIT_TOL``, and the command and the function must agree to ``SAME``. Measured here (Mesa, software EGL): 0.0075 (bag,
mono8), 0.0083 (PNG folder), 0.018 (MJPG .avi), 0.011 (six frozen frames), 0.030 (four dark and three blurred frames),
0.013 (the 15 Hz stream, bgr8); the calibrated focal length within 0.06 % (PNGs) and 0.04 % (an .mp4). Rendering tests
skip, with the reason, only where no OpenGL context can be created.
"""

from __future__ import annotations

import re
import shutil

import cv2
import numpy as np
import pytest
from helpers_camera import (  # tests/ is on the path
    CAMERA,
    FIT_CAMERA,
    JOINTS,
    TAG_SPEC,
    Recording,
    open_sim,
    record,
    write_bag,
    write_folder,
    write_frame_times,
    write_joint_csv,
    write_video,
)
from helpers_docs import DOCS, check_block_prints_what_it_says, python_blocks, stated_outputs
from helpers_logs import run_fit_command  # tests/ is on the path

import selfid_jax as sj
from selfid_jax.cli import main
from selfid_jax.robot.camera.intrinsics import read_intrinsics, write_intrinsics
from selfid_jax.robot.camera.render import RenderUnavailable, apply_sensor
from selfid_jax.robot.camera.sim import BoardCamera, board_views
from selfid_jax.robot.camera.sources import MIN_VALID_FRAMES, bag_source, camera_info_topic
from selfid_jax.robot.log import LogError
from selfid_jax.robot.read import read_log

FIT_TOL = 0.15  # ||J J_hat - I||_F, position task, against MuJoCo's Jacobian at the start
SAME = 1e-12  # the command and sj.fit run one program on one table
FOCAL_TOL = 0.01  # relative, the calibrated fx, fy against the MuJoCo camera's
BAG = ("--joints", "/joint_states", "--camera", "/camera/image_raw", "--tag", TAG_SPEC)
NAMES = ",".join(JOINTS)


@pytest.fixture(scope="module")
def rec() -> Recording:
    sim = open_sim(FIT_CAMERA)
    try:
        return record(sim)
    finally:
        sim.close()


@pytest.fixture(scope="module")
def files(rec, tmp_path_factory):
    """The recording as a ROS 2 bag (mcap) and as a joint CSV beside a PNG folder, frame times and an OpenCV YAML."""
    root = tmp_path_factory.mktemp("camera_logs")
    return {"bag": write_bag(root / "bag", rec), "csv": write_joint_csv(root / "joints.csv", rec),
            "times": write_frame_times(root / "times.csv", rec.frame_t),
            "folder": write_folder(root / "frames", rec.frames),
            "yaml": write_intrinsics(root / "camera.yaml", rec.intrinsics)}


@pytest.fixture
def no_figures(monkeypatch):
    """The run directory without its figure (matplotlib's ~2 s per file; the figure is tests/test_fit.py's)."""
    from selfid_jax.runner import figures

    monkeypatch.setattr(figures, "save_figure", lambda fig, folder, name: [])


_command = run_fit_command


def _agree(result, info, est):
    np.testing.assert_allclose(result.estimate, est, rtol=0, atol=SAME)
    assert info["notes"] == list(result.notes) and info["warnings"] == list(result.warnings)
    assert (info["converged_at"], info["samples"], info["rows"]) == (result.converged_at, result.deltas.shape[0],
                                                                     result.samples.rows)
    camera = result.report.camera
    assert info["camera"]["frames"] == camera.frames and info["camera"]["edge"] == camera.edge


def _error(rec, estimate):
    return float(np.linalg.norm(rec.jacobian @ np.asarray(estimate) - np.eye(3)))


@pytest.mark.slow
def test_bag_form_command_and_sj_fit(rec, files, tmp_path, no_figures, capsys):
    """/joint_states, /camera/image_raw (mono8) and /camera/camera_info in a ROS 2 bag: the camera's tag poses are
    the tracker, matched to the joints by stamp; the intrinsics come from the camera_info topic."""
    code, info, est = _command(tmp_path, files["bag"], *BAG)
    printed = capsys.readouterr().out
    assert code == 0, printed
    result = sj.fit(files["bag"], joints="/joint_states", camera="/camera/image_raw", tag=TAG_SPEC)
    _agree(result, info, est)
    assert _error(rec, result.estimate) <= FIT_TOL
    camera = result.report.camera
    assert (camera.frames, camera.poses, camera.dropouts) == (31, 31, {})
    assert camera.intrinsics.endswith("topic /camera/camera_info") and camera.kind == "sensor_msgs/msg/Image"
    assert np.allclose([camera.fx, camera.cx, camera.cy], rec.intrinsics.K[[0, 0, 1], [0, 2, 2]])
    assert result.samples.rows == 31 and result.converged
    assert "31 frames of" in printed and "31 tag poses, 0 dropouts" in printed
    assert "edge 0.05 m" in printed and "a wrong edge scales the estimate" in printed
    assert "intrinsics: " in printed and "topic /camera/camera_info (fx 289.7" in printed


@pytest.mark.slow
def test_a_ros1_bag_with_images_and_compressed_images(rec, tmp_path):
    """The bag form from a ROS 1 ``.bag`` (CameraInfo's matrices named D, K, R, P there): the same tag poses, so the
    same estimate as a ROS 2 bag of the same recording, for raw (mono8) and PNG-compressed images."""
    for encoding, topic in (("mono8", "/camera/image_raw"), ("png", "/camera/image_raw/compressed")):
        ros1, ros2 = (sj.fit(write_bag(tmp_path / f"{encoding}{suffix}", rec, encoding=encoding, image_topic=topic,
                                       storage=storage), joints="/joint_states", camera=topic, tag=TAG_SPEC)
                      for suffix, storage in ((".bag", "ros1"), ("", "sqlite3")))
        camera = ros1.report.camera
        assert (camera.frames, camera.poses, camera.dropouts) == (31, 31, {})
        assert camera.intrinsics.endswith("topic /camera/camera_info")
        assert np.allclose([camera.fx, camera.cx, camera.cy], rec.intrinsics.K[[0, 0, 1], [0, 2, 2]])
        assert _error(rec, ros1.estimate) <= FIT_TOL
        np.testing.assert_array_equal(ros1.estimate, ros2.estimate)


@pytest.mark.slow
def test_video_form_folder_command_and_sj_fit(rec, files, tmp_path, no_figures, capsys):
    """A joint CSV (50 Hz, ROS-like joint names), a folder of PNGs, their frame times and an OpenCV YAML; a wrong
    tag edge scales the estimate by true / given, as the report says."""
    flags = ("--video", str(files["folder"]), "--frame-times", str(files["times"]), "--camera-info",
             str(files["yaml"]), "--tag", TAG_SPEC, "--joint-names", NAMES)
    code, info, est = _command(tmp_path, files["csv"], *flags)
    printed = capsys.readouterr().out
    assert code == 0, printed
    kwargs = dict(video=files["folder"], frame_times=files["times"], camera_info=files["yaml"], joint_names=NAMES)
    result = sj.fit(files["csv"], tag=TAG_SPEC, **kwargs)
    _agree(result, info, est)
    assert _error(rec, result.estimate) <= FIT_TOL
    camera = result.report.camera
    assert (camera.frames, camera.poses, camera.kind, camera.intrinsics) == (31, 31, "images", str(files["yaml"]))
    assert f"intrinsics: {files['yaml']} (fx 289.7" in printed and "edge 0.05 m" in printed

    doubled = sj.fit(files["csv"], tag="tag36h11:7:0.1", **kwargs)  # positions twice as large: J_hat halved
    np.testing.assert_allclose(doubled.estimate, 0.5 * result.estimate, rtol=1e-6, atol=1e-9)


@pytest.mark.slow
def test_video_form_avi(rec, files, tmp_path):
    """The same frames as an MJPG .avi (cv2.VideoWriter): JPEG's blocks move the corners a little."""
    avi = write_video(tmp_path / "frames.avi", rec.frames)
    result = sj.fit(files["csv"], video=avi, frame_times=files["times"], camera_info=files["yaml"], tag=TAG_SPEC,
                    joint_names=NAMES)
    assert _error(rec, result.estimate) <= FIT_TOL
    assert (result.report.camera.kind, result.report.camera.poses) == ("video", 31)
    short = write_frame_times(tmp_path / "short.csv", rec.frame_t[:-1])
    with pytest.raises(LogError, match=r"frames\.avi: more frames than the 30 frame times of .*short\.csv$"):
        read_log(files["csv"], video=avi, frame_times=short, camera_info=files["yaml"], tag=TAG_SPEC,
                 joint_names=NAMES)


@pytest.mark.slow
def test_image_encodings_and_compressed_images(rec, tmp_path):
    """mono8, rgb8, bgr8, rgba8, bgra8 (rows padded) and PNG CompressedImage decode to the same grey frame."""
    short = rec._replace(frame_t=rec.frame_t[:2], frames=rec.frames[:2])
    want = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in short.frames]
    for encoding in ("mono8", "rgb8", "bgr8", "rgba8", "bgra8", "png"):
        topic = "/cam/image_raw/compressed" if encoding == "png" else "/cam/image_raw"
        bag = write_bag(tmp_path / encoding, short, encoding=encoding, image_topic=topic, storage="sqlite3")
        with pytest.raises(LogError, match=r"topic /cam/image_raw.* has no camera_info beside it \(/cam/camera_info "
                           r"is not in the bag\): give the camera's intrinsics with --camera-info FILE"):
            bag_source(bag, topic)
        yaml = write_intrinsics(tmp_path / f"{encoding}.yaml", rec.intrinsics)
        source, intrinsics, where = bag_source(bag, topic, camera_info=yaml)
        frames = list(source.frames)
        assert where == str(yaml) and source.frame_count == 2
        for (frame, t), grey, t_rec in zip(frames, want, short.frame_t):
            assert frame.shape == grey.shape and np.abs(frame.astype(int) - grey).max() <= 1, encoding
            assert t == pytest.approx(1_700_000_000.123456789 + t_rec, abs=1e-6)
    assert camera_info_topic("/camera/image_raw") == "/camera/camera_info"
    assert camera_info_topic("/camera/image_raw/compressed") == "/camera/camera_info"
    assert camera_info_topic("/rgb/image_rect") == "/rgb/camera_info"


# ------------------------------------------------------------------------------------------- bad inputs
@pytest.mark.slow
def test_a_tag_never_seen_names_family_and_id(files, tmp_path, capsys):
    code = main(["fit", str(files["bag"]), "--out", str(tmp_path / "o"), *BAG[:-1], "tag36h11:3:0.05"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "tag tag36h11 id 3 never seen in 31 frames (dropouts: no_tag 31); the frames show tag36h11 ids 7 " \
           "(31 frames): is --tag's id right?" in err
    with pytest.raises(LogError, match=r"tag tag25h9 id 0 never seen in 31 frames \(dropouts: no_tag 31\); no "
                       r"tag25h9 tag was detected at all: is the tag in view, lit and of this family\?$"):
        read_log(files["csv"], video=files["folder"], frame_times=files["times"], camera_info=files["yaml"],
                 tag="tag25h9:0:0.05", joint_names=NAMES)
    assert not (tmp_path / "o").exists()  # a failed fit writes nothing


@pytest.mark.slow
def test_a_bag_without_camera_info(rec, files, tmp_path, capsys):
    bag = write_bag(tmp_path / "no_info", rec, camera_info=False)
    code = main(["fit", str(bag), "--out", str(tmp_path / "o"), *BAG])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "topic /camera/image_raw has no camera_info beside it (/camera/camera_info is not in the bag): give the " \
           "camera's intrinsics with --camera-info FILE (camera_info=)" in err
    samples, report = read_log(bag, joints="/joint_states", camera="/camera/image_raw", tag=TAG_SPEC,
                               camera_info=files["yaml"])
    assert report.camera.intrinsics == str(files["yaml"]) and samples.dtheta.shape == (30, 3)


def _folder_log(files, tmp_path, frames):
    """The CSV form's keywords with ``frames`` as the folder."""
    folder = write_folder(tmp_path / "frames", frames)
    return dict(video=folder, frame_times=files["times"], camera_info=files["yaml"], tag=TAG_SPEC, joint_names=NAMES)


@pytest.mark.slow
def test_a_frozen_camera(rec, files, tmp_path):
    """Repeated frames are stale dropouts; a camera frozen for a few frames still fits, one frozen from the start
    is an error that says so."""
    frames = list(rec.frames)
    frames[12:18] = [frames[11]] * 6
    result = sj.fit(files["csv"], **_folder_log(files, tmp_path / "a", frames))
    camera = result.report.camera
    assert camera.dropouts == {"stale": 6} and camera.poses == 25
    assert "6 stale frames (identical to the frame before: a frozen camera or driver) dropped" in result.notes
    assert _error(rec, result.estimate) <= FIT_TOL
    frozen = frames[:4] + [frames[3]] * 27
    with pytest.raises(LogError, match=rf"only 4 of 31 frames gave a pose of tag tag36h11 id 7 \(dropouts: stale "
                       rf"27\); 27 stale frames: a frozen camera or driver repeats its last frame; a fit needs at "
                       rf"least {MIN_VALID_FRAMES}$"):
        sj.fit(files["csv"], **_folder_log(files, tmp_path / "b", frozen))


@pytest.mark.slow
def test_a_camera_clock_that_steps_back_in_a_bag(rec, files, tmp_path):
    """Five frames whose header stamps step back 2 s (the camera's clock; their receive times keep pace) are dropped
    and reported as a CSV's backwards rows are, not re-sorted onto joints 2 s earlier: the estimate is the one of
    the same bag without those frames."""
    offset = np.zeros(len(rec.frames))
    offset[10:15] = -2.0
    stepped = write_bag(tmp_path / "stepped", rec, stamp_offset=offset)
    keep = np.r_[0:10, 15:len(rec.frames)]
    without = write_bag(tmp_path / "without", rec._replace(frame_t=rec.frame_t[keep],
                                                           frames=[rec.frames[k] for k in keep]))
    result, reference = (sj.fit(bag, joints="/joint_states", camera="/camera/image_raw", tag=TAG_SPEC)
                         for bag in (stepped, without))
    assert any(re.search(r"dropped: 5 poses whose stamps step off the bag's clock by more than .* first: "
                         r"/camera/image_raw stamp 1700000003\.", note) for note in result.notes), result.notes
    np.testing.assert_array_equal(result.estimate, reference.estimate)
    assert result.samples.rows == 26 and _error(rec, result.estimate) <= FIT_TOL


@pytest.mark.slow
def test_a_dark_and_a_blurred_stretch(rec, files, tmp_path):
    """Four dark frames (exposure 4 %) and three blurred ones drop out with their reasons; the fit is still good."""
    frames = list(rec.frames)
    dark = CAMERA._replace(exposure=0.04, noise=1.0)
    rng = np.random.default_rng(0)
    frames[8:12] = [apply_sensor(f, dark, rng) for f in frames[8:12]]
    frames[20:23] = [cv2.GaussianBlur(f, (0, 0), 6.0) for f in frames[20:23]]
    result = sj.fit(files["csv"], **_folder_log(files, tmp_path, frames))
    camera = result.report.camera
    assert camera.dropouts == {"low_contrast": 4, "no_tag": 3} and camera.poses == 24
    assert _error(rec, result.estimate) <= FIT_TOL


BAD_OPTIONS = [
    (("--camera", "/camera/image_raw"), r"camera \(--camera\) needs tag \(--tag\)"),
    (("--tag", TAG_SPEC), r"tag \(--tag\) is for camera frames: give video \(--video\)"),
    (("--video", "frames", "--tag", TAG_SPEC), r"video \(--video\) needs frame_times \(--frame-times\)"),
    (("--video", "frames", "--frame-times", "t.csv", "--tag", TAG_SPEC),
     r"video \(--video\) needs camera_info \(--camera-info\)"),
    (("--camera", "/c", "--tracker", "/t", "--tag", TAG_SPEC), r"camera \(--camera\) is the tracker: drop tracker"),
    (("--video", "f", "--child-frame", "m", "--tag", TAG_SPEC), r"video \(--video\) is the tracker: drop child_frame"),
    (("--camera", "/c", "--tag", "tag36h11:7"), r"tag \(--tag\): expected FAMILY:ID:EDGE_M"),
    (("--camera", "/c", "--tag", "tag36h11:7:50"), r"an edge of 50 m is not a tag's; give it in metres \(0\.05 for "
     r"50 mm\)"),
    (("--camera", "/c", "--tag", "tag36h11:-1:0.05"), r"the tag id must be >= 0"),
    (("--camera", "/c", "--tag", TAG_SPEC, "--length", "mm"), r"length \(--length\) mm: the camera's positions are "
     r"in metres"),
]


@pytest.mark.slow
@pytest.mark.parametrize("flags, message", BAD_OPTIONS, ids=[" ".join(f[:2]) + f" {i}" for i, (f, _) in
                                                             enumerate(BAD_OPTIONS)])
def test_camera_options_are_refused_by_keyword_and_flag(files, tmp_path, capsys, flags, message):
    assert main(["fit", str(files["csv"]), "--out", str(tmp_path / "o"), *flags]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and re.search(message, err), err


@pytest.mark.slow
def test_camera_inputs_that_cannot_be_used(rec, files, tmp_path):
    """Each names the file, topic or flag: an unknown family, a camera topic of a table log, a video beside a bag,
    frames of another size than the intrinsics, more images than frame times, times that do not increase,
    unpadded frame numbers."""
    video = dict(video=files["folder"], frame_times=files["times"], camera_info=files["yaml"], joint_names=NAMES)
    with pytest.raises(ValueError, match=r"tag \(--tag\) tag99h1:0:0\.05: tag family: expected one of"):
        read_log(files["csv"], tag="tag99h1:0:0.05", **video)
    with pytest.raises(LogError, match=r"joints\.csv: --joints, --tracker, --child-frame and --camera .* are for a "
                       r"ROS bag"):
        read_log(files["csv"], camera="/camera/image_raw", tag=TAG_SPEC)
    with pytest.raises(LogError, match=r"bag: --video \(video=\) goes with a table log"):
        read_log(files["bag"], joints="/joint_states", tag=TAG_SPEC, **{**video, "joint_names": None})
    big = write_intrinsics(tmp_path / "big.yaml", rec.intrinsics._replace(width=640, height=480))
    with pytest.raises(LogError, match=r"frames: frame 1: frame: 320x240 pixels, but the intrinsics are for 640x480 "
                       rf"\(from {big}\)$"):
        read_log(files["csv"], tag=TAG_SPEC, **{**video, "camera_info": big})
    short = write_frame_times(tmp_path / "short.csv", rec.frame_t[:-1])
    with pytest.raises(LogError, match=r"frames: 31 images but .*short\.csv has 30 frame times"):
        read_log(files["csv"], tag=TAG_SPEC, **{**video, "frame_times": short})
    backwards = write_frame_times(tmp_path / "back.csv", rec.frame_t[::-1])
    with pytest.raises(LogError, match=r"back\.csv \(--frame-times\): line 3: t = 14\.95 s does not come after "
                       r"15\.45 s; frame times must increase"):
        read_log(files["csv"], tag=TAG_SPEC, **{**video, "frame_times": backwards})
    unpadded = tmp_path / "unpadded"
    unpadded.mkdir()
    for k in (1, 2, 10):
        shutil.copy(files["folder"] / f"frame_{k:04d}.png", unpadded / f"f{k}.png")
    with pytest.raises(LogError, match=r"f10\.png sorts before f2\.png: number the files with zero padding"):
        read_log(files["csv"], tag=TAG_SPEC, **{**video, "video": unpadded})


# ------------------------------------------------------------------------------------------- calibration
@pytest.mark.slow
def test_calibrate_command_recovers_the_focal_length(tmp_path, capsys):
    """``selfid-jax calibrate FOLDER --board checkerboard:8x6:0.03 --out camera.yaml`` on rendered board views, and
    the same views as a video; the YAML it writes is what ``fit --camera-info`` reads."""
    camera = CAMERA._replace(fovy=50.0, position=(0.0, 0.0, 1.0), look_at=(1.0, 0.0, 1.0), noise=1.0)
    try:
        scene = BoardCamera((8, 6, 0.03), camera)
    except RenderUnavailable as err:
        pytest.skip(f"no OpenGL backend for headless rendering: {err}")
    with scene:
        images = [scene.render(p, q) for p, q in board_views(camera, 10, distance=0.5, tilt=35, spread=0.1)]
        truth = scene.intrinsics
    images.append(np.full_like(images[0], 128))  # a view without the board: listed, not used
    folder = write_folder(tmp_path / "views", images)
    out = tmp_path / "camera.yaml"
    assert main(["calibrate", str(folder), "--board", "checkerboard:8x6:0.03", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    K = read_intrinsics(out).K
    assert abs(K[0, 0] / truth.K[0, 0] - 1) < FOCAL_TOL and abs(K[1, 1] / truth.K[1, 1] - 1) < FOCAL_TOL
    assert f"fx {K[0, 0]:.2f}  fy {K[1, 1]:.2f}  cx {K[0, 2]:.2f}  cy {K[1, 2]:.2f}" in printed
    assert "RMS reprojection error" in printed and "used: frame_0000.png" in printed
    assert "board not found in: frame_0010.png" in printed and f"intrinsics (opencv): {out}" in printed

    # MPEG-4 (mp4v): from an MJPG .avi of these views the focal length came out 0.7 % off and the principal point
    # 1.7 px (JPEG's 8x8 blocks on the board's edges), from this .mp4 0.04 %, as from the PNGs (0.05 %)
    video = write_video(tmp_path / "views.mp4", images[:-1], fourcc="mp4v")
    ros = tmp_path / "camera_ros.yaml"
    board = ("--board", "checkerboard:8x6:0.03")
    assert main(["calibrate", str(video), *board, "--out", str(ros), "--format", "ros"]) == 0
    assert "used: views.mp4 frame 0" in capsys.readouterr().out
    assert abs(read_intrinsics(ros).K[0, 0] / truth.K[0, 0] - 1) < FOCAL_TOL

    for flags, message in [(("--board", "chess:8x6:0.03"), "--board: expected checkerboard:COLSxROWS:SQUARE_M"),
                           (("--board", "checkerboard:8x6:0"), "--board: expected checkerboard:COLSxROWS:SQUARE_M"),
                           (("--board", "checkerboard:8x6:0.03", "--max-images", "3"), "--max-images): 3 is fewer "
                            "than the 6 views needed")]:
        assert main(["calibrate", str(folder), *flags, "--out", str(tmp_path / "x.yaml")]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    assert main(["calibrate", str(tmp_path / "nothing"), "--board", "checkerboard:8x6:0.03", "--out", str(out)]) == 2
    assert "nothing: no such file or folder" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------- slow
@pytest.mark.slow
def test_a_continuous_camera_in_a_bag(tmp_path):
    """A 15 Hz camera (bgr8) filming the moves and the rests: the matched table is a stream, reduced to one settled
    row per rest, and the fit still inverts MuJoCo's Jacobian (11 s on 2 idle cores: 233 frames rendered and
    tracked)."""
    sim = open_sim(FIT_CAMERA)
    try:
        stream = record(sim, frames="stream", camera_rate=15.0, seed=1)
    finally:
        sim.close()
    bag = write_bag(tmp_path / "stream", stream, encoding="bgr8")
    result = sj.fit(bag, joints="/joint_states", camera="/camera/image_raw", tag=TAG_SPEC)
    assert result.report.stream is not None and result.report.stream.continuous
    assert result.report.camera.frames == len(stream.frames) and result.samples.rows >= 28
    assert _error(stream, result.estimate) <= FIT_TOL


TAG_BLOCKS = [b for b in python_blocks((DOCS / "camera.md").read_text(encoding="utf-8")) if "generateImageMarker" in b]


def test_the_camera_page_prints_a_tag(tmp_path):
    """docs/camera.md's tag block (the tag to print, generated by OpenCV) runs as a reader would paste it."""
    assert len(TAG_BLOCKS) == 1 and stated_outputs(TAG_BLOCKS[0])
    check_block_prints_what_it_says(TAG_BLOCKS[0], tmp_path)
    assert (tmp_path / "tag36h11_7.png").is_file()
