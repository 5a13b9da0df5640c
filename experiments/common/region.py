"""The valid inverse-Jacobian region from a results table: its bounds around 1 and the curves per eps_limit.

Statistics only (no drawing): the ``valid_region`` and
``valid_region_workspace`` summaries use them, and the figures of
:mod:`selfid_jax.experiments.common.figures` draw them.

Valid-region results table (one row per rollout), columns used here:

    system          str    system name, e.g. "two_link"
    eps_limit       float  m_eps entries ~ uniform(1, eps_limit) (dimensionless)
    config_id       int    sampled start configuration
    trial           int    repetition with a fresh m_eps
    completion      float  fraction of the path completed, in [0, 1]
    mean_error      float  mean tracking error [m]
    max_error       float  max tracking error [m]
    waypoint_error  float  error at reached waypoints [m]
    steps_used      int    control steps used
    failed          bool   rollout diverged / produced non-finite values
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

__all__ = ["VALID_REGION_COLUMNS", "curves", "finite", "require", "valid_region_bounds", "valid_region_summary"]


VALID_REGION_COLUMNS = (
    "system", "eps_limit", "config_id", "trial", "completion",
    "mean_error", "max_error", "waypoint_error", "steps_used", "failed",
)


def require(df: pd.DataFrame, cols: tuple[str, ...]) -> None:
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise ValueError(f"results table lacks column(s) {missing}; has {list(df.columns)}")


def valid_region_bounds(df: pd.DataFrame, threshold: float = 0.95) -> dict[str, dict[str, Any]]:
    """Valid inverse-Jacobian region per system (paper Sec. III-C).

    The region is the contiguous run of ``eps_limit`` grid points around the
    grid point nearest 1.0 (the true inverse Jacobian) where the mean path
    completion over all rollouts is at least ``threshold``. Points beyond a
    failing grid point do not count, even if they pass again further out.

    Args:
      df: results table with columns ``system, eps_limit, completion``.
      threshold: completion fraction in (0, 1], e.g. 0.95.

    Returns:
      ``{system: {"lower": float | None, "upper": float | None, "contains_one": bool}}``;
      bounds are grid values of ``eps_limit``, both ``None`` when the grid
      point nearest 1.0 fails. ``contains_one`` says whether ``lower <= 1 <= upper``.
    """
    require(df, ("system", "eps_limit", "completion"))
    out: dict[str, dict[str, Any]] = {}
    for system, g in df.groupby("system", sort=False):
        mean = g.groupby("eps_limit")["completion"].mean().sort_index()
        eps = mean.index.to_numpy(float)
        ok = mean.to_numpy(float) >= threshold  # NaN fails
        i = int(np.argmin(np.abs(eps - 1.0)))
        if not ok[i]:
            out[str(system)] = {"lower": None, "upper": None, "contains_one": False}
            continue
        lo = hi = i
        while lo > 0 and ok[lo - 1]:
            lo -= 1
        while hi < len(ok) - 1 and ok[hi + 1]:
            hi += 1
        lower, upper = float(eps[lo]), float(eps[hi])
        out[str(system)] = {"lower": lower, "upper": upper, "contains_one": bool(lower <= 1.0 <= upper)}
    return out


def finite(x: pd.Series) -> pd.Series:
    return x.astype(float).replace([np.inf, -np.inf], np.nan)


def curves(g: pd.DataFrame, col: str) -> pd.DataFrame:
    """Per eps_limit: mean over rollouts, and min/max over per-config means (band)."""
    vals = g.assign(_v=finite(g[col]))
    mean = vals.groupby("eps_limit")["_v"].mean()
    if "config_id" in vals.columns:
        per_cfg = vals.groupby(["eps_limit", "config_id"])["_v"].mean().groupby(level=0)
        lo, hi = per_cfg.min(), per_cfg.max()
    else:
        sd = vals.groupby("eps_limit")["_v"].std()
        lo, hi = mean - sd, mean + sd
    return pd.DataFrame({"mean": mean, "lo": lo, "hi": hi}).sort_index()


def valid_region_summary(df: pd.DataFrame, threshold: float = 0.95, **extra: Any) -> dict[str, Any]:
    """Summary dict for ``summary.json``: bounds and per-eps curves per system.

    Returns ``{"completion_threshold": t, "systems": {system: {"lower",
    "upper", "contains_one", "n_rollouts", "eps_limit": [...],
    "mean_completion": [...], "mean_error": [...] (m), "failed_fraction":
    [...]}}, **extra}``; pass the controller protocol in ``extra`` (e.g.
    ``controller=cfg.controller.model_dump()``) so it is stated beside the bounds.
    """
    bounds = valid_region_bounds(df, threshold)
    systems: dict[str, Any] = {}
    for system, g in df.groupby("system", sort=False):
        comp = curves(g, "completion")
        entry: dict[str, Any] = dict(bounds[str(system)])
        entry["n_rollouts"] = int(len(g))
        entry["eps_limit"] = comp.index.to_numpy(float).tolist()
        entry["mean_completion"] = comp["mean"].to_numpy(float).tolist()
        if "mean_error" in g.columns:
            entry["mean_error"] = curves(g, "mean_error")["mean"].to_numpy(float).tolist()
        if "failed" in g.columns:
            entry["failed_fraction"] = g.groupby("eps_limit")["failed"].mean().sort_index().to_numpy(float).tolist()
        systems[str(system)] = entry
    return {"completion_threshold": float(threshold), **extra, "systems": systems}
