"""The valid inverse-Jacobian region over the workspace: bounds per start configuration against its dexterity.

The paper's valid-region study (Sec. III-C, Fig. 2) pools its start
configurations; here each configuration gets its own bounds, and the
configurations are drawn to span the arm's manipulability: ``candidates``
configurations are sampled (joint limits or the sampling box), binned into
``n_bins`` quantiles of the task Jacobian's manipulability, and ``n_configs /
n_bins`` are drawn from each bin. Every row (configuration x ``eps_limit`` x
trial) follows the star with ``m_eps * Jinv_true(q)``, ``m_eps`` entries
``uniform(1, eps_limit)`` held for the rollout, exactly as
``experiments/valid_region.py``; no feasibility filter, so configurations
where even the exact inverse fails (an outstretched elbow) are counted and
reported.

The prediction. With ``Jhat = m_eps * Jinv`` the error after one full-gain,
unclipped control step is ``(I - gain J Jhat) e``, so the loop converges iff
the spectral radius ``rho(I - gain J Jhat) < 1`` (for a uniform ``m_eps = c``,
``rho = |1 - c|``: stable for ``0 < c < 2``). Each row computes ``rho`` for
its own ``m_eps`` and the stable fraction over ``prediction_draws`` fresh
draws at the start configuration; the predicted upper bound is where that
fraction drops below the completion threshold. It ignores what the simulation
has: step clipping (large errors move at ``max_step``, a smaller effective
gain), the step budget and tolerance (they set the lower bound), joint limits
and the Jacobian changing along the path.
"""

from __future__ import annotations

from typing import Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import Field

from selfid_jax import control
from selfid_jax.control import paths
from selfid_jax.runner import Experiment, Part, precision
from selfid_jax.runner.grids import grid_table, row_keys
from selfid_jax.systems import System, manipulability

from .common.lazy_figures import figures_plot
from .common.region import valid_region_bounds
from .common.schema import (
    ControllerConfig,
    EpsLimits,
    HostOrDevice,
    PathConfig,
    StudyConfig,
    controller_rows,
)
from .common.specs import SystemSpec, build_system, needs_x64, system_name


class ValidRegionWorkspaceConfig(StudyConfig):
    """Valid region per start configuration, configurations stratified by manipulability; predicted beside it."""

    experiment: Literal["valid_region_workspace"] = "valid_region_workspace"
    system: SystemSpec = Field("arm5", description="a built-in name or {mjcf: ...} / {pose_fn: ...}")
    n_configs: int = Field(ge=1, le=10**4, description="start configurations (a multiple of n_bins)")
    n_bins: int = Field(10, ge=1, le=1000, description="manipulability quantile bins the starts are drawn from")
    candidates: int = Field(20000, ge=10, le=10**7, description="configurations sampled to form the bins")
    sample: Literal["limits", "box"] = Field("box", description="candidates uniform in the sampling box or limits")
    eps_limits: EpsLimits
    n_trials: int = Field(ge=1, le=10**4, description="m_eps draws (rollouts) per configuration and eps_limit")
    prediction_draws: int = Field(64, ge=1, le=10**4, description="m_eps draws per row for the predicted bound")
    controller: ControllerConfig = ControllerConfig()
    path: PathConfig
    completion_threshold: float = Field(0.95, gt=0, le=1)
    chunk_size: int = Field(4096, gt=0, le=10**7)


class Static(NamedTuple):
    system: System
    path: jax.Array  # (W, task_dim) star offsets [m]
    steps: int  # control-step budget
    draws: int  # m_eps draws for the prediction


class Params(NamedTuple):
    eps_limit: HostOrDevice  # ()
    key: HostOrDevice  # (2,) uint32 key data of the row
    q0: HostOrDevice  # (n,) start configuration
    controller: control.ControllerParams  # () each


class Outputs(NamedTuple):
    completion: jax.Array  # () fraction of the star's waypoints reached
    mean_error: jax.Array  # () [m]
    failed: jax.Array  # () bool
    steps_used: jax.Array  # () int32
    spectral_radius: jax.Array  # () rho(I - gain J(q0) (m_eps * Jinv(q0))) of this rollout's m_eps
    predicted_stable: jax.Array  # () fraction of prediction_draws fresh m_eps with rho < 1


def scaling_matrix(key, eps_limit, shape):
    """``m_eps`` of ``shape`` with entries ``uniform(1, eps_limit)`` (Sec. III-C)."""
    return 1.0 + (eps_limit - 1.0) * jax.random.uniform(key, shape, dtype=jnp.result_type(float))


