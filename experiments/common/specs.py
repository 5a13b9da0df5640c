"""Systems named in configs: a built-in name, an MJCF file with a site, or a pose function ``package.module:function``.

In YAML::

    systems: [two_link, ur5e]                       # built-in robots (selfid_jax.systems.REGISTRY)
    system:                                         # any MuJoCo robot, no Python
      mjcf: robots/my_arm.xml                       # relative to the config file
      site: tip                                     # the point of manipulation (or body: + offset: [x, y, z])
      actuators: [shoulder, elbow, wrist]           # default: every actuator; 'joints': every hinge/slide
      joints_fixed: {gripper_slide: 0.01}           # joints held away from qpos0
      task_dim: 3
      m_a: [0.03, 0.03, 0.05]                       # per actuator, or one number
      home: [0.0, -0.8, 1.2]                        # start-box centre, or {keyframe: home} (the default)
      sample_half_width: 0.4                        # box half-width around home [rad or m]
    system:                                         # a pure JAX pose function
      pose_fn: my_package.robots:planar_three_link  # fn(params, q) -> (p, R) or p
      n_act: 3
      task_dim: 2
      params: [0.5, 0.4, 0.3]
      q_low: -3.0
      q_high: 3.0
      m_a: 0.02
      sample_box: {low: [-1, 0.3, 0.3], high: [1, 1.5, 1.5]}

:func:`build_system` turns a validated spec into a :class:`~selfid_jax.systems.System`.
"""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, Discriminator, Field, Tag, ValidationInfo, field_validator, model_validator

from selfid_jax.runner.config import STRICT, unique
from selfid_jax.runner.layout import SAFE_NAME
from selfid_jax.systems import REGISTRY
from selfid_jax.systems.system import System

__all__ = ["BUILTIN_FACTORIES", "Keyframe", "MjcfSystem", "PoseFnSystem", "SampleBox", "SystemSpec", "build_system",
           "entry_spec", "needs_x64", "spec_or_run", "unique_system_names", "system_name"]


Numbers = float | list[float]


BUILTIN_FACTORIES = tuple(REGISTRY)
"""Names a config may use for the shipped robots (:data:`selfid_jax.systems.REGISTRY`'s keys)."""


class SampleBox(BaseModel):
    """A box of start configurations, actuator units (rad or m)."""

    model_config = STRICT

    low: list[float] = Field(min_length=1)
    high: list[float] = Field(min_length=1)

    @model_validator(mode="after")
    def _ordered(self):
        if len(self.low) != len(self.high) or any(lo > hi for lo, hi in zip(self.low, self.high)):
            raise ValueError(f"low and high must have equal lengths and low <= high, got {self.low} and {self.high}")
        return self


class Keyframe(BaseModel):
    """A keyframe of the model, by name: its ``qpos`` in actuator coordinates."""

    model_config = STRICT

    keyframe: str = Field(min_length=1, description="keyframe name")


class MjcfSystem(BaseModel):
    """A MuJoCo model: the actuation space is its actuators (or the named subset)."""

    model_config = STRICT

    mjcf: str = Field(description="MJCF or URDF (.urdf) file, relative to the config file")
    site: str | None = Field(None, min_length=1, description="name of the POM site (or give body and offset)")
    body: str | None = Field(None, min_length=1, description="name of the POM's body, when the model has no site")
    offset: list[float] | None = Field(None, min_length=3, max_length=3,
                                       description="POM position in the body's frame [m] (with body; default 0 0 0)")
    actuators: list[str] | Literal["joints"] | None = Field(
        None, min_length=1, description="actuator names (default: all), or 'joints': every hinge and slide joint")
    joints_fixed: dict[str, float] | None = Field(None, description="joint name -> held value (rad or m)")
    task_dim: Literal[2, 3, 6] = 3
    m_a: Numbers = Field(0.03, description="self-ID magnitude, one number or one per actuator [rad or m]")
    dq_max: Numbers = Field(0.1, description="largest actuator step per control step [rad or m]")
    home: list[float] | Keyframe | None = Field(
        None, description="centre of the start box, or {keyframe: NAME} (default: the 'home' keyframe, else qpos0)")
    sample_half_width: float | None = Field(None, gt=0, description="half-width of the start box around home")
    sample_box: SampleBox | None = Field(None, description="explicit start box (instead of home +- half-width)")
    min_sigma: float = Field(1e-3, ge=0, description="start configurations need sigma_min(J) above this")
    name: str | None = Field(None, pattern=SAFE_NAME,
                             description="label (default: the file's stem); letters, digits, '.', '_', '+', '-'")
    x64: bool = Field(False, description="build and run this system in float64 (the others stay as set)")

    def input_files(self) -> dict[str, str]:
        """The model file and every file it reads (includes, meshes, textures), path -> SHA-256."""
        from selfid_jax.systems.model_files import file_sha256, model_files

        return {str(p): file_sha256(p) for p in model_files(self.mjcf)}

    @field_validator("mjcf")
    @classmethod
    def _resolve(cls, value: str, info: ValidationInfo) -> str:
        base = (info.context or {}).get("config_dir")
        path = Path(value).expanduser()
        if not path.is_absolute() and base is not None:
            path = Path(base) / path
        if not path.is_file():
            raise ValueError(f"MJCF file {str(path)!r} not found" + (" (relative paths are relative to the config file)"
                                                                      if base is not None else ""))
        return str(path.resolve())

    @model_validator(mode="after")
    def _one_pom(self):
        if (self.site is None) == (self.body is None):
            raise ValueError("give the point of manipulation as 'site: NAME' or as 'body: NAME' (with 'offset: "
                             "[x, y, z]' in the body frame), exactly one of them")
        if self.offset is not None and self.body is None:
            raise ValueError("'offset' needs 'body' (a site has its own position)")
        return self

    @field_validator("m_a", "dq_max")
    @classmethod
    def _positive(cls, value: Numbers) -> Numbers:
        values = value if isinstance(value, list) else [value]
        if not values or any(v <= 0 for v in values):
            raise ValueError(f"must be > 0 (one number or one per actuator), got {value}")
        return value


