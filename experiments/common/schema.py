"""The domain config blocks the experiments share: error-scaling grids, the controller protocol, the path.

Each is a strict, frozen pydantic model (:data:`selfid_jax.runner.config.STRICT`);
:class:`StudyConfig` is the base of every experiment config here, adding the
check that the controller's tolerance fits the path.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax.runner.config import STRICT, BaseConfig, stop_after_start

__all__ = ["ControllerConfig", "EpsLimits", "PathConfig", "StudyConfig", "check_noise_pairs", "controller_rows"]


class EpsLimits(BaseModel):
    """A linspace grid of inverse-Jacobian error scalings ``eps_limit`` (dimensionless)."""

    model_config = STRICT

    start: float = Field(ge=0, le=100)
    stop: float = Field(le=100, description="greater than start")
    num: int = Field(ge=2, le=10**5, description="number of grid points")

    _stop_after_start = field_validator("stop")(stop_after_start)

    def values(self) -> np.ndarray:
        """The grid, shape ``(num,)``, float64."""
        return np.linspace(self.start, self.stop, self.num)


class ControllerConfig(BaseModel):
    """Inverse-Jacobian path-following protocol (state it beside every bound).

    The defaults are :class:`selfid_jax.control.ControllerParams`' and
    ``control.follow``'s (the UR5e protocol of the shipped configs). ``steps``
    is static (the scan length); the rest are traced, see :meth:`traced`.
    """

    model_config = STRICT

    max_step: float = Field(0.0025, gt=0, le=1, description="largest POM step per control step [m]")
    tol: float = Field(0.0005, gt=0, le=1, description="waypoint reached when closer than this [m]")
    steps: int = Field(435, ge=1, le=10**6, description="control-step budget per rollout")
    gain: float = Field(1.0, gt=0, le=10, description="fraction of the correction applied per step")
    max_rot_step: float = Field(0.05, gt=0, le=3.14,
                                description="largest rotation step per control step [rad] (6-D tasks)")
    rot_tol: float = Field(0.01, gt=0, le=3.14,
                           description="waypoint orientation reached within this [rad] (6-D tasks)")

    def traced(self) -> dict[str, float]:
        """The swept numbers (every field but ``steps``), the fields of ``control.ControllerParams``."""
        return self.model_dump(exclude={"steps"})


class PathConfig(BaseModel):
    """Reference path traced by the point of manipulation."""

    model_config = STRICT

    kind: Literal["star"] = "star"
    size: float = Field(gt=0, le=10, description="path extent [m]")

    def check_controller(self, controller: ControllerConfig) -> None:
        """``ValueError`` unless the tolerance is below half the path's size (else waypoints count as reached at the
        start)."""
        if not controller.tol < self.size / 2:
            raise ValueError(f"controller.tol ({controller.tol}) must be below half of path.size ({self.size}): "
                             "waypoints would count as reached without moving")


def check_noise_pairs(pose_noise: list, rot_noise: list) -> None:
    """``ValueError`` unless the tracker-noise lists pair up level by level (equal lengths)."""
    if len(pose_noise) != len(rot_noise):
        raise ValueError(f"pose_noise and rot_noise pair up level by level: lengths {len(pose_noise)} "
                         f"and {len(rot_noise)} differ")


class StudyConfig(BaseConfig):
    """Base of the experiment configs: :class:`BaseConfig`'s fields, and a tolerance that fits the path."""

    def input_files(self) -> dict[str, str]:
        """Every file the config's systems read (MJCF/URDF files and theirs, pose-function modules), path -> SHA-256."""
        found: dict[str, str] = {}

        def walk(value) -> None:
            if isinstance(value, BaseModel):
                if value is not self and hasattr(value, "input_files"):
                    found.update(value.input_files())
                    return
                for name in type(value).model_fields:
                    walk(getattr(value, name))
            elif isinstance(value, (list, tuple)):
                for v in value:
                    walk(v)
            elif isinstance(value, dict):
                for v in value.values():
                    walk(v)

        walk(self)
        return found

    @model_validator(mode="after")
    def _controller_fits_path(self):
        """Experiments with a ``path`` and a ``controller``: the tolerance must fit the path."""
        path, controller = getattr(self, "path", None), getattr(self, "controller", None)
        if isinstance(path, PathConfig) and isinstance(controller, ControllerConfig):
            path.check_controller(controller)
        return self


def controller_rows(controller: ControllerConfig, n_rows: int):
    """The traced controller settings of ``controller`` repeated for ``n_rows`` rows: ``ControllerParams`` of
    ``(N,)``."""
    from selfid_jax.control import ControllerParams

    return ControllerParams(**{k: np.full((n_rows,), float(v)) for k, v in controller.traced().items()})
