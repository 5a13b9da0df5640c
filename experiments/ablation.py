"""Estimation ablation (paper Sec. V-A, Fig. 5): path completion vs self-ID iterations per method.

One batched computation: every row of the grid (start configuration x trial x
tracker noise x self-ID magnitude) generates one self-ID sample stream on the
UR5e (position task), feeds the same stream to every estimation method
(``selfid_jax.baselines``), reads each method's estimate at every checkpoint
iteration count, and follows the star path with it from the start
configuration. The methods are static branches of the one compiled function;
iteration checkpoints, configurations, trials and noise levels are batch axes.

The tidy results table has one row per (grid row, method, iteration count):
``method, iterations, config_id, trial, pose_noise, rot_noise, m_a,
completion, mean_error, failed, converged_at``. ``converged_at`` is the first
iteration at which the method's estimate met the Sec. IV-D test
(``||J_t - J_{t-1}||_F <= eps`` twice in a row), -1 if it never did.

Model-based rows (``method: ekm`` with a ``nominal:`` model; issue 16) learn
from the same stream and follow the star with their own Eq. 10-11 QP
controller, one vmapped rollout per group of E-KM rows
(``experiments/common/ekm.py``); with any of them the part runs in float64.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax import baselines, control
from selfid_jax.control import paths
from selfid_jax.identify import algorithm as selfid
from selfid_jax.identify import estimator
from selfid_jax.runner import Experiment, Part, precision
from selfid_jax.runner.config import unique
from selfid_jax.runner.grids import grid_table, row_keys
from selfid_jax.systems import System

from .common import ekm as ablation_ekm
from .common.ekm import METHOD_CHOICES, MethodName, NominalSpec, is_model_based
from .common.lazy_figures import figures_plot
from .common.schema import (
    M_A_LABEL,
    NOISE_COLUMNS,
    ControllerConfig,
    HostOrDevice,
    Magnitude,
    PathConfig,
    PoseNoise,
    RotNoise,
    StartsConfig,
    StudyConfig,
    check_noise_pairs,
    controller_rows,
    m_a_label,
    m_a_summary,
    resolve_m_a,
)
from .common.specs import SystemSpec, build_system, needs_x64, system_name


class MethodSpec(BaseModel):
    """One curve of the ablation: a label, a method of ``selfid_jax.baselines`` and its options."""

    model_config = dict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = Field(min_length=1, description="label of the curve")
    method: MethodName = Field(description="one of " + ", ".join(METHOD_CHOICES))
    options: dict[str, float | int | str | bool] = Field(
        default_factory=dict, description="keyword options of the method's factory in selfid_jax.baselines"
    )
    nominal: NominalSpec | None = Field(None, description="model-based methods (ekm) only, and required there: "
                                        "the nominal model's length scale and joint offsets "
                                        "(experiments/common/ekm.py)")


class AblationConfig(StudyConfig, StartsConfig):
    """Estimation ablation on the UR5e (Sec. V-A)."""

    experiment: Literal["ablation"] = "ablation"
    system: SystemSpec = Field("ur5e", description="a built-in name or {mjcf: ...} / {pose_fn: ...}")
    methods: Annotated[list[MethodSpec], Field(min_length=1)]
    iterations: Annotated[list[Annotated[int, Field(ge=1, le=10**5)]], Field(min_length=1)]
    n_configs: int = Field(ge=1, le=10**5)
    n_trials: int = Field(ge=1, le=10**5)
    pose_noise: PoseNoise  # m
    rot_noise: RotNoise  # rad
    m_a: Annotated[list[Magnitude], Field(min_length=1)] | None = Field(
        None, description="self-ID magnitude levels, each one number or one per actuator [rad or m] (default: one "
        "level, the system's own m_a; the rule of common.schema.resolve_m_a)")
    eps: float = Field(gt=0, le=1e6, description="Sec. IV-D convergence threshold on ||J_t - J_{t-1}||_F [rad/m]")
    eps_rel: float = Field(0.0, ge=0, le=10, description="relative threshold: converged at eps + eps_rel ||J_t||_F")
    controller: ControllerConfig = ControllerConfig()
    path: PathConfig
    completion_threshold: float = Field(0.95, gt=0, le=1)

    @field_validator("iterations")
    @classmethod
    def _increasing(cls, its: list[int]) -> list[int]:
        if any(b <= a for a, b in zip(its, its[1:])):
            raise ValueError("must be strictly increasing")
        return its

    @field_validator("methods")
    @classmethod
    def _unique_names(cls, methods: list[MethodSpec]) -> list[MethodSpec]:
        unique([m.name for m in methods], "method names")
        for spec in methods:
            baselines.make(spec.method, **spec.options)  # unknown or bad options raise here, before compute
        return methods

    @model_validator(mode="after")
    def _noise_pairs(self):
        check_noise_pairs(self.pose_noise, self.rot_noise)
        ablation_ekm.check_methods(self.methods, self.system)
        return self


class Static(NamedTuple):
    """Shared by every row: the arm, the path, the estimators and the static sizes."""

    system: System
    path: jax.Array  # (W, task_dim) star waypoint offsets [m]
    steps: int  # control-step budget
    iters: int  # self-ID iterations per stream (the largest checkpoint)
    checkpoints: tuple[int, ...]  # 0-based sample indices at which each estimate is followed
    methods: tuple[baselines.Estimator | None, ...]  # one per curve, in config order (None: an E-KM row)
    ekm: tuple[ablation_ekm.EKMGroup, ...] = ()  # the E-KM rows, grouped by static settings (ablation_ekm.py)


class Params(NamedTuple):
    """One self-ID stream's traced inputs (batch axis first when batched)."""

    key: HostOrDevice  # (2,) uint32 PRNG key data
    q0: HostOrDevice  # (n,) start configuration [rad]
    pose_noise: HostOrDevice  # () tracker position noise sd [m]
    rot_noise: HostOrDevice  # () tracker rotation noise sd [rad]
    m_a: HostOrDevice  # (n,) self-ID magnitude per actuator [rad or m]
    eps: HostOrDevice  # () Sec. IV-D threshold on ||J_t - J_{t-1}||_F [rad/m]
    eps_rel: HostOrDevice  # () relative Sec. IV-D threshold (times ||J_t||_F)
    controller: control.ControllerParams  # () each


