"""The camera as the tracker: AprilTag poses from frames, intrinsics files, calibration and a simulated camera.

Needs the ``camera`` extra (``opencv-python-headless``). :mod:`~selfid_jax.robot.camera.tracker`
maps frames ``(frame, capture_time)`` to the tag's pose in the camera frame or a
dropout with its reason; :mod:`~selfid_jax.robot.camera.intrinsics` reads and
writes OpenCV's and ROS's calibration YAML; :mod:`~selfid_jax.robot.camera.calibrate`
estimates intrinsics from checkerboard views; :mod:`~selfid_jax.robot.camera.sim`
renders an MJCF arm with a generated tag headless (:mod:`~selfid_jax.robot.camera.render`,
``MUJOCO_GL=egl``) with its ground truth; :mod:`~selfid_jax.robot.camera.measure`
measures the tracker on it; :mod:`~selfid_jax.robot.camera.sources` reads a video,
a folder of images or a bag's image topic for ``sj.fit`` / ``selfid-jax fit``.
Modules are imported on first use (listed once in
``__init__.pyi``), so importing this package loads neither OpenCV nor OpenGL.
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
