"""The simulated camera: any MJCF arm rendered headless with a generated AprilTag on its tracked body.

:class:`SimCamera` builds the scene (an MJCF path or XML string, the tracked
body, the tag's family, id, edge and place on the body, a
:class:`~selfid_jax.robot.camera.render.CameraSettings`) and then gives, for a
joint configuration ``qpos (nq,)``:

* :meth:`SimCamera.render`: the frame the camera sees, ``(H, W, 3)`` RGB (or
  ``(H, W)`` grey) uint8, with the settings' blur, exposure, gain and noise;
* :meth:`SimCamera.truth`: the ground truth in the camera frame (OpenCV's: x
  right, y down, z forward), the tag centre's position (m) and orientation, and
  MuJoCo's Jacobian of the tag centre (``mj_jacSite``, rotated into the camera
  frame), for tests and for measuring the tracker;
* :attr:`SimCamera.intrinsics`: the pinhole intrinsics that match the MuJoCo
  camera (no distortion).

The tag texture is generated at run time (``cv2.aruco.generateImageMarker``
with a white quiet zone of ``white_cells`` cells around the black border) and
added with MuJoCo's ``MjSpec`` API; no image file is shipped. ``edge`` is the
black square's edge, as OpenCV's marker length (and the tracker's ``edge``).

:class:`BoardCamera` renders a generated checkerboard held in front of the same
kind of camera, for calibration tests (:func:`board_views` draws board poses).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import mujoco
import numpy as np
from numpy.typing import ArrayLike

from selfid_jax.robot.camera.intrinsics import Intrinsics
from selfid_jax.robot.camera.render import (
    CameraSettings,
    OffscreenRenderer,
    add_camera,
    add_textured_quad,
    apply_sensor,
    camera_matrix,
    camera_rotation,
    check_settings,
)
from selfid_jax.robot.camera.tracker import TrackerSettings, check_tracker_settings, tag_dictionary

__all__ = ["BoardCamera", "SimCamera", "TagTruth", "board_image", "board_views", "tag_image"]

_CAMERA = "selfid_camera"
_TAG_SITE = "selfid_tag"


class TagTruth(NamedTuple):
    """The tag's true pose and Jacobian in the camera frame (OpenCV's: x right, y down, z forward)."""

    position: np.ndarray  # (3,) tag centre, m
    quaternion: np.ndarray  # (4,) (w, x, y, z), w >= 0, tag frame in the camera frame
    rotation: np.ndarray  # (3, 3) the same rotation as a matrix
    jacobian: np.ndarray  # (6, nv) [linear (m per dof unit); angular (rad per dof unit)] of the tag centre


def tag_image(family: str, tag_id: int, *, cell_px: int = 16, white_cells: int = 1) -> np.ndarray:
    """``(S, S) uint8`` image of a tag with a white quiet zone: ``S = (bits + 2 + 2 white_cells) cell_px``.

    ``bits`` is the family's data width (6 for tag36h11); the black border is one cell.
    """
    dictionary = tag_dictionary(family)
    cells = int(dictionary.markerSize) + 2
    marker = cv2.aruco.generateImageMarker(dictionary, int(tag_id), cells * cell_px, borderBits=1)
    pad = white_cells * cell_px
    return cv2.copyMakeBorder(marker, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)


def _load_spec(xml: str | Path) -> Any:
    text = str(xml)
    if isinstance(xml, Path) or not text.lstrip().startswith("<"):
        path = Path(xml)
        if not path.is_file():
            raise FileNotFoundError(f"MJCF: {path} is not a file (pass a path or an XML string starting with '<')")
        return mujoco.MjSpec.from_file(str(path))
    return mujoco.MjSpec.from_string(text)


class SimCamera:
    """A camera looking at an MJCF arm whose ``body`` carries an AprilTag; renders frames and their ground truth.

    ``tag_pos (3,)`` (m) and ``tag_quat (4,)`` (wxyz) place the tag frame in
    ``body``'s frame: the tag lies in its x-y plane, facing +z, the printed
    tag's top towards +y. ``tag`` gives the family, id and edge (the tracker's
    settings; the rest of them is ignored here). ``render``/``truth`` take the
    model's full ``qpos (nq,)``; the Jacobian's columns are its dofs ``(nv,)``.
    Creating one opens an OpenGL context
    (:class:`~selfid_jax.robot.camera.render.RenderUnavailable` where none can
    be); :meth:`close` (or a ``with`` block) frees it.
    """

    def __init__(self, xml: str | Path, body: str, *, tag: TrackerSettings = TrackerSettings(),
                 tag_pos: ArrayLike = (0.0, 0.0, 0.0), tag_quat: ArrayLike = (1.0, 0.0, 0.0, 0.0),
                 camera: CameraSettings = CameraSettings(), white_cells: int = 1) -> None:
        check_tracker_settings(tag)
        self.settings = check_settings(camera)
        spec = _load_spec(xml)
        tracked = spec.body(body)
        if tracked is None:
            names = [b.name for b in spec.bodies if b.name]
            raise ValueError(f"tracked body {body!r} is not in the MJCF; its bodies: {names}")
        image = tag_image(tag.family, tag.tag_id, white_cells=white_cells)
        cells = tag_dictionary(tag.family).markerSize + 2
        half = 0.5 * tag.edge * (cells + 2 * white_cells) / cells
        quat = np.asarray(tag_quat, dtype=np.float64)
        if quat.shape != (4,) or not np.isfinite(quat).all() or np.linalg.norm(quat) < 1e-9:
            raise ValueError(f"tag_quat: expected a nonzero (w, x, y, z), got {tag_quat!r}")
        add_textured_quad(spec, tracked, name=_TAG_SITE, image=image, half_size=(half, half),
                          pos=np.asarray(tag_pos, dtype=np.float64).reshape(3).tolist(),
                          quat=(quat / np.linalg.norm(quat)).tolist())
        add_camera(spec, camera, name=_CAMERA)
        self.model = spec.compile()
        self._data = mujoco.MjData(self.model)
        self._site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, _TAG_SITE)
        self._R = camera_rotation(camera.position, camera.look_at, camera.up)  # camera axes in the world
        self._p = np.asarray(camera.position, dtype=np.float64)
        self._rng = np.random.default_rng(camera.seed)
        self.intrinsics = Intrinsics(camera_matrix(camera.width, camera.height, camera.fovy), np.zeros(5),
                                     int(camera.width), int(camera.height))
        self._renderer = OffscreenRenderer(self.model, camera=_CAMERA, width=camera.width, height=camera.height)

    def _set(self, qpos: Any) -> None:
        qpos = np.asarray(qpos, dtype=np.float64).reshape(-1)
        if qpos.shape != (self.model.nq,) or not np.isfinite(qpos).all():
            raise ValueError(f"qpos: expected {self.model.nq} finite numbers, got shape {qpos.shape}")
        self._data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self._data)
        mujoco.mj_comPos(self.model, self._data)
        mujoco.mj_camlight(self.model, self._data)

    def render(self, qpos: Any) -> np.ndarray:
        """The camera's frame at ``qpos (nq,)``: ``(H, W, 3)`` RGB or ``(H, W)`` grey uint8 (sensor applied).

        Without read noise one ``qpos`` renders the identical frame each time,
        which the tracker takes for a frozen camera (``"stale"``).
        """
        self._set(qpos)
        return apply_sensor(self._renderer.render(self._data), self.settings, self._rng)

    def frames(self, qpos: Iterable[Any], times: Iterable[float]) -> Iterator[tuple[np.ndarray, float]]:
        """A frame source: ``(render(q), t)`` for each configuration and capture time (s)."""
        for q, t in zip(qpos, times):
            yield self.render(q), float(t)

    def truth(self, qpos: Any) -> TagTruth:
        """The tag's pose and Jacobian in the camera frame at ``qpos (nq,)`` (:class:`TagTruth`)."""
        self._set(qpos)
        R_wc = self._R
        position = R_wc.T @ (self._data.site_xpos[self._site] - self._p)
        rotation = R_wc.T @ self._data.site_xmat[self._site].reshape(3, 3)
        quaternion = np.empty(4)
        mujoco.mju_mat2Quat(quaternion, rotation.reshape(-1))
        if quaternion[0] < 0:
            quaternion = -quaternion
        jacp = np.zeros((3, self.model.nv))
        jacr = np.zeros((3, self.model.nv))
        mujoco.mj_jacSite(self.model, self._data, jacp, jacr, self._site)
        return TagTruth(position, quaternion, rotation, np.concatenate([R_wc.T @ jacp, R_wc.T @ jacr]))

    def close(self) -> None:
        """Free the renderer's OpenGL context."""
        self._renderer.close()

    def __enter__(self) -> SimCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def board_image(cols: int, rows: int, *, square_px: int = 40, margin_squares: float = 1.0) -> np.ndarray:
    """``(h, w) uint8`` checkerboard with ``cols x rows`` inner corners (OpenCV's count) and a white margin.

    ``(cols + 1) x (rows + 1)`` squares of ``square_px`` pixels, the top-left one black.
    """
    if cols < 2 or rows < 2:
        raise ValueError(f"board: expected at least 2x2 inner corners, got {cols}x{rows}")
    yy, xx = np.mgrid[0:(rows + 1) * square_px, 0:(cols + 1) * square_px]
    squares = np.where(((yy // square_px) + (xx // square_px)) % 2 == 0, 0, 255).astype(np.uint8)
    pad = int(round(margin_squares * square_px))
    return cv2.copyMakeBorder(squares, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)


class BoardCamera:
    """A generated checkerboard (``board = (cols, rows, square_m)``, inner corners) posed freely before a camera.

    :meth:`render` draws the board with its centre at ``position (3,)`` (m,
    world) and orientation ``quaternion (4,)`` (wxyz; the board faces its +z,
    its top row at +y). The scene holds nothing else.
    """

    _XML = """<mujoco><worldbody><body name="board" mocap="true"/></worldbody></mujoco>"""

    def __init__(self, board: tuple[int, int, float], camera: CameraSettings = CameraSettings()) -> None:
        cols, rows, square = board
        if not (isinstance(cols, int) and isinstance(rows, int)) or not (math.isfinite(square) and square > 0):
            raise ValueError(f"board: expected (cols, rows, square_m) with whole cols, rows and square_m > 0, "
                             f"got {board!r}")
        self.settings = check_settings(camera)
        image = board_image(cols, rows)
        scale = square / 40.0  # metres per texture pixel
        spec = mujoco.MjSpec.from_string(self._XML)
        add_textured_quad(spec, spec.body("board"), name="board_quad", image=image,
                          half_size=(0.5 * image.shape[1] * scale, 0.5 * image.shape[0] * scale))
        add_camera(spec, camera, name=_CAMERA)
        self.model = spec.compile()
        self._data = mujoco.MjData(self.model)
        self._rng = np.random.default_rng(camera.seed)
        self.intrinsics = Intrinsics(camera_matrix(camera.width, camera.height, camera.fovy), np.zeros(5),
                                     int(camera.width), int(camera.height))
        self._renderer = OffscreenRenderer(self.model, camera=_CAMERA, width=camera.width, height=camera.height)

    def render(self, position: ArrayLike, quaternion: ArrayLike) -> np.ndarray:
        """The frame with the board at ``position (3,)`` m and ``quaternion (4,)`` wxyz (world frame)."""
        self._data.mocap_pos[0] = np.asarray(position, dtype=np.float64)
        q = np.asarray(quaternion, dtype=np.float64)
        self._data.mocap_quat[0] = q / np.linalg.norm(q)
        mujoco.mj_kinematics(self.model, self._data)
        mujoco.mj_camlight(self.model, self._data)
        return apply_sensor(self._renderer.render(self._data), self.settings, self._rng)

    def close(self) -> None:
        """Free the renderer's OpenGL context."""
        self._renderer.close()

    def __enter__(self) -> BoardCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def board_views(camera: CameraSettings, n: int, *, distance: float, tilt: float = 30.0, spread: float = 0.3,
                seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` board poses ``(position (3,), quaternion (4,))`` facing ``camera`` at about ``distance`` m.

    Each is tilted up to ``tilt`` degrees about a random in-plane axis and
    rolled up to 15 degrees, its centre offset sideways up to ``spread`` times
    the distance, so that the views constrain the focal length and the
    principal point (calibration needs tilted views).
    """
    rng = np.random.default_rng(seed)
    R_wc = camera_rotation(camera.position, camera.look_at, camera.up)
    p = np.asarray(camera.position, dtype=np.float64)
    # facing the camera: board +z towards the camera (-z_cam), board +y up in the image (-y_cam)
    R_face = R_wc @ np.diag([1.0, -1.0, -1.0])
    views = []
    for _ in range(n):
        axis_angle = rng.uniform(0, 2 * np.pi)
        tilt_vec = math.radians(rng.uniform(0.3, 1.0) * tilt) * np.array([np.cos(axis_angle), np.sin(axis_angle), 0])
        roll = math.radians(rng.uniform(-15.0, 15.0))
        tilt_q, roll_q, board_q = np.empty(4), np.empty(4), np.empty(4)
        angle = float(np.linalg.norm(tilt_vec))
        mujoco.mju_axisAngle2Quat(tilt_q, tilt_vec / max(angle, 1e-12), angle)
        mujoco.mju_axisAngle2Quat(roll_q, np.array([0.0, 0.0, 1.0]), roll)
        face_q = np.empty(4)
        mujoco.mju_mat2Quat(face_q, R_face.reshape(-1))
        mujoco.mju_mulQuat(board_q, face_q, tilt_q)
        mujoco.mju_mulQuat(board_q, board_q.copy(), roll_q)
        offset = rng.uniform(-spread, spread, size=2) * distance
        position = p + R_wc @ np.array([offset[0], offset[1], distance * rng.uniform(0.9, 1.1)])
        views.append((position, board_q))
    return views