class Outputs(NamedTuple):
    """Per stream: M methods x C checkpoints."""

    completion: jax.Array  # (M, C) fraction of the star completed
    mean_error: jax.Array  # (M, C) mean distance to the path [m]
    failed: jax.Array  # (M, C) bool
    converged_at: jax.Array  # (M,) int32 first iteration meeting Sec. IV-D, -1 if none


def compute(static: Static, p: Params) -> Outputs:
    """One self-ID stream fed to every method; each method's estimate at every checkpoint followed along the star.

    All fixed estimates (every method but ``true``, at every checkpoint) are
    followed by ONE vmapped rollout, and ``true`` by one more, so the compiled
    program holds two rollout loops whatever the number of methods (one per
    method made compile time grow with the method list: 19 s of compile for
    the 14 methods of ``configs/ablation/ablation_ur5e.yaml``).
    """
    system = static.system
    checkpoints = jnp.asarray(static.checkpoints)
    n_ckpt = len(static.checkpoints)
    k_sid, k_est = jax.random.split(jax.random.wrap_key_data(jnp.asarray(p.key)))
    sid = selfid.run(system, k_sid, p.q0, iters=static.iters, eps=p.eps, m_a=p.m_a, pose_noise=p.pose_noise,
                     rot_noise=p.rot_noise, stop_at_convergence=False)
    truth = system.true_inverse_jacobian(p.q0)
    accepted = jax.vmap(estimator.is_valid_sample)(sid.dtheta, sid.V)  # the screen every method shares

    def follow(jinv):
        return control.follow(system, jinv, static.path, p.q0, p.controller, steps=static.steps)

    fixed, converged = [], {}
    for j, method in enumerate(static.methods):
        if method is None:  # an E-KM row: below
            continue
        est = baselines.run_stream(method, k_est, sid.dtheta, sid.V, truth)
        converged[j] = estimator.convergence_iteration(est, p.eps, p.eps_rel, accepted=accepted)
        if method.name != "true":
            fixed.append(est[checkpoints])
    model_based = {}  # E-KM: one vmapped QP rollout per group of rows
    for group in static.ekm:
        res, conv = ablation_ekm.rollouts(group, system, static.path, p.q0, p.controller, sid, checkpoints,
                                          static.steps, p.eps, p.eps_rel, accepted)
        for g, j in enumerate(group.rows):
            model_based[j] = jax.tree.map(lambda x, g=g: x[g], res)
            converged[j] = conv[g]
    if fixed:
        stacked = jnp.concatenate(fixed)  # (M' C, n, m), methods in config order
        res_fixed = jax.vmap(lambda J: follow(control.fixed(J)))(stacked)
    rows, i = [], 0
    for j, method in enumerate(static.methods):
        if method is None:
            res = model_based[j]
        elif method.name == "true":
            res = jax.tree.map(lambda x: jnp.broadcast_to(x, (n_ckpt,) + jnp.shape(x)),
                               follow(control.true_inverse(system)))
        else:
            res = jax.tree.map(lambda x, i=i: x[i * n_ckpt : (i + 1) * n_ckpt], res_fixed)
            i += 1
        rows.append((res.completion, res.mean_error, res.failed))
    completion, mean_error, failed = (jnp.stack(x) for x in zip(*rows))
    return Outputs(completion, mean_error, failed, jnp.stack([converged[j] for j in range(len(static.methods))]))


