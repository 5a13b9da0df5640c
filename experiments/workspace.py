"""Reachable-workspace maps (seed 004, "Visualizing the Reachable Workspace"): dexterity over sampled configurations.

Every row is one configuration drawn uniformly in the joint limits (or the
system's sampling box); one compiled call gives its tool position and the
dexterity metrics of its 6-row geometric Jacobian
(:mod:`selfid_jax.systems.manipulability`): seed 004's manipulability
``sqrt(prod sigma)``, Yoshikawa's ``prod sigma``, the mixed-unit condition, the
position-only (3-row) versions and the unit-consistent condition (rotation
rows times ``length``). ``summarize`` and ``plot`` bin the tool positions into
square cells in the r-z plane (``r = sqrt(x^2 + y^2)``: the arm's plane swept
around its base) and in the x-z plane (every configuration projected along y)
and draw per cell the maximum and mean manipulability and the minimum
condition, as images. The maps are binned from the saved table (``plot`` and
``summarize`` never re-simulate), so :func:`cell_maps` re-bins a run at any
cell size from Python.

From the command line::

    selfid-jax sweep configs/workspace/workspace_arm5.yaml        # 50k configurations
    selfid-jax sweep configs/workspace/workspace_arm5_full.yaml   # 1M configurations
"""

from __future__ import annotations

from typing import Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import Field

from selfid_jax.runner import Experiment, Part, precision
from selfid_jax.runner.grids import row_keys
from selfid_jax.systems import System, manipulability

from .common.lazy_figures import figures_plot
from .common.schema import HostOrDevice, StudyConfig
from .common.specs import SystemSpec, build_system, needs_x64, system_name

PLANES = ("rz", "xz")
METRIC_COLUMNS = ("sqrt_manipulability", "yoshikawa", "condition", "position_sqrt_manipulability",
                  "position_yoshikawa", "position_condition", "unit_consistent_condition")


class WorkspaceConfig(StudyConfig):
    """Reachable-workspace maps: ``n_configs`` configurations, their tool positions and dexterity, binned in cells."""

    experiment: Literal["workspace"] = "workspace"
    system: SystemSpec = Field("arm5", description="a built-in name or {mjcf: ...} / {pose_fn: ...} with orientation")
    n_configs: int = Field(ge=1, le=10**8, description="configurations sampled (one row each)")
    sample: Literal["limits", "box"] = Field("limits", description="uniform in the joint limits or the sampling box")
    length: float = Field(0.1, gt=0, le=100, description="characteristic length L [m] of the unit-consistent "
                          "condition (rotation rows times L)")
    cell: float = Field(0.01, gt=0, le=10, description="map cell size [m]")
    x64: bool = Field(False, description="float64 kinematics (default float32, about 1.7x faster)")
    chunk_size: int = Field(65536, gt=0, le=10**7, description="configurations per compiled chunk")


class Static(NamedTuple):
    system: System  # task_dim 6: the geometric Jacobian [Jv; Jw]
    low: jax.Array  # (n,) sampling box [rad / m]
    high: jax.Array  # (n,)


class Params(NamedTuple):
    key: HostOrDevice  # (2,) uint32 PRNG key data of the configuration
    length: HostOrDevice  # () characteristic length [m]


class Outputs(NamedTuple):
    x: jax.Array  # () tool position [m]
    y: jax.Array
    z: jax.Array
    sqrt_manipulability: jax.Array  # () seed 004's omega = sqrt(prod sigma(J)), J 6 x n
    yoshikawa: jax.Array  # () prod sigma(J)
    condition: jax.Array  # () sigma_max / sigma_min of the mixed-unit J
    position_sqrt_manipulability: jax.Array  # () of Jv (3 x n)
    position_yoshikawa: jax.Array  # () [m^3/rad^3]
    position_condition: jax.Array  # ()
    unit_consistent_condition: jax.Array  # () of [Jv; L Jw]


