"""Valid inverse-Jacobian region (paper Sec. III-C, Fig. 2), as one batched computation per system.

For each ``eps_limit`` on the grid, each start configuration and each trial, a
scaling matrix ``m_eps (n, m)`` is drawn elementwise from
``uniform(1, eps_limit)`` (below 1 when ``eps_limit < 1``) and held for the
trial; the controller follows the star path with ``m_eps * Jinv_true(q)`` at
every step. Start configurations are drawn away from singularities and kept
only if the true inverse Jacobian completes the path from them
(:func:`selfid_jax.control.feasible_starts`). The valid region is the contiguous range of ``eps_limit`` around 1
where the mean path completion reaches the threshold.

From Python::

    from selfid_jax.config import load_config
    from experiments.valid_region import study
    df = study(load_config("configs/valid_region_two_link.yaml"), "runs/vr")   # one row per rollout

``selfid-jax sweep configs/valid_region_ur5e.yaml`` runs the same and also
writes ``summary.json`` and the figures.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from selfid_jax import control, paths, plots
from selfid_jax.config import ValidRegionConfig
from selfid_jax.results import write_results, write_summary
from selfid_jax.sweep import grid_table, register_experiment, row_keys, run_chunked
from selfid_jax.systems import System, two_link, ur5e

SYSTEMS = {
    "two_link": lambda: two_link(),
    "ur5e": lambda: ur5e(task_dim=3),
}


def build_system(name: str) -> System:
    """The named system of the study (position tasks: 2-link xy, UR5e xyz)."""
    return SYSTEMS[name]()


def scaling_matrix(key, eps_limit, shape):
    """``m_eps`` of ``shape`` with entries ``uniform(1, eps_limit)`` (Sec. III-C)."""
    u = jax.random.uniform(key, shape, dtype=jnp.result_type(float))
    return 1.0 + (eps_limit - 1.0) * u


def make_compute(system: System, cfg: ValidRegionConfig):
    """Batched rollout function: params ``{eps_limit (B,), key (B, 2), q0 (B, n)}`` -> metric columns."""
    path = paths.star(size=cfg.path.size, dim=system.task_dim)
    ctrl = cfg.controller

    def one(eps_limit, key_data, q0):
        m_eps = scaling_matrix(jax.random.wrap_key_data(key_data), eps_limit, (system.n_act, system.task_dim))
        res = control.follow(
            system,
            control.scaled_true_inverse(system, m_eps),
            path,
            q0,
            steps=ctrl.steps,
            max_step=ctrl.max_step,
            tol=ctrl.tol,
            gain=ctrl.gain,
        )
        return {
            "completion": res.completion,
            "mean_error": res.mean_error,
            "max_error": res.max_error,
            "waypoint_error": res.waypoint_error,
            "steps_used": res.steps_used,
            "failed": res.failed,
        }

    def compute(params):
        return jax.vmap(one)(params["eps_limit"], params["key"], params["q0"])

    return compute


def system_grid(cfg: ValidRegionConfig, name: str, system: System) -> tuple[pd.DataFrame, dict]:
    """Meta table and parameter arrays of one system's part of the grid."""
    meta = grid_table(
        {
            "system": [name],
            "eps_limit": cfg.eps_limits.values(),
            "config_id": range(cfg.n_configs),
            "trial": range(cfg.n_trials),
        }
    )
    ctrl = cfg.controller
    configs = np.asarray(
        control.feasible_starts(
            system, paths.star(size=cfg.path.size, dim=system.task_dim), jax.random.key(cfg.seed), cfg.n_configs,
            steps=ctrl.steps, max_step=ctrl.max_step, tol=ctrl.tol, gain=ctrl.gain,
        )
    )
    params = {
        "eps_limit": meta["eps_limit"].to_numpy(float),
        "key": row_keys(cfg.seed, len(meta)),
        "q0": configs[meta["config_id"].to_numpy()],
    }
    return meta, params


def study(cfg: ValidRegionConfig, out_dir: str | Path | None = None, *, fresh: bool = False,
          progress: bool = False) -> pd.DataFrame:
    """Run the study; returns the tidy results table (one row per rollout).

    Each system is one compiled batched function run in chunks of
    ``cfg.chunk_size`` rollouts under ``out_dir/systems/<name>/`` (resumable);
    the combined table is written to ``out_dir/results.parquet``. Without
    ``out_dir`` a temporary directory is used.
    """
    if out_dir is None:
        with tempfile.TemporaryDirectory() as tmp:
            return study(cfg, tmp, fresh=True, progress=progress)
    out_dir = Path(out_dir)
    tables = []
    for name in cfg.systems:
        system = build_system(name)
        meta, params = system_grid(cfg, name, system)
        df = run_chunked(
            make_compute(system, cfg),
            params,
            chunk_size=cfg.chunk_size,
            out_dir=out_dir / "systems" / name,
            meta=meta,
            fresh=fresh,
            progress=progress,
            desc=name,
        )
        if df is None:  # another process of a jax.distributed run writes the files
            return None
        tables.append(df.drop(columns=["row"]))
    df = pd.concat(tables, ignore_index=True)
    write_results(out_dir, df)
    return df


def run(cfg: ValidRegionConfig, out_dir: Path, fresh: bool, progress: bool) -> None:
    """CLI runner: the study, then ``summary.json`` with the bounds and the protocol beside them."""
    df = study(cfg, out_dir, fresh=fresh, progress=progress)
    if df is None or jax.process_index() != 0:
        return
    summary = plots.valid_region_summary(
        df,
        cfg.completion_threshold,
        controller=cfg.controller.model_dump(),
        path=cfg.path.model_dump(),
        n_configs=cfg.n_configs,
        n_trials=cfg.n_trials,
    )
    write_summary(out_dir, summary)
    for system, entry in summary["systems"].items():
        if entry["lower"] is None:
            print(f"{system}: no valid region around 1 ({entry['n_rollouts']} rollouts)")
        else:
            print(f"{system}: valid region {entry['lower']:.3g}x - {entry['upper']:.3g}x the true inverse Jacobian "
                  f"({entry['n_rollouts']} rollouts)")


register_experiment("valid_region", run, plots.valid_region_figure)
