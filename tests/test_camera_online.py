"""A live camera as the online runner's tracker: frames over MJPEG-over-HTTP opened by ``cv2.VideoCapture(url)``.

Fast tests serve generated frames from this process (:class:`~selfid_jax.robot.camera.stream.MjpegServer`) in
front of the fake arm of helpers_online: the newest frame, stamped on the runner's clock; a frame exposed before a
move never reported as its result; a camera that ends; a frozen camera (the stale stop, before any motion); a
camera that cannot be opened, a camera_info that cannot be used and a tag that does not exist (errors naming the key,
before the robot is reached). The end-to-end test runs ``selfid-jax robot-sim`` with its camera (the shipped
configs/robot/robot_sim_camera.yaml at 320x240) in a process of its own and an online session whose tracker is that
camera (configs/robot/online_camera_sim.yaml): self-ID from rendered frames, convergence, a 3 cm star, and the
estimate against MuJoCo's Jacobian of the tag's centre in the camera frame.
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers_online import FakeArm  # tests/ is on the path

from selfid_jax.robot import live
from selfid_jax.robot.camera.intrinsics import Intrinsics, write_intrinsics
from selfid_jax.robot.camera.live import CameraError, CameraTracked, LiveCamera, parse_tag
from selfid_jax.robot.camera.sim import tag_image
from selfid_jax.robot.camera.stream import FrameFeed, MjpegServer
from selfid_jax.robot.camera.tracker import TagTracker, TrackerSettings
from selfid_jax.robot.journal import floats, read_journal
from selfid_jax.robot.options import OnlineOptions as options
from selfid_jax.robot.protocol import RobotConnectionError
from selfid_jax.runner.errors import ConfigError
from selfid_jax.sessions.online_config import load_online_config
from selfid_jax.sessions.online_run import open_camera, run_session

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "robot"
W, H = 320, 240
K = np.array([[300.0, 0.0, (W - 1) / 2], [0.0, 300.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
INTRINSICS = Intrinsics(K, np.zeros(5), W, H)
TAG = TrackerSettings(family="tag36h11", tag_id=3, edge=0.05)
SELFID_TOL = 0.15  # ||J J_hat - I||_F of the end-to-end session (measured 0.054-0.064 over four runs; 0.11-0.15 with
#   wander 3: the arm's curvature over the self-ID moves, the estimate being a fit over them, not J at the start)


def _picture(seed: int) -> np.ndarray:
    """A (H, W, 3) frame of tag 3 rolled 20 degrees, 60 px wide, on grey with read noise (seed: the noise)."""
    tag = tag_image(TAG.family, TAG.tag_id, cell_px=6)  # 10 cells of 6 px with its quiet zone
    frame = np.full((H, W), 110, np.uint8)
    y, x = (H - tag.shape[0]) // 2, (W - tag.shape[1]) // 2
    frame[y:y + tag.shape[0], x:x + tag.shape[1]] = tag
    turn = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), 20.0, 1.0)
    frame = cv2.warpAffine(frame, turn, (W, H), flags=cv2.INTER_LINEAR, borderValue=110)
    noisy = frame + np.random.default_rng(seed).normal(0.0, 2.0, frame.shape)
    return np.repeat(np.clip(np.rint(noisy), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _Noisy:
    """A frame source: the tag picture with fresh read noise each frame."""

    def __init__(self):
        self.k = 0

    def render(self):
        self.k += 1
        return _picture(self.k)

    def close(self):
        pass


def test_parse_tag():
    assert parse_tag("tag36h11:7:0.05") == ("tag36h11", 7, 0.05)
    for bad, match in (("tag36h11:7", "FAMILY:ID:EDGE_M"), ("tag99h9:1:0.05", "tag family"),
                       ("tag36h11:x:0.05", "whole number"), ("tag36h11:1:-0.05", "> 0 m")):
        with pytest.raises(ValueError, match=match):
            parse_tag(bad)


@pytest.mark.slow
def test_the_newest_frame_on_the_runners_clock_and_never_one_from_before_a_move():
    """Poses from the stream, stamped at arrival less latency_s; after a move only a frame exposed after it; a
    silent camera repeats its stamp; a stream that ends is a lost connection."""
    with MjpegServer(quality=95) as server:
        server.start()
        server.publish(_picture(0))
        camera = LiveCamera(server.url, latency_s=0.02, size=(W, H))
        arm = FakeArm()
        robot = CameraTracked(arm, camera, TagTracker(INTRINSICS, TAG), wait_s=0.3)
        try:
            first = robot.read()  # only the priming frame so far: no pose
            assert not first.valid and np.isnan(first.position).all() and first.tracker_t <= first.t
            for k in range(1, 4):
                sent = time.monotonic()
                server.publish(_picture(k))
                frame = camera.wait_newer(camera.latest().seq, 5.0)
                obs = robot.read()
                assert obs.valid and np.isfinite(obs.position).all() and 0.2 < obs.position[2] < 2.0
                assert obs.tracker_t == frame.t and sent - 0.02 <= obs.tracker_t <= obs.t
            again = robot.read()  # no new frame: the same pose and stamp (the watchdog's age grows)
            assert again.valid and again.tracker_t == obs.tracker_t

            robot.move(arm.q + 0.01)  # no frame after the move within wait_s: no pose, the stamp stays
            start = time.monotonic()
            late = robot.read()
            assert not late.valid and late.tracker_t == obs.tracker_t and time.monotonic() - start >= 0.3
            robot.move(arm.q + 0.01)
            moved = time.monotonic()
            time.sleep(0.05)  # more than latency_s: the next frame was exposed after the move
            server.publish(_picture(10))
            camera.wait_newer(camera.latest().seq, 5.0)
            after = robot.read()
            assert after.valid and moved < after.tracker_t <= after.t
            counts = robot.counts()
            assert counts["poses"] == 4 and counts["dropouts"] == {"late": 1} and counts["frames"] == 5
        finally:
            server.close()
        deadline = time.monotonic() + 10
        while camera.ended is None and time.monotonic() < deadline:
            time.sleep(0.05)
        with pytest.raises(RobotConnectionError, match="stream ended"):
            robot.read()
        robot.close()
        assert arm.closed


class _Webcam:
    """Stands in for ``cv2.VideoCapture`` of a device index (no webcam on the test machines): what the runner asked
    of it (``opened``, ``asked``), and the tag picture at 30 frames per second."""

    opened: list = []

    def __init__(self, *args):
        type(self).opened.append(args)
        self.asked: dict[int, int] = {}
        self.k = 0
        _Webcam.last = self

    def isOpened(self):
        return True

    def set(self, prop, value):
        self.asked[prop] = value
        return True

    def grab(self):
        time.sleep(1 / 30)
        self.k += 1
        return True

    def retrieve(self):
        return True, _picture(self.k)[:, :, ::-1]

    def release(self):
        pass


def test_a_webcam_by_device_index(monkeypatch):
    """A device index goes to cv2.VideoCapture as the int OpenCV opens webcams by (no FFmpeg URL options), is asked
    for the intrinsics' resolution, and its frames become poses; an index with no device is one error naming it."""
    with pytest.raises(CameraError, match=r"^camera 7: OpenCV cannot open it \(cv2\.VideoCapture\); is it connected, "
                       r"and not in use by another program\?$"):
        LiveCamera(7, open_timeout_s=1.0)
    monkeypatch.setattr(cv2, "VideoCapture", _Webcam)
    _Webcam.opened.clear()
    camera = LiveCamera(0, size=(W, H), open_timeout_s=2.0)
    robot = CameraTracked(FakeArm(), camera, TagTracker(INTRINSICS, TAG), wait_s=0.5)
    try:
        assert _Webcam.opened == [(0,)]
        assert _Webcam.last.asked == {cv2.CAP_PROP_FRAME_WIDTH: W, cv2.CAP_PROP_FRAME_HEIGHT: H}
        camera.wait_newer(camera.latest().seq, 2.0)
        obs = robot.read()
        assert obs.valid and 0.2 < obs.position[2] < 2.0 and obs.tracker_t <= obs.t
    finally:
        robot.close()