class PoseFnSystem(BaseModel):
    """A pure JAX pose function ``fn(params, q) -> (p (3,), R (3, 3))`` or ``-> p``, importable by name."""

    model_config = STRICT

    pose_fn: str = Field(pattern=r"^[\w.]+:\w+$", description="'package.module:function'")
    n_act: int = Field(ge=1, le=1000)
    task_dim: Literal[2, 3, 6] = 3
    params: list[float] | None = Field(None, description="passed to the pose function as an array")
    q_low: Numbers = -3.14159
    q_high: Numbers = 3.14159
    dq_max: Numbers = 0.1
    m_a: Numbers = 0.03
    sample_box: SampleBox | None = None
    min_sigma: float = Field(1e-3, ge=0)
    name: str | None = Field(None, pattern=SAFE_NAME, description="label; letters, digits, '.', '_', '+', '-'")
    x64: bool = Field(False, description="build and run this system in float64 (the others stay as set)")

    def input_files(self) -> dict[str, str]:
        """The source file of the pose function's module, path -> SHA-256 (found without running the module)."""
        from selfid_jax.systems.model_files import file_sha256

        module = self.pose_fn.partition(":")[0]
        try:
            spec = importlib.util.find_spec(module)
        except (ImportError, ValueError):
            spec = None
        origin = spec.origin if spec is not None else None
        if origin is None or not Path(origin).is_file():
            return {f"pose_fn module {module}": "not found"}
        return {origin: file_sha256(origin)}


def _kind(value) -> str | None:
    if isinstance(value, str):
        return "<builtin>"
    if isinstance(value, MjcfSystem) or (isinstance(value, dict) and "mjcf" in value):
        return "<mjcf>"
    if isinstance(value, PoseFnSystem) or (isinstance(value, dict) and "pose_fn" in value):
        return "<pose_fn>"
    return None


SystemSpec = Annotated[
    # a Literal of a runtime tuple: pydantic validates it, mypy cannot check what it cannot see
    Annotated[Literal[BUILTIN_FACTORIES], Tag("<builtin>")]  # type: ignore[valid-type]
    | Annotated[MjcfSystem, Tag("<mjcf>")]
    | Annotated[PoseFnSystem, Tag("<pose_fn>")],
    Discriminator(
        _kind,
        custom_error_type="system_spec",
        custom_error_message="a system is a built-in name (" + ", ".join(map(repr, BUILTIN_FACTORIES)) + ") or a "
        "mapping with an 'mjcf' or a 'pose_fn' key",
    ),
]
"""What a config's ``system`` / ``systems`` entries accept (config errors drop the ``<tag>`` parts of keys)."""


X64_BUILTINS: frozenset[str] = frozenset(name for name, b in REGISTRY.items() if b.x64)
"""Built-in systems that run in float64 whatever the global setting (closed-chain hands)."""


def needs_x64(spec) -> bool:
    """Whether a system spec is built and run in float64 (``jax.enable_x64``); arms stay in the default dtype."""
    return spec in X64_BUILTINS if isinstance(spec, str) else spec.x64


def system_name(spec) -> str:
    """The label of a system spec: the built-in name, ``name``, the MJCF file stem or the function name."""
    if isinstance(spec, str):
        return spec
    if spec.name is not None:
        return spec.name
    if isinstance(spec, MjcfSystem):
        return Path(spec.mjcf).stem
    return spec.pose_fn.rsplit(":", 1)[1]



