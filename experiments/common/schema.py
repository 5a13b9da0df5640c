"""The domain config blocks the experiments share: self-ID magnitude, error-scaling grids, controller, path, realism.

Each is a strict, frozen pydantic model (:data:`selfid_jax.runner.config.STRICT`);
:class:`StudyConfig` is the base of every experiment config here, adding the
check that the controller's tolerance fits the path.

Size: about 480 lines, one class per config block the experiments share; split by topic, each
experiment would import its blocks from several modules.
"""

from __future__ import annotations

import itertools
import math
from typing import Annotated, Any, Literal, NamedTuple, TypeAlias, cast

import jax
import numpy as np
from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax.control.loop import DEFAULT_STEPS, ControllerParams
from selfid_jax.control.realism import Realism
from selfid_jax.runner.config import STRICT, BaseConfig, stop_after_start
from selfid_jax.runner.grids import decimal_linspace

__all__ = ["ControllerConfig", "EpsLimits", "HostOrDevice", "M_A_LABEL", "Magnitude", "MagnitudeSource",
           "NOISE_COLUMNS", "PathConfig", "PoseNoise", "REALISM_FIELDS", "RealismConfig", "RealismRows", "RotNoise",
           "SelfIdConfig", "SelfIdMagnitude", "SelfIdRealismConfig", "StartsConfig", "StudyConfig",
           "TrackerNoiseConfig", "add_m_a_columns", "check_noise_pairs", "check_realism_noise", "controller_rows",
           "format_m_a", "m_a_columns", "m_a_label", "m_a_summary", "realism_columns", "resolve_m_a"]


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


def m_a_label(value) -> float:
    """The one number of the ``m_a`` results column for a ``(n_act,)`` magnitude: the value where every actuator
    has the same, else the geometric mean over actuators [rad or m]."""
    v = np.asarray(value, float).reshape(-1)
    return float(v[0]) if np.all(v == v[0]) else float(np.exp(np.log(v).mean()))


def add_m_a_columns(meta, choice: SelfIdMagnitude, prefix: str = "") -> None:
    """Record ``choice`` in every row of ``meta`` (in place): ``{prefix}m_a`` (one number, :func:`m_a_label`),
    ``{prefix}m_a_vec`` (the ``(n_act,)`` values) and ``{prefix}m_a_source``.

    The columns reach ``results.parquet``, so ``summarize`` (which reads the
    table only) can say which magnitude each system used (:func:`m_a_summary`).
    Every experiment writes ``m_a`` as a float and ``m_a_vec`` per actuator, so
    a table filters and groups by ``m_a`` the same way whichever wrote it.
    """
    meta[f"{prefix}m_a"] = m_a_label(choice.value)
    meta[f"{prefix}m_a_vec"] = [tuple(choice.value.tolist())] * len(meta)  # tuples: the run manifest hashes meta
    meta[f"{prefix}m_a_source"] = choice.source


M_A_LABEL = "the value where all actuators have the same, else the geometric mean over actuators"
"""What the ``m_a`` results column holds (:func:`m_a_label`), for the experiments' ``COLUMNS``."""


def m_a_columns(prefix: str = "", of: str = "") -> dict[str, str]:
    """The results-column documentation (an ``Experiment``'s ``columns``) of :func:`add_m_a_columns`' columns."""
    return {
        f"{prefix}m_a": f"self-ID actuation magnitude{of}: {M_A_LABEL} (per actuator: {prefix}m_a_vec) "
                        "[rad or m: the actuator's unit]",
        f"{prefix}m_a_vec": f"(n_act,) self-ID actuation magnitude per actuator{of} [rad or m: the actuator's unit]",
        f"{prefix}m_a_source": f"where {prefix}m_a came from: 'system' (the system's own) or 'config' (the m_a key) "
                               "[label]",
    }