def spectral_radius(A, squarings: int = 60):
    """Spectral radius of a square ``A (k, k)`` by repeated normalised squaring: ``lim |A^N|^(1/N)``, ``N = 2^s``.

    Matrix products only (no nonsymmetric eigensolver, which JAX lacks on
    some accelerators); ``log |A^(2^s)| / 2^s`` converges to ``log rho`` for
    every ``A``, at a rate set by the eigenvector conditioning, which 60
    squarings make negligible. 0 for a nilpotent ``A``.
    """
    norm0 = jnp.linalg.norm(A)
    B = A / jnp.where(norm0 > 0, norm0, 1.0)
    log_a = jnp.log(jnp.where(norm0 > 0, norm0, 1.0))
    tiny = jnp.finfo(B.dtype).tiny

    def body(i, carry):
        B, acc, dead = carry
        B2 = B @ B
        nb = jnp.linalg.norm(B2)
        dead = dead | (nb <= tiny)
        acc = acc + jnp.log(jnp.where(nb > tiny, nb, 1.0)) / 2.0 ** (i + 1)
        return B2 / jnp.where(nb > tiny, nb, 1.0), acc, dead

    _, acc, dead = jax.lax.fori_loop(0, squarings, body, (B, jnp.zeros((), B.dtype), norm0 <= 0))
    return jnp.where(dead, 0.0, jnp.exp(log_a + acc))


def compute(static: Static, p: Params) -> Outputs:
    """One rollout with ``m_eps * Jinv_true`` and the one-step error map's spectral radius at ``q0``."""
    system = static.system
    n, m = system.n_act, system.task_dim
    k_roll, k_pred = jax.random.split(jax.random.wrap_key_data(jnp.asarray(p.key)))
    m_eps = scaling_matrix(k_roll, p.eps_limit, (n, m))
    res = control.follow(system, control.scaled_true_inverse(system, m_eps), static.path, p.q0, p.controller,
                         steps=static.steps)
    J = system.jacobian(p.q0)
    Jinv = system.true_inverse_jacobian(p.q0)
    eye = jnp.eye(m, dtype=J.dtype)

    def rho(M):
        return spectral_radius(eye - p.controller.gain * (J @ (M * Jinv)))

    draws = scaling_matrix(k_pred, p.eps_limit, (static.draws, n, m))
    stable = jnp.mean(jax.vmap(rho)(draws) < 1.0)
    return Outputs(res.completion, res.mean_error, res.failed, res.steps_used, rho(m_eps), stable)


def stratified_starts(system: System, key, cfg: ValidRegionWorkspaceConfig) -> tuple[np.ndarray, pd.DataFrame]:
    """``n_configs`` configurations spread over manipulability quantile bins, and their dexterity table."""
    if cfg.n_configs % cfg.n_bins:
        raise ValueError(f"n_configs ({cfg.n_configs}) must be a multiple of n_bins ({cfg.n_bins})")
    low, high = ((system.q_low, system.q_high) if cfg.sample == "limits" else (system.sample_low, system.sample_high))
    if not (np.all(np.isfinite(np.asarray(low))) and np.all(np.isfinite(np.asarray(high)))):
        raise ValueError(f"system {system.name!r} has infinite joint limits; use sample: box")
    k_cand, k_pick = jax.random.split(key)
    cand = jax.random.uniform(k_cand, (cfg.candidates, system.n_act), dtype=jnp.result_type(float), minval=low,
                              maxval=high)
    J = jax.jit(jax.vmap(system.jacobian))(cand)
    mani = np.asarray(manipulability.yoshikawa_manipulability(J))
    cond = np.asarray(manipulability.condition(J))
    order = np.argsort(mani, kind="stable")
    per_bin = cfg.n_configs // cfg.n_bins
    bins = np.array_split(order, cfg.n_bins)
    if min(len(b) for b in bins) < per_bin:
        raise ValueError(f"candidates ({cfg.candidates}) too few for {per_bin} configurations in each of "
                         f"{cfg.n_bins} bins")
    rng = np.random.default_rng(np.asarray(jax.random.key_data(k_pick)))
    picks = np.concatenate([rng.choice(b, per_bin, replace=False) for b in bins])
    bin_of = np.repeat(np.arange(cfg.n_bins), per_bin)
    table = pd.DataFrame({"config_id": np.arange(cfg.n_configs), "manipulability_bin": bin_of,
                          "manipulability": mani[picks], "condition": cond[picks]})
    return np.asarray(cand)[picks], table


def build(cfg: ValidRegionWorkspaceConfig) -> Part:
    """One part: ``n_configs x eps_limits x n_trials`` rows from manipulability-stratified starts."""
    cfg.path.check_controller(cfg.controller)
    x64 = needs_x64(cfg.system)
    with precision(x64):
        name, system = system_name(cfg.system), build_system(cfg.system)
        configs, dexterity = stratified_starts(system, jax.random.key(cfg.seed), cfg)
        path = paths.star(size=cfg.path.size, dim=system.task_dim)
        meta = grid_table({"system": [name], "config_id": range(cfg.n_configs),
                           "eps_limit": list(cfg.eps_limits.values()), "trial": range(cfg.n_trials)})
        meta = meta.merge(dexterity, on="config_id", how="left")
        ids = meta["config_id"].to_numpy()
        params = Params(eps_limit=meta["eps_limit"].to_numpy(float), key=row_keys(cfg.seed + 1, len(meta)),
                        q0=configs[ids], controller=controller_rows(cfg.controller, len(meta)))
    return Part(name, Static(system, path, cfg.controller.steps, cfg.prediction_draws), params, meta, x64)