def build(cfg):
    """The one part, built (and later run) in float64 if the system needs it (closed-chain hands) or a
    model-based method is in the list (the E-KM's SOGP is float64 only)."""
    x64 = needs_x64(cfg.system) or any(is_model_based(spec.method) for spec in cfg.methods)
    with precision(x64):
        return _build(cfg)._replace(x64=x64)


def _build(cfg: AblationConfig) -> Part:
    """Configs x trials x noise levels x m_a streams on the configured system (UR5e position task by default)."""
    system = build_system(cfg.system)
    levels = ([resolve_m_a(None, system)] if cfg.m_a is None else
              [resolve_m_a(v, system, f"m_a[{i}]") for i, v in enumerate(cfg.m_a)])
    meta = grid_table(
        {
            "noise_level": range(len(cfg.pose_noise)),
            "m_a_level": range(len(levels)),
            "config_id": range(cfg.n_configs),
            "trial": range(cfg.n_trials),
        }
    )
    meta.insert(1, "pose_noise", np.asarray(cfg.pose_noise)[meta["noise_level"]])
    meta.insert(2, "rot_noise", np.asarray(cfg.rot_noise)[meta["noise_level"]])
    level = meta["m_a_level"].to_numpy()
    meta.insert(4, "m_a", np.asarray([m_a_label(lv.value) for lv in levels], float)[level])  # one number a level
    meta["m_a_vec"] = [tuple(levels[i].value.tolist()) for i in level]  # tuples: the run manifest hashes meta
    meta["m_a_source"] = levels[0].source
    path = paths.star(size=cfg.path.size, dim=system.task_dim)
    configs = np.asarray(control.feasible_starts(system, path, jax.random.key(cfg.seed), cfg.n_configs,
                                                 control.ControllerParams(**cfg.controller.traced()),
                                                 steps=cfg.controller.steps, oversample=cfg.oversample))
    n = len(meta)
    params = Params(
        key=row_keys(cfg.seed, n),
        q0=configs[meta["config_id"].to_numpy()],
        pose_noise=meta["pose_noise"].to_numpy(float),
        rot_noise=meta["rot_noise"].to_numpy(float),
        m_a=np.stack([lv.value for lv in levels])[level],
        eps=np.full((n,), cfg.eps),
        eps_rel=np.full((n,), cfg.eps_rel),
        controller=controller_rows(cfg.controller, n),
    )
    static = Static(
        system=system,
        path=path,
        steps=cfg.controller.steps,
        iters=max(cfg.iterations),
        checkpoints=tuple(i - 1 for i in cfg.iterations),
        methods=tuple(None if is_model_based(spec.method) else baselines.make(spec.method, **spec.options)
                      for spec in cfg.methods),
        ekm=ablation_ekm.groups(system, cfg.methods, max(cfg.iterations)),
    )
    return Part(system_name(cfg.system), static, params, meta)


def tabulate(wide: pd.DataFrame, part: Part, cfg: AblationConfig) -> pd.DataFrame:
    """Stream table (list columns of M x C values) -> one row per (stream, method, iteration count)."""
    base_cols = ["noise_level", "pose_noise", "rot_noise", "m_a_level", "m_a", "config_id", "trial", "m_a_vec",
                 "m_a_source"]
    its = np.asarray(cfg.iterations)
    M, C, rows = len(cfg.methods), len(its), len(wide)

    def cube(col):  # (rows, M, C)
        return np.stack(wide[col].to_numpy()).reshape(rows, M, C)

    comp, err, fail = cube("completion"), cube("mean_error"), cube("failed")
    conv = np.stack(wide["converged_at"].to_numpy()).reshape(rows, M)
    frames = []
    for i, spec in enumerate(cfg.methods):
        df = wide[base_cols].loc[wide.index.repeat(C)].reset_index(drop=True)
        df.insert(0, "method", spec.name)
        df["iterations"] = np.tile(its, rows)
        df["completion"] = comp[:, i].reshape(-1)
        df["mean_error"] = err[:, i].reshape(-1)
        df["failed"] = fail[:, i].reshape(-1).astype(bool)
        df["converged_at"] = np.repeat(conv[:, i], C)
        frames.append(df)
    return pd.concat(frames, ignore_index=True)