def m_a_summary(rows, prefix: str = "", vector: str | None = None) -> dict[str, Any]:
    """``{"m_a": ..., "m_a_source": ...}`` of the rows of one system (columns of :func:`add_m_a_columns`).

    ``vector``: the column holding the per-actuator values, if not ``{prefix}m_a_vec``. A table written before
    ``m_a_vec`` existed holds the per-actuator values in ``{prefix}m_a`` itself, and is read from there.
    """
    first = rows.iloc[0]
    source = cast(MagnitudeSource, str(first[f"{prefix}m_a_source"]))  # written by add_m_a_columns
    column = vector or f"{prefix}m_a_vec"
    if column not in rows.columns and np.ndim(first[f"{prefix}m_a"]) == 1:  # an older run: m_a was the vector
        column = f"{prefix}m_a"
    return SelfIdMagnitude(np.asarray(first[column], float), source).summary()


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
        """The grid, shape ``(num,)``, float64: ``linspace`` with each point its 12-digit decimal (0.35, not
        0.35000000000000003: the value swept is the value written, :func:`selfid_jax.runner.grids.decimal_linspace`)."""
        return decimal_linspace(self.start, self.stop, self.num)


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


# ------------------------------------------------------------------ realism

MAX_REALISM_LEVELS = 10**4
"""Most combinations a ``realism`` section may expand to (the product of its lists' lengths)."""

_Sweep = Annotated[list[float], Field(min_length=1, max_length=1000)]


def _listed(value: Any) -> Any:
    """A scalar given for a sweepable realism value is a one-value list (the section's values are lists inside)."""
    return value if isinstance(value, list) else [value]


REALISM_FIELDS = Realism._fields
"""The swept values of a ``realism`` section, in grid order (last fastest): the fields of
:class:`selfid_jax.control.realism.Realism`, named the same from YAML to the kernel."""


class RealismRows(NamedTuple):
    """The traced realism values of ``N`` rows (:meth:`RealismConfig.rows`)."""

    realism: Realism  # each field (N,): float64, latency int32
    settle: np.ndarray | None  # (N,) int32 control steps a self-ID sample waits; None without self-ID


