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
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated, Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax import baselines, control, paths, plots, selfid
from selfid_jax.config import BaseConfig, ControllerConfig, PathConfig, register_experiment_config
from selfid_jax.results import write_results, write_summary
from selfid_jax.sweep import grid_table, register_experiment, row_keys, run_chunked
from selfid_jax.systems import ur5e

_STRICT = dict(extra="forbid", frozen=True, strict=True)


class MethodSpec(BaseModel):
    """One curve of the ablation: a label, a method of ``selfid_jax.baselines`` and its options."""

    model_config = dict(extra="forbid", frozen=True)

    name: str = Field(min_length=1, description="label of the curve")
    method: Literal[baselines.METHOD_NAMES] = Field(description="one of " + ", ".join(baselines.METHOD_NAMES))
    options: dict[str, float | int | str | bool] = Field(default_factory=dict)


class AblationConfig(BaseConfig):
    """Estimation ablation on the UR5e (Sec. V-A)."""

    experiment: Literal["ablation"] = "ablation"
    system: Literal["ur5e"] = "ur5e"
    methods: Annotated[list[MethodSpec], Field(min_length=1)]
    iterations: Annotated[list[Annotated[int, Field(ge=1)]], Field(min_length=1)]
    n_configs: int = Field(ge=1)
    n_trials: int = Field(ge=1)
    pose_noise: Annotated[list[Annotated[float, Field(ge=0)]], Field(min_length=1)]
    rot_noise: Annotated[list[Annotated[float, Field(ge=0)]], Field(min_length=1)]
    m_a: Annotated[list[Annotated[float, Field(gt=0, le=0.1)]], Field(min_length=1)]
    eps: float = Field(gt=0, description="Sec. IV-D convergence threshold on ||J_t - J_{t-1}||_F")
    controller: ControllerConfig
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
        names = [m.name for m in methods]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"method names must be unique, repeated: {', '.join(dup)}")
        for spec in methods:
            baselines.get_method(spec.method, **spec.options)  # unknown options raise here, before compute
        return methods

    @model_validator(mode="after")
    def _noise_pairs(self):
        if len(self.pose_noise) != len(self.rot_noise):
            raise ValueError(
                f"pose_noise and rot_noise pair up level by level: lengths {len(self.pose_noise)} "
                f"and {len(self.rot_noise)} differ"
            )
        return self


register_experiment_config("ablation", AblationConfig)


def convergence_iteration(estimates, eps):
    """First iteration (1-based) where ``||J_t - J_{t-1}||_F <= eps`` twice in a row, -1 if none. ``(T, n, m)``."""
    prev = jnp.concatenate([jnp.zeros_like(estimates[:1]), estimates[:-1]], axis=0)
    small = jnp.sqrt(jnp.sum((estimates - prev) ** 2, axis=(1, 2))) <= eps
    both = small & jnp.concatenate([jnp.zeros((1,), bool), small[:-1]])
    return jnp.where(jnp.any(both), jnp.argmax(both) + 1, -1).astype(jnp.int32)


def make_compute(cfg: AblationConfig, system):
    """Batched function: params ``{key, q0 (B, n), pose_noise, rot_noise, m_a (B,)}`` -> per-method metrics."""
    path = paths.star(size=cfg.path.size, dim=system.task_dim)
    ctrl = dict(steps=cfg.controller.steps, max_step=cfg.controller.max_step, tol=cfg.controller.tol,
                gain=cfg.controller.gain)
    T = max(cfg.iterations)
    checkpoints = jnp.asarray(cfg.iterations) - 1
    methods = [(spec.name, baselines.get_method(spec.method, **spec.options)) for spec in cfg.methods]

    def one(key_data, q0, pose_noise, rot_noise, m_a):
        k_sid, k_est = jax.random.split(jax.random.wrap_key_data(key_data))
        sid = selfid.run(system, k_sid, q0, iters=T, eps=cfg.eps, m_a=m_a, pose_noise=pose_noise,
                         rot_noise=rot_noise, stop_at_convergence=False)
        truth = system.true_inverse_jacobian(q0)
        out = {}
        for name, method in methods:
            est = baselines.run_stream(method, k_est, sid.dtheta, sid.V, truth)
            if method.name == "true":
                res = control.follow(system, control.true_inverse(system), path, q0, **ctrl)
                res = jax.tree.map(lambda x: jnp.broadcast_to(x, checkpoints.shape + jnp.shape(x)), res)
            else:
                res = jax.vmap(lambda J: control.follow(system, control.fixed(J), path, q0, **ctrl))(est[checkpoints])
            out[f"{name}/completion"] = res.completion
            out[f"{name}/mean_error"] = res.mean_error
            out[f"{name}/failed"] = res.failed
            out[f"{name}/converged_at"] = convergence_iteration(est, cfg.eps)
        return out

    def compute(p):
        return jax.vmap(one)(p["key"], p["q0"], p["pose_noise"], p["rot_noise"], p["m_a"])

    return compute


