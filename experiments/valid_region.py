"""Valid inverse-Jacobian region (paper Sec. III-C, Fig. 2), one compiled batched computation per system.

For each ``eps_limit`` on the grid, each start configuration and each trial, a
scaling matrix ``m_eps (n, m)`` is drawn elementwise from
``uniform(1, eps_limit)`` (below 1 when ``eps_limit < 1``) and held for the
trial; the controller follows the star path with ``m_eps * Jinv_true(q)`` at
every step. Start configurations are drawn away from singularities and kept
only if the true inverse Jacobian completes the path from them (the test of
:func:`selfid_jax.control.feasible_starts`, run as rows of the study itself
with ``eps_limit = 1``, so that the study's one compiled program serves both:
:func:`feasible_configs`). The valid region is the contiguous range of
``eps_limit`` around 1 where the mean path completion reaches the threshold.

From Python::

    from selfid_jax import runner
    cfg = runner.load("configs/valid_region/valid_region_two_link.yaml")
    table, summary = runner.run(runner.get("valid_region"), cfg, "runs/vr")
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from selfid_jax import control
from selfid_jax.control import paths
from selfid_jax.control import realism as realism_lib
from selfid_jax.runner import Experiment, Part, precision
from selfid_jax.runner.sweep import compiled_batch, compute_rows, grid_table, row_keys
from selfid_jax.systems import System

from .common import realism as realistic
from .common.lazy_figures import figures_plot
from .common.region import valid_region_summary
from .common.schema import (
    ControllerConfig,
    EpsLimits,
    HostOrDevice,
    PathConfig,
    RealismConfig,
    StartsConfig,
    StudyConfig,
    controller_rows,
    realism_columns,
)
from .common.specs import (
    SystemSpec,
    build_system,
    needs_x64,
    spec_or_run,
    system_name,
    unique_system_names,
)


class SystemRun(BaseModel):
    """A system with its own protocol (hands need mm paths where an arm needs cm): overrides the top level."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    system: SystemSpec
    path: PathConfig | None = None
    controller: ControllerConfig | None = None


if TYPE_CHECKING:  # a type built at run time for pydantic; mypy sees any entry
    SystemEntry = Any
else:
    SystemEntry = spec_or_run(SystemRun)
"""A ``systems`` entry: a system spec, or ``{system: spec, path: ..., controller: ...}``."""


def protocol(cfg: ValidRegionConfig, entry) -> tuple[object, PathConfig, ControllerConfig]:
    """``(system spec, path, controller)`` of one ``systems`` entry, the top level filling what it leaves out."""
    if isinstance(entry, SystemRun):
        return entry.system, entry.path or cfg.path, entry.controller or cfg.controller
    return entry, cfg.path, cfg.controller


class ValidRegionConfig(StudyConfig, StartsConfig):
    """Valid inverse-Jacobian region study (paper Sec. III-C, Fig. 2).

    Every rollout scales the true inverse Jacobian elementwise by ``m_eps`` with
    entries drawn from ``uniform(1, eps_limit)`` and follows the path; the grid is
    ``systems x eps_limits x n_configs x n_trials`` rollouts.
    """

    experiment: Literal["valid_region"] = "valid_region"
    systems: Annotated[list[SystemEntry], Field(
        min_length=1,
        description="built-in names, {mjcf: ...} / {pose_fn: ...}, or {system: ..., path: ..., controller: ...}")]
    eps_limits: EpsLimits
    n_configs: int = Field(ge=1, le=10**5)
    n_trials: int = Field(ge=1, le=10**5)
    controller: ControllerConfig = ControllerConfig()
    path: PathConfig
    completion_threshold: float = Field(0.95, gt=0, le=1)
    realism: RealismConfig | None = Field(None, description="the real loop's non-idealities (default: the ideal loop)")

    _unique = field_validator("systems")(unique_system_names)

    @model_validator(mode="after")
    def _protocols_fit(self):
        for entry in self.systems:
            _, path, controller = protocol(self, entry)
            path.check_controller(controller)
        return self


class Static(NamedTuple):
    """What every rollout of one system shares (closed over by the compiled function)."""

    system: System
    path: jax.Array  # (W, task_dim) star waypoint offsets [m]
    steps: int  # control-step budget
    max_latency: int | None = None  # with realism: the tracker's history length - 1 [steps]; None: the ideal loop
    plant: realism_lib.Plant | None = None  # with realism.plant 'dynamic': the arm's physics; None: kinematic


class Params(NamedTuple):
    """One rollout's traced inputs (batch axis first when batched)."""

    eps_limit: HostOrDevice  # () m_eps entries ~ uniform(1, eps_limit)
    key: HostOrDevice  # (2,) uint32 PRNG key data of the trial
    q0: HostOrDevice  # (n,) start configuration
    controller: control.ControllerParams  # () each: controller protocol
    realism: realism_lib.Realism | None = None  # () each, with a realism section