def compute(static: Static, p: Params) -> Outputs:
    """One configuration: draw ``q``, one kinematics pass for pose and Jacobian, three SVDs."""
    system = static.system
    q = jax.random.uniform(jax.random.wrap_key_data(jnp.asarray(p.key)), (system.n_act,), dtype=static.low.dtype,
                           minval=static.low, maxval=static.high)
    (pos, _), J = system.pose_and_jacobian(q)
    m = manipulability.metrics(J, p.length)
    return Outputs(pos[0], pos[1], pos[2], *(getattr(m, c) for c in METRIC_COLUMNS))


def build(cfg: WorkspaceConfig) -> Part:
    """One part: ``n_configs`` rows of (key, length); the system at task dimension 6."""
    x64 = cfg.x64 or needs_x64(cfg.system)
    with precision(x64):
        system = build_system(cfg.system)
        if not system.has_rotation:
            raise ValueError(f"system {system_name(cfg.system)!r} has no orientation: the workspace maps need the "
                             "6-row geometric Jacobian")
        system = system.with_task_dim(6)
        if cfg.sample == "limits":
            low, high = np.asarray(system.q_low), np.asarray(system.q_high)
            if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
                raise ValueError(f"system {system_name(cfg.system)!r} has infinite joint limits; use sample: box")
        else:
            low, high = np.asarray(system.sample_low), np.asarray(system.sample_high)
        n = cfg.n_configs
        params = Params(key=row_keys(cfg.seed, n), length=np.full((n,), cfg.length))
        meta = pd.DataFrame({"system": pd.Categorical(np.full(n, system_name(cfg.system)))})
        static = Static(system, jnp.asarray(low), jnp.asarray(high))
    return Part(system_name(cfg.system), static, params, meta, x64)


# ------------------------------------------------------------------ binning (numpy, from the saved table)
class CellMap(NamedTuple):
    """Per-cell statistics on a regular grid (NaN where no configuration fell)."""

    extent: tuple[float, float, float, float]  # (h_min, h_max, z_min, z_max) [m], for imshow
    count: np.ndarray  # type: ignore[assignment]  # (nz, nh) configurations per cell; shadows tuple.count
    max_manipulability: np.ndarray  # (nz, nh)
    mean_manipulability: np.ndarray  # (nz, nh)
    min_condition: np.ndarray  # (nz, nh)


def cell_maps(table: pd.DataFrame, cell: float, plane: str, *, manipulability_column: str = "sqrt_manipulability",
              condition_column: str = "condition") -> CellMap:
    """Bin the tool positions of ``table`` into ``cell``-sized squares of the ``plane`` (``"rz"`` or ``"xz"``)."""
    if plane not in PLANES:
        raise ValueError(f"plane must be one of {PLANES}, got {plane!r}")
    if not cell > 0:
        raise ValueError(f"cell must be > 0, got {cell}")
    x, z = table["x"].to_numpy(np.float64), table["z"].to_numpy(np.float64)
    h = np.hypot(x, table["y"].to_numpy(np.float64)) if plane == "rz" else x
    ok = np.isfinite(h) & np.isfinite(z)
    h, z = h[ok], z[ok]
    h0, z0 = np.floor(h.min() / cell) * cell, np.floor(z.min() / cell) * cell
    ih, iz = ((h - h0) / cell).astype(np.int64), ((z - z0) / cell).astype(np.int64)
    nh, nz = int(ih.max()) + 1, int(iz.max()) + 1
    flat = iz * nh + ih
    mani = table[manipulability_column].to_numpy(np.float64)[ok]
    cond = table[condition_column].to_numpy(np.float64)[ok]
    frame = pd.DataFrame({"cell": flat, "m": mani, "c": cond})
    g = frame.groupby("cell")
    stats = pd.DataFrame({"count": g.size(), "max": g["m"].max(), "mean": g["m"].mean(), "min": g["c"].min()})
    out = {}
    for k in ("count", "max", "mean", "min"):
        grid = np.full(nz * nh, np.nan)
        grid[stats.index.to_numpy()] = stats[k].to_numpy()
        out[k] = grid.reshape(nz, nh)
    count = np.nan_to_num(out["count"], nan=0.0).astype(np.int64)
    return CellMap((h0, h0 + nh * cell, z0, z0 + nz * cell), count, out["max"], out["mean"], out["min"])