def grid(cfg: AblationConfig, system) -> tuple[pd.DataFrame, dict[str, np.ndarray]]:
    """Meta table and parameter arrays: configs x trials x noise levels x m_a."""
    meta = grid_table(
        {
            "noise_level": range(len(cfg.pose_noise)),
            "m_a": cfg.m_a,
            "config_id": range(cfg.n_configs),
            "trial": range(cfg.n_trials),
        }
    )
    meta.insert(1, "pose_noise", np.asarray(cfg.pose_noise)[meta["noise_level"]])
    meta.insert(2, "rot_noise", np.asarray(cfg.rot_noise)[meta["noise_level"]])
    path = paths.star(size=cfg.path.size, dim=system.task_dim)
    c = cfg.controller
    configs = np.asarray(control.feasible_starts(system, path, jax.random.key(cfg.seed), cfg.n_configs,
                                                 steps=c.steps, max_step=c.max_step, tol=c.tol, gain=c.gain))
    params = {
        "key": row_keys(cfg.seed, len(meta)),
        "q0": configs[meta["config_id"].to_numpy()],
        "pose_noise": meta["pose_noise"].to_numpy(float),
        "rot_noise": meta["rot_noise"].to_numpy(float),
        "m_a": meta["m_a"].to_numpy(float),
    }
    return meta, params


def to_long(wide: pd.DataFrame, cfg: AblationConfig) -> pd.DataFrame:
    """Wide chunk table (list columns per method) -> one row per (grid row, method, iteration count)."""
    base_cols = ["noise_level", "pose_noise", "rot_noise", "m_a", "config_id", "trial"]
    frames = []
    its = np.asarray(cfg.iterations)
    for spec in cfg.methods:
        n = spec.name
        comp = np.stack(wide[f"{n}/completion"].to_numpy())
        err = np.stack(wide[f"{n}/mean_error"].to_numpy())
        fail = np.stack(wide[f"{n}/failed"].to_numpy())
        rows = len(wide)
        df = wide[base_cols].loc[wide.index.repeat(len(its))].reset_index(drop=True)
        df.insert(0, "method", n)
        df["iterations"] = np.tile(its, rows)
        df["completion"] = comp.reshape(-1)
        df["mean_error"] = err.reshape(-1)
        df["failed"] = fail.reshape(-1).astype(bool)
        df["converged_at"] = np.repeat(wide[f"{n}/converged_at"].to_numpy(), len(its))
        frames.append(df)
    return pd.concat(frames, ignore_index=True)


def study(cfg: AblationConfig, out_dir: str | Path | None = None, *, fresh: bool = False,
          progress: bool = False) -> pd.DataFrame | None:
    """Run the ablation; returns the tidy long table (also written to ``out_dir/results.parquet``)."""
    if out_dir is None:
        with tempfile.TemporaryDirectory() as tmp:
            return study(cfg, tmp, fresh=True, progress=progress)
    out_dir = Path(out_dir)
    system = ur5e(task_dim=3)
    meta, params = grid(cfg, system)
    wide = run_chunked(make_compute(cfg, system), params, chunk_size=cfg.chunk_size,
                       out_dir=out_dir / "systems" / cfg.system, meta=meta, fresh=fresh, progress=progress,
                       desc="ablation")
    if wide is None:
        return None
    df = to_long(wide, cfg)
    write_results(out_dir, df)
    return df


def summarize(df: pd.DataFrame, cfg: AblationConfig) -> dict[str, Any]:
    """Per method (noise-free, first m_a): iterations to reach the completion threshold, convergence stats."""
    clean = df[(df.noise_level == 0) & (df.m_a == cfg.m_a[0])]
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
        "controller": cfg.controller.model_dump(),
        "path": cfg.path.model_dump(),
        "methods": methods,
        "completion_at_max_iterations_by_pose_noise": {
            str(m): {str(k): float(v) for k, v in row.items()} for m, row in noise.iterrows()
        },
    }


def run(cfg: AblationConfig, out_dir: Path, fresh: bool, progress: bool) -> None:
    """CLI runner: the ablation, then ``summary.json``."""
    df = study(cfg, out_dir, fresh=fresh, progress=progress)
    if df is None or jax.process_index() != 0:
        return
    summary = summarize(df, cfg)
    write_summary(out_dir, summary)
    print(f"{'method':24s} {'iters to ' + format(cfg.completion_threshold, '.0%'):>14s} {'converged at':>16s}")
    for name, s in summary["methods"].items():
        conv = s["convergence_iteration_mean"]
        conv_txt = f"{conv:.1f} +- {s['convergence_iteration_sd']:.1f}" if conv is not None else "never"
        print(f"{name:24s} {str(s['iterations_to_threshold']):>14s} {conv_txt:>16s}")


register_experiment("ablation", run, plots.ablation_figures)