class Outputs(NamedTuple):
    """One rollout's metrics (see :class:`selfid_jax.control.FollowResult`)."""

    completion: jax.Array
    mean_error: jax.Array
    max_error: jax.Array
    waypoint_error: jax.Array
    steps_used: jax.Array
    failed: jax.Array
    dropouts: jax.Array | None = None  # () int32 tracker readings that dropped out, with realism


def scaling_matrix(key, eps_limit, shape):
    """``m_eps`` of ``shape`` with entries ``uniform(1, eps_limit)`` (Sec. III-C)."""
    u = jax.random.uniform(key, shape, dtype=jnp.result_type(float))
    return 1.0 + (eps_limit - 1.0) * u


def compute(static: Static, p: Params) -> Outputs:
    """Follow the star from ``p.q0`` with ``m_eps * Jinv_true(q)`` for one trial's ``m_eps`` (under ``p.realism``
    where given: :mod:`selfid_jax.control.realism`, its noise drawn from the trial's key)."""
    system = static.system
    key = jax.random.wrap_key_data(jnp.asarray(p.key))
    m_eps = scaling_matrix(key, p.eps_limit, (system.n_act, system.task_dim))
    res = control.follow(system, control.scaled_true_inverse(system, m_eps), static.path, p.q0, p.controller,
                         steps=static.steps, realism=p.realism, key=jax.random.fold_in(key, 1),
                         max_latency=static.max_latency, plant=static.plant)
    return Outputs(*(getattr(res, f) for f in Outputs._fields))


def build(cfg: ValidRegionConfig) -> list[Part]:
    """One part per system: ``eps_limits x n_configs x n_trials`` rollouts from feasible start configurations."""
    parts = []
    for entry in cfg.systems:
        spec, path, controller = protocol(cfg, entry)
        x64 = needs_x64(spec)
        with precision(x64):
            parts.append(_system_part(cfg, spec, path, controller, x64))
    return parts


PAD_LIMIT = 4096
"""Padding rollouts a shared compilation may cost: at ~0.35 ms per UR5e rollout on 2 cores, about one compile."""


def feasible_configs(static: Static, key, k: int, controller: ControllerConfig, *, batch: int,
                     oversample: int = 4) -> np.ndarray:
    """``k`` start configurations ``(k, n)`` from which the true inverse Jacobian completes the path.

    The test of :func:`selfid_jax.control.feasible_starts` with its sampling
    (``k * oversample`` draws of ``system.sample_configs(key, ...)``) and its
    selection and message (:func:`selfid_jax.control.feasible_indices`: the
    first ``k`` that complete the path without failing), but each rollout
    is a row of the study (``eps_limit = 1``: ``m_eps = 1`` exactly, the true
    inverse Jacobian; with a realism section at its ``IDEAL`` values, the
    ideal loop) run by :func:`selfid_jax.runner.sweep.compute_rows` at the
    study's compiled ``batch``, so the sweep reuses this compilation instead of
    compiling a second rollout program (1.3-1.8 s for the UR5e), unless
    padding the candidates to ``batch`` would waste more than
    :data:`PAD_LIMIT` rollouts. With a dynamic plant the test runs the
    kinematic ideal loop (a program of its own), so the starts do not depend
    on the servos. Eager; ``ValueError`` if fewer than ``k`` qualify.
    """
    system = static.system
    static = static._replace(plant=None)
    total = k * oversample
    if batch - total > PAD_LIMIT:  # padding would cost more than compiling a program of its own
        batch = compiled_batch(total, total)
    cand, valid = system.sample_configs(key, total, return_valid=True)  # jitted in selfid_jax.systems
    rows = Params(
        eps_limit=np.ones((total,)),
        key=row_keys(0, total),  # unused at eps_limit = 1
        q0=np.asarray(cand),
        controller=controller_rows(controller, total),
        realism=None if static.max_latency is None else _ideal_rows(total),
    )
    out = compute_rows(EXPERIMENT.batched(static), rows, batch=batch)
    return np.asarray(cand)[control.feasible_indices(system, valid, out["completion"], out["failed"], k)]