def _session_config(tmp_path: Path, camera, *, info: str = "camera.yaml", tag: str = "tag36h11:3:0.05",
                    extra: str = "") -> Path:
    cfg = tmp_path / "online.yaml"
    cfg.write_text(textwrap.dedent(f"""\
        robot: {{driver: "fake_driver:make"}}
        tracker: {{camera: {json.dumps(camera)}, tag: "{tag}", camera_info: {info}, open_timeout_s: 3.0}}
        selfid: {{task: "x,y,z", m_a: 0.03, max_samples: 20, settle_s: 0.0, poll_s: 0.01}}
        safety: {{stale_s: 0.5}}
        """) + extra)
    return cfg


@pytest.mark.slow
def test_a_frozen_camera_stops_the_session_as_stale_before_any_motion(tmp_path):
    """The camera streams, its picture does not change (robot-sim's freeze_camera_at_s: 0): every frame after the
    first is stale, no pose is ever reported, the runner's watchdog stops the session and the arm is never moved."""
    write_intrinsics(tmp_path / "camera.yaml", INTRINSICS)
    with MjpegServer() as server:
        server.start()
        feed = FrameFeed(server, _Noisy, fps=20, freeze_at_s=0.0).start()
        try:
            cfg = _session_config(tmp_path, server.url)
            camera, tracker = open_camera(load_online_config(cfg), tmp_path)  # what run_session opens
            arm = FakeArm()
            robot = CameraTracked(arm, camera, tracker)
            result = live.run_online(robot, options(task="x,y,z", m_a=0.03, max_samples=20, settle_s=0.0,
                                                    poll_s=0.01, stale_s=0.5), tmp_path / "run")
        finally:
            feed.close()
    assert result.status == live.Stop.STALE, result.detail
    assert arm.moves == [] and arm.closed and result.moves == 0 and camera.ended is None
    counts = robot.counts()
    assert counts["camera"] == server.url and counts["poses"] == 0 and counts["tracked"] >= 1
    assert counts["dropouts"] == {"stale": counts["tracked"]}