def spec_or_run(run_model: type[BaseModel]):
    """The type of a ``systems`` entry with per-system protocols: a system spec, or a ``run_model``.

    ``run_model`` is a pydantic model with a ``system`` field (a
    :data:`SystemSpec`) and the settings it overrides; a mapping with a
    ``system`` key is read as one.
    """
    return Annotated[
        Annotated[SystemSpec, Tag("<spec>")] | Annotated[run_model, Tag("<run>")],
        Discriminator(lambda v: "<run>" if isinstance(v, run_model) or (isinstance(v, dict) and "system" in v)
                      else "<spec>"),
    ]


def entry_spec(entry):
    """The system spec of a ``systems`` entry of :func:`spec_or_run`: the entry, or its ``system`` field."""
    return entry if isinstance(entry, (str, MjcfSystem, PoseFnSystem)) else entry.system


def unique_system_names(entries: list) -> list:
    """``entries`` (``systems`` entries of :func:`spec_or_run`) if their system names are distinct, else
    ``ValueError``."""
    unique([system_name(entry_spec(e)) for e in entries], "system names")
    return entries

def _one_line(text: str, limit: int = 300) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _import(target: str):
    module, _, attr = target.partition(":")
    try:
        fn = getattr(importlib.import_module(module), attr)
    except KeyboardInterrupt:
        raise
    except BaseException as err:  # noqa: BLE001 - the module's own code runs here: a SyntaxError, anything, sys.exit
        what = f"exit({err.code!r})" if isinstance(err, SystemExit) else f"{type(err).__name__}: {err}"
        raise ValueError(f"pose_fn {target!r}: importing module {module!r} failed ({_one_line(what)})") from None
    if not callable(fn):
        raise ValueError(f"pose_fn {target!r} is not callable")
    return fn


def build_system(spec) -> System:
    """The :class:`System` a validated spec describes (``ValueError`` naming the problem if it cannot be built)."""
    import numpy as np

    if isinstance(spec, str):
        if spec not in REGISTRY:
            raise ValueError(f"unknown system {spec!r}; built-in: {', '.join(REGISTRY)}")
        return REGISTRY[spec].factory()
    box = {} if spec.sample_box is None else {"sample_low": spec.sample_box.low, "sample_high": spec.sample_box.high}
    if isinstance(spec, MjcfSystem):
        from selfid_jax.systems.mjcf import from_mjcf

        extra = {k: getattr(spec, k) for k in ("actuators", "joints_fixed", "home", "sample_half_width", "body",
                                               "offset") if getattr(spec, k) is not None}
        if isinstance(spec.home, Keyframe):
            extra["home"] = {"keyframe": spec.home.keyframe}
        return from_mjcf(spec.mjcf, spec.site, task_dim=spec.task_dim, m_a=spec.m_a, dq_max=spec.dq_max,
                         min_sigma=spec.min_sigma, name=system_name(spec), **extra, **box)
    from selfid_jax.systems.system import from_pose_fn

    params = None if spec.params is None else np.asarray(spec.params)
    return from_pose_fn(_import(spec.pose_fn), spec.n_act, task_dim=spec.task_dim, q_low=spec.q_low,
                        q_high=spec.q_high, dq_max=spec.dq_max, m_a=spec.m_a, params=params,
                        min_sigma=spec.min_sigma, name=system_name(spec), **box)


def build_dynamic_arm(spec, gravcomp: float | None = None):
    """The :class:`~selfid_jax.systems.dynamic.DynamicArm` of a validated system spec (the ``realism.plant:
    dynamic`` backend): ``ur5e`` or an ``mjcf`` arm whose actuators are position servos; ``ValueError`` naming the
    problem otherwise."""
    from selfid_jax.systems.dynamic import dynamic_arm, dynamic_ur5e

    if spec in ("ur5e", "ur5e_6d"):  # the shipped UR5e's MJCF, whatever the task
        return dynamic_ur5e(gravcomp=gravcomp)
    if isinstance(spec, MjcfSystem):
        if spec.site is None or spec.body is not None or spec.actuators is not None or spec.joints_fixed:
            raise ValueError(f"realism.plant 'dynamic': system {system_name(spec)!r} sets body/actuators/"
                             f"joints_fixed or no site, which the dynamic arm does not support; it steps the "
                             f"file's own position servos with the POM at site {spec.site!r}")
        return dynamic_arm(spec.mjcf, spec.site, gravcomp=gravcomp, name=f"dynamic_{system_name(spec)}")
    raise ValueError(f"realism.plant 'dynamic' needs an arm whose actuators are position servos (the built-in "
                     f"'ur5e', 'ur5e_6d' or an mjcf arm), got system {system_name(spec)!r}; use plant 'servo' for it")