class RealismConfig(BaseModel):
    """The real loop's non-idealities (:mod:`selfid_jax.control.realism`): each value one number or a list to sweep.

    The rows of the experiment's grid are multiplied by every combination of
    the listed values (a ``realism_level`` axis, the last field fastest), and
    one compiled program serves them all: every value is traced, the
    tracker's history is sized by the largest ``latency``. Left out, the
    experiment runs the ideal loop, exactly as without the section; all
    values 0 (``realism: {}``) reproduce it bit for bit. The results table
    gets ``realism_level`` and one column per value. Start configurations
    are still those from which the ideal loop completes the path with the
    true inverse Jacobian, so every level starts from the same ones.
    Each value is one number or a list of them (a sweep).
    """

    model_config = STRICT

    period: _Sweep = Field([0.0], description="control period [s]; > 0 wherever servo_tau > 0")
    latency: Annotated[list[Annotated[int, Field(ge=0, le=1000)]], Field(min_length=1, max_length=1000)] = Field(
        [0], description="whole control steps between a pose and its tracker reading")
    noise_pos: _Sweep = Field([0.0], description="tracker position noise sd per axis [m]")
    noise_rot: _Sweep = Field([0.0], description="tracker rotation noise sd per axis [rad]")
    dropout: _Sweep = Field([0.0], description="probability that a tracker reading is missing, in [0, 0.99]")
    servo_tau: _Sweep = Field([0.0], description="first-order servo time constant [s] (0: no lag)")
    deadband: _Sweep = Field([0.0], description="actuator deadband: smaller commanded changes do not move "
                             "[rad or m]")
    plant: Literal["servo", "dynamic"] = Field(
        "servo", description="the actuators between control steps: 'servo', the kinematic model (servo_tau, "
        "deadband); 'dynamic', the arm's own position servos, inertia and gravity stepped in MJX (an arm whose "
        "actuators are position servos: ur5e or an mjcf arm); one period, a multiple of the model's timestep")
    gravcomp: float = Field(1.0, ge=0.0, le=1.0, description="with plant 'dynamic': the fraction of the links' "
                            "weight compensated (1: none sags, 0: the servos alone hold the arm up)")
    kp: float | None = Field(None, gt=0.0, le=1e8, description="with plant 'dynamic': every position servo's "
                             "stiffness [N m/rad or N/m] (default: the model file's)")
    kv: float | None = Field(None, ge=0.0, le=1e7, description="with plant 'dynamic': every servo's damping "
                             "[N m s/rad or N s/m] (default: the model file's)")

    _scalars_are_lists = field_validator(*REALISM_FIELDS, mode="before")(_listed)

    @field_validator("period", "noise_pos", "noise_rot", "dropout", "servo_tau", "deadband")
    @classmethod
    def _in_range(cls, values: list[float], info) -> list[float]:
        hi = {"period": 10.0, "noise_pos": 0.1, "noise_rot": 1.0, "dropout": 0.99, "servo_tau": 100.0,
              "deadband": 1.0}[info.field_name]
        bad = [v for v in values if not 0.0 <= v <= hi]
        if bad:
            raise ValueError(f"values must lie in [0, {hi:g}], got {bad}")
        return values

    @model_validator(mode="after")
    def _consistent(self):
        for name in self.swept_fields():
            values = getattr(self, name)
            if len(set(values)) != len(values):
                raise ValueError(f"realism.{name}: values must be unique, got {values}")
        if self.n_levels() > MAX_REALISM_LEVELS:
            raise ValueError(f"realism: {self.n_levels()} combinations of values; at most {MAX_REALISM_LEVELS}")
        if self.plant == "dynamic":
            if len(self.period) != 1 or self.period[0] <= 0:
                raise ValueError(f"realism.plant 'dynamic' needs one control period > 0 (it fixes the physics "
                                 f"steps per control step), got period {self.period}")
            for name in ("servo_tau", "deadband"):
                if any(v != 0 for v in getattr(self, name)):
                    raise ValueError(f"realism.{name} belongs to plant 'servo'; with plant 'dynamic' the arm's own "
                                     f"servos lag, so leave {name} at [0.0], got {getattr(self, name)}")
        else:
            for name, default in (("gravcomp", 1.0), ("kp", None), ("kv", None)):
                if getattr(self, name) != default:
                    raise ValueError(f"realism.{name} applies to plant 'dynamic' only")
        if any(t > 0 for t in self.servo_tau) and any(p <= 0 for p in self.period):
            raise ValueError(f"realism.servo_tau {self.servo_tau} needs realism.period > 0 everywhere (the lag per "
                             f"control step is 1 - exp(-period / servo_tau)), got period {self.period}")
        return self

    def swept_fields(self) -> tuple[str, ...]:
        """The section's value names, in grid order."""
        return REALISM_FIELDS

    def n_levels(self) -> int:
        """Number of combinations (rows of :meth:`levels`)."""
        return math.prod(len(getattr(self, f)) for f in self.swept_fields())

    def levels(self) -> list[dict[str, Any]]:
        """Every combination of the values, ``{name: value}``, the last field fastest."""
        names = self.swept_fields()
        return [dict(zip(names, combo)) for combo in itertools.product(*(getattr(self, f) for f in names))]

    def max_latency(self) -> int:
        """The static history length of the tracker: the largest ``latency``."""
        return max(self.latency)

    def max_settle(self) -> int:
        """The static settle-loop length of a self-ID sample: 1 (overridden with ``settle``)."""
        return 1

    def add_columns(self, meta) -> None:
        """Write each row's values into ``meta`` (in place) from its ``realism_level`` column."""
        table = self.levels()
        idx = meta["realism_level"].to_numpy()
        for name in self.swept_fields():
            meta[name] = np.asarray([lvl[name] for lvl in table])[idx]

    def rows(self, meta) -> RealismRows:
        """The traced values of ``meta``'s rows (after :meth:`add_columns`): :class:`RealismRows` of ``(N,)``."""
        values = {f: meta[f].to_numpy(np.int32 if f == "latency" else float) for f in REALISM_FIELDS}
        return RealismRows(Realism(**values), None)


class SelfIdRealismConfig(RealismConfig):
    """:class:`RealismConfig` of an experiment that self-identifies: also how long each self-ID sample waits.

    Each sample of Algorithm 1 reads the tracker, commands the actuation,
    waits ``settle`` control steps (the actuators lag, the tracker lags) and
    reads again (:func:`selfid_jax.control.realism.self_id_sampler`).
    ``realism.noise_pos`` / ``noise_rot`` are the tracker's noise on every
    reading, self-ID and path following; the experiment's ``pose_noise`` /
    ``rot_noise`` (the same tracker's noise, level by level) must then stay 0.
    """

    settle: Annotated[list[Annotated[int, Field(ge=1, le=1000)]], Field(min_length=1, max_length=1000)] = Field(
        [1], description="control steps a self-ID sample waits between its command and its second reading")

    _settle_is_a_list = field_validator("settle", mode="before")(_listed)

    def swept_fields(self) -> tuple[str, ...]:
        return REALISM_FIELDS + ("settle",)

    def max_settle(self) -> int:
        return max(self.settle)

    def rows(self, meta) -> RealismRows:
        return super().rows(meta)._replace(settle=meta["settle"].to_numpy(np.int32))