@pytest.mark.slow
def test_a_camera_that_cannot_be_used_is_an_error_naming_it_before_the_robot_is_reached(tmp_path, driver_module):
    write_intrinsics(tmp_path / "camera.yaml", INTRINSICS)
    url = f"http://127.0.0.1:{_free_port()}/stream.mjpg"  # nothing serves it
    for info, match in (("camera.yaml", rf"tracker\.camera: camera '{url}': OpenCV cannot open it"),
                        ("nonesuch.yaml", r"tracker\.camera_info: nonesuch\.yaml: no such file")):
        cfg = _session_config(tmp_path, url, info=info)
        with pytest.raises(ConfigError, match=match):
            run_session(load_online_config(cfg), tmp_path / "run", config_path=cfg)
    with pytest.raises(ConfigError, match=r"tracker\.tag.*family tag36h11 has ids 0\.\.586"):
        load_online_config(_session_config(tmp_path, url, tag="tag36h11:900:0.05"))
    with MjpegServer() as server:  # a camera that sends 320x240 frames, intrinsics for 640x480
        server.start()
        feed = FrameFeed(server, _Noisy, fps=20).start()
        write_intrinsics(tmp_path / "big.yaml", Intrinsics(K * [[2], [2], [1]], np.zeros(5), 2 * W, 2 * H))
        cfg = _session_config(tmp_path, server.url, info="big.yaml")
        try:
            with pytest.raises(ConfigError, match=r"tracker\.camera: .* sends 320x240 frames, but the intrinsics "
                                                  r"are for 640x480"):
                run_session(load_online_config(cfg), tmp_path / "run", config_path=cfg)
        finally:
            feed.close()
        silent = MjpegServer()  # listens, never sends a frame
        silent.start()
        try:
            with pytest.raises(CameraError, match="cannot open it|no frame within 0.5 s"):
                LiveCamera(silent.url, open_timeout_s=0.5)
        finally:
            silent.close()
    assert driver_module.CREATED == []  # the robot was never reached, let alone moved
    assert not (tmp_path / "run" / live.LOG_FILE).exists()


# ------------------------------------------------------------------------------------------- end to end
# The simulated camera at 20 frames a second with 0.05 s of latency (shipped 10 and 0.1 s), the session told so:
# it waits 0.25 s after each move instead of 0.35 s (the servo's 0.1 s, a frame interval, the latency, 0.05 s to
# spare), about 0.1 s less for each of some 45 moves. Rendering 320x240 frames at 20 a second is about a third of
# the shipped 640x480 at 10.
FAST_CAMERA = ["camera.fps=20", "camera.latency_s=0.05"]