def _system_part(cfg: ValidRegionConfig, spec, path_cfg: PathConfig, controller: ControllerConfig, x64: bool) -> Part:
    """One system's rollouts: the grid rows, feasible start configurations and the traced parameters."""
    name, system = system_name(spec), build_system(spec)
    path = paths.star(size=path_cfg.size, dim=system.task_dim)
    meta = grid_table(realistic.add_realism_axis(
        {
            "system": [name],
            "eps_limit": list(cfg.eps_limits.values()),
            "config_id": range(cfg.n_configs),
            "trial": range(cfg.n_trials),
        }, cfg.realism, before="eps_limit")
    )
    static = Static(system, path, controller.steps,
                    None if cfg.realism is None else cfg.realism.max_latency())
    configs = feasible_configs(static, jax.random.key(cfg.seed), cfg.n_configs, controller,
                               batch=compiled_batch(len(meta), cfg.chunk_size), oversample=cfg.oversample)
    params = Params(
        eps_limit=meta["eps_limit"].to_numpy(float),
        key=row_keys(cfg.seed, len(meta)),
        q0=configs[meta["config_id"].to_numpy()],
        controller=controller_rows(controller, len(meta)),
    )
    if cfg.realism is not None:
        cfg.realism.add_columns(meta)
        params = params._replace(realism=cfg.realism.rows(meta).realism)
        static = static._replace(plant=realistic.plant(cfg.realism, spec, system))
    return Part(name, static, params, meta, x64)


def _ideal_rows(n: int) -> realism_lib.Realism:
    """:data:`~selfid_jax.control.realism.IDEAL` for ``n`` rows: ``Realism`` of ``(n,)`` zeros (latency int32)."""
    zeros = np.zeros((n,))
    return realism_lib.Realism(period=zeros, latency=np.zeros((n,), np.int32), noise_pos=zeros, noise_rot=zeros,
                               dropout=zeros, servo_tau=zeros, deadband=zeros)


def series(table: pd.DataFrame) -> pd.DataFrame:
    """``table`` with each system's realism levels as series of their own: ``system`` becomes ``"<system>
    (<values>)"`` (the values that differ between levels); unchanged without a realism section."""
    labels = realistic.level_labels(table)
    if not labels:
        return table
    names = [f"{s} ({labels[int(k)]})" for s, k in zip(table["system"], table["realism_level"])]
    return table.assign(system=names)


def summarize(table: pd.DataFrame, cfg: ValidRegionConfig) -> dict:
    """Bounds per system with the protocol beside them (per system where a ``systems`` entry sets its own).

    With a realism section, per system and realism level: the key is
    ``"<system> (<values>)"`` (:func:`series`), its entry holding the level's
    values (``realism``) and the mean tracker dropouts per rollout.
    """
    summary = valid_region_summary(
        series(table),
        cfg.completion_threshold,
        controller=cfg.controller.model_dump(),
        path=cfg.path.model_dump(),
        n_configs=cfg.n_configs,
        n_trials=cfg.n_trials,
    )
    own = {system_name(spec): {"path": path.model_dump(), "controller": controller.model_dump()}
           for entry in cfg.systems if isinstance(entry, SystemRun)
           for spec, path, controller in [protocol(cfg, entry)]}
    for name, g in series(table).groupby("system", sort=False):
        entry = summary["systems"][str(name)]
        system = str(table.loc[g.index[0], "system"])
        if "realism_level" in g.columns:
            entry["realism"] = realistic.realism_summary(g, int(g["realism_level"].iloc[0]))
            entry["mean_dropouts"] = float(g["dropouts"].mean())
        if system in own:
            entry["protocol"] = own[system]
    return summary


def report(summary: dict) -> str:
    """One line per system: the valid region or its absence."""
    lines = []
    for system, entry in summary["systems"].items():
        if entry["lower"] is None:
            lines.append(f"{system}: no valid region around 1 ({entry['n_rollouts']} rollouts)")
        else:
            lines.append(f"{system}: valid region {entry['lower']:.3g}x - {entry['upper']:.3g}x the true inverse "
                         f"Jacobian ({entry['n_rollouts']} rollouts)")
    return "\n".join(lines)


plot = figures_plot("valid_region")  # experiments/figures/valid_region.py, imported (with matplotlib) when called


COLUMNS = {
    "system": "system name [label]",
    "eps_limit": "upper limit of the scaling entries: m_eps drawn elementwise uniform(1, eps_limit) [-]",
    "config_id": "feasible start configuration index [id]",
    "trial": "m_eps draw index (one rollout each) [id]",
    "completion": "fraction of the star's waypoints reached [-]",
    "mean_error": "mean distance of the POM to the path over the steps used [m]",
    "max_error": "largest distance of the POM to the path over the steps used [m]",
    "waypoint_error": "mean over waypoints of the position error when reached (at the end if not) [m]",
    "steps_used": "control steps until the last waypoint was reached (or the budget) [steps]",
    "failed": "non-finite state or divergence from the path [bool]",
    **realism_columns(self_id=False),
    "dropouts": "tracker readings that dropped out while following the path (realism) [count]",
}
"""The results columns (``results.parquet``): one row per system, eps_limit, start configuration and trial."""


EXPERIMENT = Experiment(
    name="valid_region",
    config=ValidRegionConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    columns=COLUMNS,
    plot=plot,
    report=report,
    description="valid inverse-Jacobian region: completion vs elementwise scaling of the true inverse (Fig. 2)",
)