def check_realism_noise(realism: RealismConfig | None, pose_noise: list, rot_noise: list, where: str = "") -> None:
    """``ValueError`` if both the ``realism`` tracker noise and the noise-level lists are set (two sources of one
    number)."""
    if realism is None:
        return
    for own, other in (("noise_pos", pose_noise), ("noise_rot", rot_noise)):
        if any(v > 0 for v in getattr(realism, own)) and any(v > 0 for v in other):
            name = "pose_noise" if own == "noise_pos" else "rot_noise"
            raise ValueError(f"{where}realism.{own} is the tracker noise of every reading (self-ID and path "
                             f"following); leave {where}{name} (the same tracker's noise, level by level) at [0.0] "
                             f"when it is set")


PoseNoise = Annotated[list[Annotated[float, Field(ge=0, le=0.1)]], Field(min_length=1)]
"""Tracker position noise sd per level [m]: one or more values in [0, 0.1]."""

RotNoise = Annotated[list[Annotated[float, Field(ge=0, le=1.0)]], Field(min_length=1)]
"""Tracker rotation noise sd per level [rad]: one or more values in [0, 1]."""


NOISE_COLUMNS = {
    "noise_level": "tracker-noise level index (pose_noise, rot_noise pair) [id]",
    "pose_noise": "tracker position noise sd [m]",
    "rot_noise": "tracker rotation noise sd [rad]",
}
"""The results-column documentation of a tracker-noise level's columns (an ``Experiment``'s ``columns``)."""


class TrackerNoiseConfig(BaseModel):
    """The tracker's noise on every reading, level by level, and the real loop's non-idealities.

    ``pose_noise[i]`` and ``rot_noise[i]`` form noise level ``i`` (the lists
    pair up), on every tracker reading of self-ID and of the motions
    (:func:`selfid_jax.control.realism.with_tracker_noise`); a ``realism``
    section adds the real loop on every self-ID and motion, whose own tracker
    noise then replaces these (:func:`check_realism_noise`). A base of the configs of the experiments
    that self-identify and then move (``tracking``, ``peg_in_hole``).
    """

    model_config = STRICT

    pose_noise: PoseNoise = Field([0.0], description="tracker position noise sd per level, every reading "
                                     "(self-ID and following) [m]")
    rot_noise: RotNoise = Field([0.0], description="tracker rotation noise sd per level, every reading "
                                   "(self-ID and following) [rad]")
    realism: SelfIdRealismConfig | None = Field(
        None, description="the real loop's non-idealities, on every self-ID and motion (default: the ideal loop)")

    @model_validator(mode="after")
    def _noise_levels(self):
        check_noise_pairs(self.pose_noise, self.rot_noise)
        check_realism_noise(self.realism, self.pose_noise, self.rot_noise)
        return self


def realism_columns(self_id: bool = True) -> dict[str, str]:
    """The results-column documentation of a ``realism`` section's columns (present only with the section)."""
    cols = {
        "realism_level": "index of the combination of realism values (only with a realism section) [id]",
        "period": "control period (realism) [s]",
        "latency": "tracker latency, whole control steps (realism) [steps]",
        "noise_pos": "tracker position noise sd per axis, every reading (realism) [m]",
        "noise_rot": "tracker rotation noise sd per axis, every reading (realism) [rad]",
        "dropout": "probability that a tracker reading is missing (realism) [-]",
        "servo_tau": "first-order servo time constant, 0: no lag (realism) [s]",
        "deadband": "actuator deadband (realism) [rad or m: the actuator's unit]",
    }
    if self_id:
        cols["settle"] = "control steps a self-ID sample waits before its second reading (realism) [steps]"
    return cols


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


class StartsConfig(BaseModel):
    """The start configurations' search: ``n_configs * oversample`` candidates, the first that the truth completes."""

    model_config = STRICT

    oversample: int = Field(4, ge=1, le=1000, description="candidate start configurations drawn per one kept "
                            "(raise it when too few candidates complete the path with the true inverse Jacobian)")


def controller_rows(controller: ControllerConfig, n_rows: int):
    """The traced controller settings of ``controller`` repeated for ``n_rows`` rows: ``ControllerParams`` of
    ``(N,)``."""
    return ControllerParams(**{k: np.full((n_rows,), float(v)) for k, v in controller.traced().items()})
