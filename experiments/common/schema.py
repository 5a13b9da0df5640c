"""The domain config blocks the experiments share: the self-ID magnitude, error-scaling grids, the controller, the path.

Each is a strict, frozen pydantic model (:data:`selfid_jax.runner.config.STRICT`);
:class:`StudyConfig` is the base of every experiment config here, adding the
check that the controller's tolerance fits the path.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, NamedTuple, TypeAlias, cast

import jax
import numpy as np
from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax.control.loop import DEFAULT_STEPS, ControllerParams
from selfid_jax.runner.config import STRICT, BaseConfig, stop_after_start

__all__ = ["ControllerConfig", "EpsLimits", "HostOrDevice", "Magnitude", "MagnitudeSource", "PathConfig",
           "SelfIdConfig", "SelfIdMagnitude", "StudyConfig", "add_m_a_columns", "check_noise_pairs", "controller_rows",
           "format_m_a", "m_a_columns", "m_a_summary", "resolve_m_a"]


HostOrDevice: TypeAlias = jax.Array | np.ndarray
"""An array field of an experiment's traced ``Params``: filled with numpy arrays on the host, a ``jax.Array`` once
traced."""

MagnitudeSource: TypeAlias = Literal["system", "config"]
"""Where a :class:`SelfIdMagnitude` came from: the system's own ``m_a`` or the experiment's ``m_a`` key."""

Magnitude = Annotated[float, Field(gt=0)] | Annotated[list[Annotated[float, Field(gt=0)]], Field(min_length=1)]
"""A self-ID magnitude ``m_a`` in a config: one number, or one per actuator [rad or m], > 0."""


class SelfIdMagnitude(NamedTuple):
    """The self-ID magnitude an experiment uses for one system, and where it came from."""

    value: np.ndarray  # (n_act,) float64 [rad or m]
    source: MagnitudeSource  # the system's own m_a, or the experiment's m_a key

    def summary(self) -> dict[str, Any]:
        """``{"m_a": number (all actuators equal) or list, "m_a_source": "system" | "config"}`` for summary.json."""
        v = [float(x) for x in self.value]
        return {"m_a": v[0] if len(set(v)) == 1 else v, "m_a_source": self.source}


def resolve_m_a(m_a, system, where: str = "m_a") -> SelfIdMagnitude:
    """THE m_a rule: the experiment's ``m_a`` (scalar or per actuator) if given, else the system's own ``m_a``.

    ``system`` is a :class:`selfid_jax.systems.System` (its ``m_a`` is ``(n_act,)``);
    ``ValueError`` naming ``where`` if a per-actuator list has the wrong length.
    """
    n = int(system.n_act)
    if m_a is None:
        own = np.asarray(system.m_a).reshape(n)
        if own.dtype == np.float32:  # the shortest decimal of each float32 (0.03, not 0.029999999329)
            own = np.array([float(np.format_float_positional(v, unique=True)) for v in own])
        return SelfIdMagnitude(own.astype(float), "system")
    value = np.asarray(m_a, float)
    if value.ndim == 1 and value.shape != (n,):
        raise ValueError(f"{where}: {len(value)} values for the {n} actuators of {system.name!r} "
                         "(give one number or one per actuator)")
    return SelfIdMagnitude(np.broadcast_to(value, (n,)).copy(), "config")


def add_m_a_columns(meta, choice: SelfIdMagnitude, prefix: str = "") -> None:
    """Record ``choice`` in every row of ``meta`` (in place): ``{prefix}m_a`` (the ``(n_act,)`` values) and its source.

    The columns reach ``results.parquet``, so ``summarize`` (which reads the
    table only) can say which magnitude each system used (:func:`m_a_summary`).
    """
    meta[f"{prefix}m_a"] = [tuple(choice.value.tolist())] * len(meta)  # tuples: the run manifest hashes meta
    meta[f"{prefix}m_a_source"] = choice.source


def m_a_columns(prefix: str = "", of: str = "") -> dict[str, str]:
    """The results-column documentation (an ``Experiment``'s ``columns``) of :func:`add_m_a_columns`' columns."""
    return {
        f"{prefix}m_a": f"(n_act,) self-ID actuation magnitude per actuator{of} [rad or m: the actuator's unit]",
        f"{prefix}m_a_source": f"where {prefix}m_a came from: 'system' (the system's own) or 'config' (the m_a key) "
                               "[label]",
    }


def m_a_summary(rows, prefix: str = "", vector: str | None = None) -> dict[str, Any]:
    """``{"m_a": ..., "m_a_source": ...}`` of the rows of one system (columns of :func:`add_m_a_columns`).

    ``vector``: the column holding the per-actuator list, if not ``{prefix}m_a``.
    """
    first = rows.iloc[0]
    source = cast(MagnitudeSource, str(first[f"{prefix}m_a_source"]))  # written by add_m_a_columns
    return SelfIdMagnitude(np.asarray(first[vector or f"{prefix}m_a"], float), source).summary()


def format_m_a(value) -> str:
    """``m_a`` of a summary for a figure title: ``0.03`` or ``[0.02, 0.05]``."""
    return f"{value:g}" if np.ndim(value) == 0 else "[" + ", ".join(f"{v:g}" for v in value) + "]"


class SelfIdConfig(BaseModel):
    """The self-ID magnitude every experiment reads the same way (:func:`resolve_m_a`).

    ``m_a`` left out: the system's own ``m_a`` (its spec's ``m_a``, or the
    built-in robot's safe magnitude); given: it overrides the system's, one
    number or one per actuator. ``summary.json`` states which was used.
    """

    model_config = STRICT

    m_a: Magnitude | None = Field(None, description="self-ID magnitude [rad or m], one number or one per actuator "
                                  "(default: the system's own m_a)")

    def magnitude(self, system, where: str = "m_a") -> SelfIdMagnitude:
        """The ``(n_act,)`` magnitude this config gives ``system`` and its source (:func:`resolve_m_a`)."""
        return resolve_m_a(self.m_a, system, where)


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


_PARAMS = ControllerParams._field_defaults  # the one place the traced controller defaults are written


class ControllerConfig(BaseModel):
    """Inverse-Jacobian path-following protocol (state it beside every bound).

    The defaults are read from :class:`selfid_jax.control.ControllerParams`
    and ``control.DEFAULT_STEPS`` (the UR5e protocol of the shipped configs),
    never restated here. ``steps`` is static (the scan length); the rest are
    traced, see :meth:`traced`.
    """

    model_config = STRICT

    max_step: float = Field(_PARAMS["max_step"], gt=0, le=1, description="largest POM step per control step [m]")
    tol: float = Field(_PARAMS["tol"], gt=0, le=1, description="waypoint reached when closer than this [m]")
    steps: int = Field(DEFAULT_STEPS, ge=1, le=10**6, description="control-step budget per rollout")
    gain: float = Field(_PARAMS["gain"], gt=0, le=10, description="fraction of the correction applied per step")
    max_rot_step: float = Field(_PARAMS["max_rot_step"], gt=0, le=3.14,
                                description="largest rotation step per control step [rad] (6-D tasks)")
    rot_tol: float = Field(_PARAMS["rot_tol"], gt=0, le=3.14,
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
    return ControllerParams(**{k: np.full((n_rows,), float(v)) for k, v in controller.traced().items()})