def summarize(df: pd.DataFrame, cfg: AblationConfig) -> dict[str, Any]:
    """Per method (noise-free, first m_a): iterations to reach the completion threshold, convergence stats."""
    clean = df[(df.noise_level == 0) & (df.m_a_level == 0)]
    methods = {}
    for name, g in clean.groupby("method", sort=False):
        curve = g.groupby("iterations")["completion"].mean()
        reached = curve[curve >= cfg.completion_threshold]
        per_stream = g.drop_duplicates(["config_id", "trial"])["converged_at"].to_numpy()
        conv = per_stream[per_stream > 0]
        methods[str(name)] = {
            "iterations_to_threshold": int(reached.index[0]) if len(reached) else None,
            "mean_completion": {int(k): float(v) for k, v in curve.items()},
            "converged_fraction": float(len(conv) / max(len(per_stream), 1)),
            "convergence_iteration_mean": float(conv.mean()) if len(conv) else None,
            "convergence_iteration_sd": float(conv.std()) if len(conv) else None,
        }
    noise = (
        df[df.iterations == max(cfg.iterations)].groupby(["method", "pose_noise"])["completion"].mean().unstack()
    )
    return {
        "completion_threshold": cfg.completion_threshold,
        "eps": cfg.eps,
        "self_id": {"m_a_levels": [m_a_summary(g, vector="m_a_vec")["m_a"]
                                   for _, g in df.groupby("m_a_level", sort=True)],
                    "m_a_source": str(df["m_a_source"].iloc[0])},
        "controller": cfg.controller.model_dump(),
        "path": cfg.path.model_dump(),
        "methods": methods,
        "completion_at_max_iterations_by_pose_noise": {
            str(m): {str(k): float(v) for k, v in row.items()} for m, row in noise.iterrows()
        },
    }


def report(summary: dict[str, Any]) -> str:
    """A table: iterations to the completion threshold and convergence iteration per method."""
    to = "iters to " + format(summary["completion_threshold"], ".0%")
    lines = [f"{'method':24s} {to:>14s} {'converged at':>16s}"]
    for name, s in summary["methods"].items():
        conv = s["convergence_iteration_mean"]
        conv_txt = f"{conv:.1f} +- {s['convergence_iteration_sd']:.1f}" if conv is not None else "never"
        its = s["iterations_to_threshold"]
        lines.append(f"{name:24s} {'never' if its is None else str(its):>14s} {conv_txt:>16s}")
    return "\n".join(lines)


plot = figures_plot("ablation")  # experiments/figures/ablation.py, imported (with matplotlib) when called


COLUMNS = {
    "method": "the method's name (methods[].name of the config) [label]",
    **NOISE_COLUMNS,
    "m_a_level": "index of the self-ID magnitude level (m_a list of the config) [id]",
    "m_a": f"the level's self-ID magnitude: {M_A_LABEL} (per actuator: m_a_vec) [rad or m]",
    "config_id": "feasible start configuration index [id]",
    "trial": "self-ID stream index [id]",
    "m_a_vec": "(n_act,) the level's self-ID magnitude per actuator [rad or m: the actuator's unit]",
    "m_a_source": "where m_a came from: 'system' (the system's own) or 'config' (the m_a key) [label]",
    "iterations": "self-ID iterations the estimate had when the star was followed (a checkpoint) [iterations]",
    "completion": "fraction of the star's waypoints reached [-]",
    "mean_error": "mean distance to the path over the steps used [m]",
    "failed": "non-finite state or divergence from the path [bool]",
    "converged_at": "the method's first iteration meeting Sec. IV-D in this stream, -1 if none [iteration]",
}
"""The results columns (``results.parquet``): one row per stream, method and iteration count."""


EXPERIMENT = Experiment(
    name="ablation",
    config=AblationConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    columns=COLUMNS,
    tabulate=tabulate,
    plot=plot,
    report=report,
    description="estimation ablation: completion vs self-ID iterations per estimation method (Fig. 5)",
)
