"""Headless rendering for the simulated cameras: a fixed camera in an ``MjSpec``, textured quads, offscreen frames.

The parts :mod:`~selfid_jax.robot.camera.sim` builds its scenes from:

* :class:`CameraSettings`: resolution, vertical field of view, pose (position
  and look-at point in the world frame) and the sensor's non-idealities
  (pixel noise, blur, exposure and gain);
* :func:`camera_rotation` and :func:`camera_matrix`: the camera's frame in
  OpenCV's convention (x right, y down, z forward) and the pinhole matrix that
  matches MuJoCo's projection (square pixels, ``fy = (H / 2) / tan(fovy / 2)``,
  principal point at the image centre ``((W - 1) / 2, (H - 1) / 2)`` in
  OpenCV's pixel-centre coordinates);
* :func:`add_camera` and :func:`add_textured_quad`: a fixed camera and a flat
  textured square (a tag, a checkerboard) added to an ``mujoco.MjSpec``;
* :class:`OffscreenRenderer`: RGB frames ``(H, W, 3) uint8`` from a compiled
  model's camera, through an OpenGL context chosen by ``MUJOCO_GL`` (``egl``
  by default: headless, with a GPU driver or Mesa's software rasteriser;
  ``osmesa`` and ``glfw`` where asked for). The context is created here, not
  by ``mujoco.Renderer``, so rendering works whichever backend ``mujoco``
  picked when it was first imported. No backend: :class:`RenderUnavailable`;
* :func:`apply_sensor`: blur (optics), exposure, gain and Gaussian read noise
  (sensor) and 8-bit quantisation applied to a rendered frame.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco loads its GL backend, where this module imports it first

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import cv2
import mujoco
import numpy as np

__all__ = ["CameraSettings", "OffscreenRenderer", "RenderUnavailable", "add_camera", "add_textured_quad",
           "apply_sensor", "camera_matrix", "camera_rotation", "check_settings"]


class RenderUnavailable(RuntimeError):
    """No OpenGL context could be created for offscreen rendering (no EGL/OSMesa library or device)."""


class CameraSettings(NamedTuple):
    """A simulated camera: optics, pose and sensor."""

    width: int = 640  # image width, pixels
    height: int = 480  # image height, pixels
    fovy: float = 45.0  # vertical field of view, degrees
    position: tuple[float, float, float] = (1.0, 0.0, 0.6)  # camera centre, m, world frame
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.3)  # point on the optical axis, m, world frame
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)  # world direction that appears up in the image
    noise: float = 0.0  # std of Gaussian read noise, grey levels (0-255) at gain 1
    blur: float = 0.0  # std of a Gaussian blur (defocus, motion), pixels; 0: none
    exposure: float = 1.0  # scales the light collected (exposure time x aperture); < 1 darkens the frame
    gain: float = 1.0  # scales signal and read noise together (the sensor's analogue gain)
    gray: bool = False  # frames (H, W) grey instead of (H, W, 3) RGB
    seed: int = 0  # seed of the noise generator


def check_settings(settings: CameraSettings) -> CameraSettings:
    """Validate a :class:`CameraSettings` (positive sizes, a field of view in (0, 180), a usable pose)."""
    for key in ("width", "height"):
        value = getattr(settings, key)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
            raise ValueError(f"camera {key}: expected a positive whole number of pixels, got {value!r}")
    if not 0.0 < float(settings.fovy) < 180.0:
        raise ValueError(f"camera fovy: expected degrees in (0, 180), got {settings.fovy!r}")
    for key in ("noise", "blur", "exposure", "gain"):
        value = float(getattr(settings, key))
        if not math.isfinite(value) or value < 0.0:
            raise ValueError(f"camera {key}: expected a finite number >= 0, got {getattr(settings, key)!r}")
    camera_rotation(settings.position, settings.look_at, settings.up)  # raises on a degenerate pose
    return settings


def camera_rotation(position: Sequence[float], look_at: Sequence[float],
                    up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """The camera's axes in the world frame, OpenCV's convention: ``(3, 3)`` columns x right, y down, z forward.

    ``R @ p_cam + position = p_world``; MuJoCo's camera frame (x right, y up,
    looking along -z) is ``R @ diag(1, -1, -1)``.
    """
    p, target, u = (np.asarray(v, dtype=np.float64).reshape(3) for v in (position, look_at, up))
    forward = target - p
    if not np.isfinite(forward).all() or np.linalg.norm(forward) < 1e-9:
        raise ValueError(f"camera pose: look_at {target.tolist()} must differ from position {p.tolist()}")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, u)
    if float(np.linalg.norm(right)) < 1e-6 * max(float(np.linalg.norm(u)), 1e-12):
        raise ValueError(f"camera pose: up {u.tolist()} is parallel to the viewing direction {forward.tolist()}")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=1)


def camera_matrix(width: int, height: int, fovy: float) -> np.ndarray:
    """``(3, 3)`` pinhole matrix of MuJoCo's camera with vertical field of view ``fovy`` (deg), square pixels.

    MuJoCo's OpenGL frustum spans the image's outer pixel edges, so the optical
    axis passes through OpenCV's pixel coordinate ``((W - 1) / 2, (H - 1) / 2)``.
    """
    f = 0.5 * height / math.tan(math.radians(fovy) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def add_camera(spec: Any, settings: CameraSettings, *, name: str = "selfid_camera") -> None:
    """Add ``settings``' fixed camera to ``spec``'s world body and size the offscreen buffer for it.

    Also sets the headlight (a light at the camera, like a ring light) to a
    moderate level, so that a scene without lights of its own is lit.
    """
    check_settings(settings)
    R = camera_rotation(settings.position, settings.look_at, settings.up)
    camera = spec.worldbody.add_camera(name=name, pos=[float(x) for x in settings.position],
                                       fovy=float(settings.fovy))
    camera.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    camera.alt.xyaxes = np.concatenate([R[:, 0], -R[:, 1]])  # MuJoCo's x right, y up
    visual = spec.visual
    visual.global_.offwidth = max(int(visual.global_.offwidth), int(settings.width))
    visual.global_.offheight = max(int(visual.global_.offheight), int(settings.height))
    visual.headlight.ambient = [0.35, 0.35, 0.35]
    visual.headlight.diffuse = [0.55, 0.55, 0.55]
    visual.headlight.specular = [0.0, 0.0, 0.0]


def add_textured_quad(spec: Any, body: Any, *, name: str, image: np.ndarray, half_size: tuple[float, float],
                      pos: Sequence[float] = (0.0, 0.0, 0.0), quat: Sequence[float] = (1.0, 0.0, 0.0, 0.0)) -> None:
    """Add a flat rectangle showing ``image`` (``(h, w)`` or ``(h, w, 3)`` uint8) to ``body`` of ``spec``.

    The rectangle lies in the x-y plane of the frame ``pos``, ``quat`` (wxyz)
    of ``body``, ``2 half_size[0]`` wide along x and ``2 half_size[1]`` high
    along y (m), facing +z; the image's top row is at +y and its left column
    at -x, as a viewer on the +z side sees it. It has no mass to speak of and
    collides with nothing; a site ``name`` marks its centre and frame.
    """
    image = np.asarray(image, dtype=np.uint8)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"texture image: expected (h, w) or (h, w, 3) uint8, got shape {image.shape}")
    texture = spec.add_texture(name=f"{name}_texture", type=mujoco.mjtTexture.mjTEXTURE_2D,
                               width=image.shape[1], height=image.shape[0], nchannel=3)
    texture.data = np.ascontiguousarray(image).tobytes()
    material = spec.add_material(name=f"{name}_material")
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = texture.name
    material.specular = 0.0
    material.shininess = 0.0
    material.reflectance = 0.0
    material.emission = 0.3  # the printed tag stays legible in a dim scene; exposure still darkens it
    hx, hy = (float(v) for v in half_size)
    mesh = spec.add_mesh(name=f"{name}_mesh")
    mesh.uservert = [-hx, -hy, 0.0, hx, -hy, 0.0, hx, hy, 0.0, -hx, hy, 0.0]
    mesh.usertexcoord = [0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0]  # texture row 0 (v = 0) at +y
    mesh.userface = [0, 1, 2, 0, 2, 3]
    mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL  # a flat mesh has no volume
    pos = [float(v) for v in pos]
    quat = [float(v) for v in quat]
    body.add_geom(name=f"{name}_geom", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh.name,
                  material=material.name, pos=pos, quat=quat, contype=0, conaffinity=0, mass=1e-9)
    body.add_site(name=name, pos=pos, quat=quat, size=[1e-3, 1e-3, 1e-3], rgba=[0.0, 0.0, 0.0, 0.0])


_FAILED: list[str] = []  # the first failure to create a context in this process, its message


def _gl_context_class() -> Any:
    backend = os.environ.get("MUJOCO_GL", "egl").strip().lower() or "egl"
    try:
        if backend == "egl":
            from mujoco.egl import GLContext
        elif backend == "osmesa":
            from mujoco.osmesa import GLContext
        elif backend in ("glfw", "glx"):
            from mujoco.glfw import GLContext
        else:
            raise RenderUnavailable(f"MUJOCO_GL={backend!r}: offscreen rendering needs egl (headless), osmesa or "
                                    "glfw")
    except (ImportError, OSError, RuntimeError, AttributeError) as err:
        if isinstance(err, RenderUnavailable):
            raise
        _FAILED.append(f"no OpenGL backend for MUJOCO_GL={backend} ({type(err).__name__}: {err}); headless "
                       "rendering needs libEGL (a GPU driver or Mesa)")
        raise RenderUnavailable(_FAILED[0]) from err
    return GLContext


class OffscreenRenderer:
    """Frames from one fixed camera of a compiled model: ``render(data) -> (height, width, 3) uint8`` RGB.

    ``data`` must hold the kinematics and camera poses of the state to draw
    (``mj_kinematics`` and ``mj_camlight``). One OpenGL context per renderer,
    made current at each frame, so several renderers coexist in one thread.
    """

    def __init__(self, model: Any, *, camera: str, width: int, height: int) -> None:
        self._gl: Any = None
        self._context: Any = None
        camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if camera_id < 0:
            raise ValueError(f"camera {camera!r} is not in the model")
        if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
            raise ValueError(f"frame {width}x{height} exceeds the offscreen buffer {model.vis.global_.offwidth}x"
                             f"{model.vis.global_.offheight} (add_camera sizes it)")
        if _FAILED:  # a backend that failed once is not tried again (a second glfw try aborts the process)
            raise RenderUnavailable(_FAILED[0])
        context_class = _gl_context_class()
        try:
            self._gl = context_class(width, height)
            self._gl.make_current()
            self._context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        except Exception as err:  # every backend fails its own way (EGLError, GLError, mujoco's); re-raised
            self.close()
            backend = os.environ.get("MUJOCO_GL", "egl")
            _FAILED.append(f"cannot create an offscreen OpenGL context with MUJOCO_GL={backend} "
                           f"({type(err).__name__}: {err})")
            raise RenderUnavailable(_FAILED[0]) from err
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._context)
        self.width, self.height = int(width), int(height)
        self._model = model
        self._scene = mujoco.MjvScene(model, maxgeom=max(1000, 2 * model.ngeom))
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._camera.fixedcamid = camera_id
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self._buffer = np.empty((self.height, self.width, 3), dtype=np.uint8)

    def render(self, data: Any) -> np.ndarray:
        """``(height, width, 3) uint8`` RGB frame of ``data``'s state, top row first."""
        if self._context is None:
            raise RuntimeError("the renderer is closed")
        self._gl.make_current()
        mujoco.mjv_updateScene(self._model, data, self._option, self._perturb, self._camera,
                               mujoco.mjtCatBit.mjCAT_ALL, self._scene)
        mujoco.mjr_render(self._rect, self._scene, self._context)
        mujoco.mjr_readPixels(self._buffer, None, self._rect, self._context)
        return np.flipud(self._buffer).copy()  # OpenGL's rows run bottom-up

    def close(self) -> None:
        """Free the OpenGL resources (idempotent)."""
        if self._context is not None:
            self._context.free()
            self._context = None
        if self._gl is not None:
            self._gl.free()
            self._gl = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - nothing to report to at interpreter shutdown
            pass


def apply_sensor(frame: np.ndarray, settings: CameraSettings, rng: np.random.Generator) -> np.ndarray:
    """The sensor's view of a rendered RGB frame ``(H, W, 3) uint8``: blur, exposure, gain, read noise, 8 bits.

    ``out = clip(round(gain (exposure blur(frame) + N(0, noise^2))), 0, 255)``
    per pixel and channel; ``(H, W)`` when ``settings.gray``.
    """
    image: np.ndarray = frame.astype(np.float32)
    if settings.blur > 0:
        image = cv2.GaussianBlur(image, (0, 0), sigmaX=float(settings.blur), sigmaY=float(settings.blur))
    if settings.gray:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    image *= float(settings.exposure)
    if settings.noise > 0:
        image += rng.normal(0.0, float(settings.noise), size=image.shape).astype(np.float32)
    image *= float(settings.gain)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