def _bounds(frame: pd.DataFrame, column: str, threshold: float) -> dict[str, Any]:
    return valid_region_bounds(frame.assign(system="c", completion=frame[column]), threshold)["c"]


def summarize(table: pd.DataFrame, cfg: ValidRegionWorkspaceConfig) -> dict[str, Any]:
    """Per configuration: simulated and predicted bounds with its dexterity; rank correlations; the protocol."""
    rows = []
    for cid, g in table.groupby("config_id", sort=True):
        sim = _bounds(g, "completion", cfg.completion_threshold)
        pred = _bounds(g, "predicted_stable", cfg.completion_threshold)
        rows.append({"config_id": int(cid), "manipulability": float(g["manipulability"].iloc[0]),
                     "condition": float(g["condition"].iloc[0]), "lower": sim["lower"], "upper": sim["upper"],
                     "predicted_lower": pred["lower"], "predicted_upper": pred["upper"]})
    per = pd.DataFrame(rows)
    valid = per.dropna(subset=["upper"])

    def spearman(a: str, b: str) -> float | None:
        both = valid[[a, b]].dropna().astype(float)
        if len(both) < 3 or both[a].nunique() < 2 or both[b].nunique() < 2:
            return None
        return float(both[a].corr(both[b], method="spearman"))

    def median(col: str, frame: pd.DataFrame = valid) -> float | None:
        v = frame[col].dropna().astype(float)
        return float(v.median()) if len(v) else None

    return {
        "system": system_name(cfg.system),
        "completion_threshold": cfg.completion_threshold,
        "controller": cfg.controller.model_dump(),
        "path": cfg.path.model_dump(),
        "n_configs": cfg.n_configs,
        "n_trials": cfg.n_trials,
        "prediction_draws": cfg.prediction_draws,
        "fail_with_exact_inverse": int(per["upper"].isna().sum()),
        "median_upper": median("upper"),
        "median_lower": median("lower"),
        "median_predicted_upper": median("predicted_upper", per),
        "spearman_upper_vs_manipulability": spearman("upper", "manipulability"),
        "spearman_upper_vs_condition": spearman("upper", "condition"),
        "spearman_lower_vs_manipulability": spearman("lower", "manipulability"),
        "spearman_upper_vs_predicted_upper": spearman("upper", "predicted_upper"),
        "median_abs_upper_minus_predicted": median("gap", valid.assign(
            gap=(valid["upper"].astype(float) - valid["predicted_upper"].astype(float)).abs())),
        "configs": per.to_dict(orient="list"),
    }


def report(summary: dict) -> str:
    def f(v):
        return "n/a" if v is None else f"{v:.3g}"

    return (f"{summary['system']}: {summary['n_configs']} start configurations, "
            f"{summary['fail_with_exact_inverse']} fail even with the exact inverse; median valid region "
            f"{f(summary['median_lower'])}x - {f(summary['median_upper'])}x (predicted upper "
            f"{f(summary['median_predicted_upper'])}x, median |simulated - predicted| "
            f"{f(summary['median_abs_upper_minus_predicted'])}); Spearman upper vs manipulability "
            f"{f(summary['spearman_upper_vs_manipulability'])}, vs condition "
            f"{f(summary['spearman_upper_vs_condition'])}")


plot = figures_plot("valid_region_workspace")  # experiments/figures/valid_region_workspace.py, loaded when called


COLUMNS = {
    "system": "system name [label]",
    "config_id": "start configuration index [id]",
    "eps_limit": "upper limit of the scaling entries: m_eps drawn elementwise uniform(1, eps_limit) [-]",
    "trial": "m_eps draw index (one rollout each) [id]",
    "manipulability_bin": "manipulability quantile bin the start was drawn from, 0 the lowest [id]",
    "manipulability": "Yoshikawa's prod sigma of the task Jacobian at the start [task units per actuator unit, "
                      "m^3/rad^3 for a position task]",
    "condition": "sigma_max / sigma_min of the task Jacobian at the start [-]",
    "completion": "fraction of the star's waypoints reached [-]",
    "mean_error": "mean distance of the POM to the path over the steps used [m]",
    "failed": "non-finite state or divergence from the path [bool]",
    "steps_used": "control steps until the last waypoint was reached (or the budget) [steps]",
    "spectral_radius": "rho(I - gain J(q0) (m_eps * Jinv(q0))) of this rollout's m_eps; < 1 predicts convergence [-]",
    "predicted_stable": "fraction of prediction_draws fresh m_eps draws with rho < 1 [-]",
}
"""The results columns (``results.parquet``): one row per start configuration, eps_limit and trial."""


EXPERIMENT = Experiment(
    name="valid_region_workspace",
    config=ValidRegionWorkspaceConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    columns=COLUMNS,
    plot=plot,
    report=report,
    description="valid inverse-Jacobian region per start configuration vs manipulability, with the spectral-radius "
                "prediction",
)