@pytest.mark.slow
@pytest.mark.xdist_group("realtime")  # a real-time clock: beside test_robot_sim's, not against it
def test_online_session_self_identifies_and_follows_a_star_through_robot_sims_camera(tmp_path, console):
    """robot-sim (a UR5e filmed at 320x240, served as MJPEG) in a process of its own; the session sees the arm only
    through the frames: it converges, makes no random move after, follows all 10 waypoints of a 3 cm star, and its
    estimate inverts MuJoCo's Jacobian of the tag's centre in the camera frame where self-ID started."""
    from selfid_jax.robot.camera.intrinsics import read_intrinsics
    from selfid_jax.robot.camera.render import RenderUnavailable
    from selfid_jax.sessions.online_sim import load_sim_config, sim_camera

    view = ["camera.width=320", "camera.height=240", "camera.fovy=30"]  # 45 px tag at 0.56 m, a third of the work
    files = [f"camera.intrinsics={tmp_path / 'camera.yaml'}", f"camera.url_file={tmp_path / 'camera.url'}"]
    sim_cfg = load_sim_config(CONFIGS / "robot_sim_camera.yaml", view + files)
    try:
        scene = sim_camera(sim_cfg)  # the same scene, for MuJoCo's Jacobian of the tag (no frame is rendered)
    except RenderUnavailable as err:
        pytest.skip(f"no OpenGL backend for headless rendering: {err}")
    port_file = tmp_path / "sim.port"
    args = [*console, "robot-sim", str(CONFIGS / "robot_sim_camera.yaml"), "--port", "0", "--port-file",
            str(port_file), "--set", "camera.port=0", *sum((["--set", s] for s in view + files + FAST_CAMERA), [])]
    started = time.monotonic()
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 120
        while not port_file.exists():
            if proc.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"robot-sim did not start: {proc.communicate(timeout=5)[0]}")
            time.sleep(0.1)
        url = (tmp_path / "camera.url").read_text().strip()
        assert url.startswith("http://127.0.0.1:") and url.endswith("/stream.mjpg")
        assert read_intrinsics(tmp_path / "camera.yaml").K.tolist() == scene.intrinsics.K.tolist()
        cfg = load_online_config(CONFIGS / "online_camera_sim.yaml", [
            f"robot.port={int(port_file.read_text())}", f"tracker.camera={url}",
            f"tracker.camera_info={tmp_path / 'camera.yaml'}",
            # gain 1 and up to 3 cm a move (shipped 0.5 and 5 mm): about one move per waypoint, 11 instead of 44
            "path.gain=1.0", "path.max_task_step=0.03",
            "safety.stale_s=2.0",  # 2 loaded cores can starve a clock past the shipped 1 s (a safe stop)
            "tracker.latency_s=0.05", "selfid.settle_s=0.25"])  # FAST_CAMERA's latency; its settle time
        session = time.monotonic()
        result, _ = run_session(cfg, tmp_path / "run", config_path=CONFIGS / "online_camera_sim.yaml")
        timing = f"robot-sim start {session - started:.0f} s, session {time.monotonic() - session:.0f} s"
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=60)[0]
    scene_J = None
    try:
        records = read_journal(result.log).records
        centre = floats(next(r for r in records if r["e"] == "centre")["q"])
        scene_J = scene.truth(centre).jacobian[:3]  # (3, 6): the UR5e's qpos is its actuators'
    finally:
        scene.close()
    assert result.status == live.Stop.COMPLETED, (result.detail, out)
    assert result.converged and result.waypoints == result.waypoints_total == 10
    at = next(i for i, r in enumerate(records) if r["e"] == "converged")
    assert all(r.get("phase") != "selfid" for r in records[at:] if r["e"] == "move")  # no random move after
    error = float(np.linalg.norm(scene_J @ result.estimate - np.eye(3)))
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    print(f"||J J_hat - I||_F = {error:.3f}; converged at {result.converged_at}; path distance mean "
          f"{1e3 * summary['track_mean_m']:.2f} mm, max {1e3 * summary['track_max_m']:.2f} mm; "
          f"camera {summary['camera']}; {timing}")
    assert error < SELFID_TOL, error
    assert summary["track_max_m"] < cfg.safety.diverge_dist
    assert summary["camera"]["poses"] >= result.samples and summary["camera"]["frames"] > summary["camera"]["tracked"]
    assert "robot-sim: serving ur5e" in out