def _finite_stats(s: pd.Series) -> dict[str, float | None]:
    v = s.to_numpy(np.float64)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"min": None, "median": None, "max": None}
    return {"min": float(v.min()), "median": float(np.median(v)), "max": float(v.max())}


def summarize(table: pd.DataFrame, cfg: WorkspaceConfig) -> dict[str, Any]:
    """Reached cells per plane, metric ranges, and the settings beside them."""
    maps = {plane: cell_maps(table, cfg.cell, plane) for plane in PLANES}
    return {
        "system": system_name(cfg.system),
        "n_configs": int(len(table)),
        "sample": cfg.sample,
        "cell_m": cfg.cell,
        "length_m": cfg.length,
        "x64": cfg.x64,
        "cells_reached": {plane: int((m.count > 0).sum()) for plane, m in maps.items()},
        "area_reached_m2": {plane: float((m.count > 0).sum() * cfg.cell**2) for plane, m in maps.items()},
        "extent_m": {plane: [float(v) for v in m.extent] for plane, m in maps.items()},
        "metrics": {c: _finite_stats(table[c]) for c in METRIC_COLUMNS},
        "singular_fraction": {c: float(np.mean(~np.isfinite(table[c].to_numpy(np.float64))))
                              for c in ("condition", "position_condition", "unit_consistent_condition")},
    }


def report(summary: dict) -> str:
    """Cells reached and the ranges of manipulability and condition."""
    m = summary["metrics"]
    lines = [
        f"{summary['system']}: {summary['n_configs']} configurations, {summary['cells_reached']['rz']} r-z and "
        f"{summary['cells_reached']['xz']} x-z cells of {1e3 * summary['cell_m']:g} mm reached",
        f"  manipulability sqrt(prod sigma), 6 x n: max {m['sqrt_manipulability']['max']:.4g}, "
        f"median {m['sqrt_manipulability']['median']:.4g}",
        f"  condition (mixed units) min {m['condition']['min']:.3g}; position-only min "
        f"{m['position_condition']['min']:.3g}; unit-consistent (L = {summary['length_m']:g} m) min "
        f"{m['unit_consistent_condition']['min']:.3g}",
    ]
    return "\n".join(lines)


plot = figures_plot("workspace")  # experiments/figures/workspace.py, imported (with matplotlib) when called


COLUMNS = {
    "system": "system name [label]",
    "x": "tool position x [m]",
    "y": "tool position y [m]",
    "z": "tool position z [m]",
    "sqrt_manipulability": "seed 004's omega = sqrt(prod sigma) of the 6 x n geometric Jacobian [mixed units]",
    "yoshikawa": "Yoshikawa's prod sigma of the 6 x n geometric Jacobian [mixed units]",
    "condition": "sigma_max / sigma_min of the mixed-unit 6 x n Jacobian (depends on the length unit) [-]",
    "position_sqrt_manipulability": "sqrt(prod sigma) of the position rows Jv (3 x n) [m^1.5/rad^1.5]",
    "position_yoshikawa": "prod sigma of the position rows Jv (3 x n) [m^3/rad^3]",
    "position_condition": "sigma_max / sigma_min of the position rows Jv [-]",
    "unit_consistent_condition": "sigma_max / sigma_min of [Jv; L Jw], L the config's length [-]",
}
"""The results columns (``results.parquet``): one row per sampled configuration (revolute joints: rad)."""


EXPERIMENT = Experiment(
    name="workspace",
    config=WorkspaceConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    columns=COLUMNS,
    plot=plot,
    report=report,
    description="reachable-workspace maps: manipulability and condition per r-z / x-z cell (seed 004)",
)
