"""Figures drawn from saved results only (a results DataFrame and a summary dict).

Nothing here simulates: ``selfid-jax plot RUN_DIR`` loads ``results.parquet``
and ``summary.json`` and calls these functions. Figures are written as PNG and
PDF through matplotlib's ``Figure`` API (Agg/PDF canvases, no pyplot state, no
display needed).

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

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from selfid_jax.runner.figures import save_figure

__all__ = [
    "VALID_REGION_COLUMNS",
    "ablation_figures",
    "save_figure",
    "valid_region_bounds",
    "valid_region_figure",
    "valid_region_summary",
]

VALID_REGION_COLUMNS = (
    "system", "eps_limit", "config_id", "trial", "completion",
    "mean_error", "max_error", "waypoint_error", "steps_used", "failed",
)


def _require(df: pd.DataFrame, cols: tuple[str, ...]) -> None:
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
    _require(df, ("system", "eps_limit", "completion"))
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


def _finite(x: pd.Series) -> pd.Series:
    return x.astype(float).replace([np.inf, -np.inf], np.nan)


def _curves(g: pd.DataFrame, col: str) -> pd.DataFrame:
    """Per eps_limit: mean over rollouts, and min/max over per-config means (band)."""
    vals = g.assign(_v=_finite(g[col]))
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
        comp = _curves(g, "completion")
        entry: dict[str, Any] = dict(bounds[str(system)])
        entry["n_rollouts"] = int(len(g))
        entry["eps_limit"] = comp.index.to_numpy(float).tolist()
        entry["mean_completion"] = comp["mean"].to_numpy(float).tolist()
        if "mean_error" in g.columns:
            entry["mean_error"] = _curves(g, "mean_error")["mean"].to_numpy(float).tolist()
        if "failed" in g.columns:
            entry["failed_fraction"] = g.groupby("eps_limit")["failed"].mean().sort_index().to_numpy(float).tolist()
        systems[str(system)] = entry
    return {"completion_threshold": float(threshold), **extra, "systems": systems}


def _protocol_text(summary: Mapping[str, Any]) -> str:
    ctrl = summary.get("controller")
    parts = [f"valid: mean completion >= {summary.get('completion_threshold', 0.95):g}"]
    if isinstance(ctrl, Mapping):
        parts.append("controller: " + ", ".join(f"{k}={v}" for k, v in ctrl.items()))
    return "; ".join(parts)


def valid_region_figure(
    df: pd.DataFrame, summary: Mapping[str, Any], out_dir: str | Path, *, name: str = "valid_region"
) -> list[Path]:
    """Paper Fig. 2: path completion and tracking error vs ``eps_limit``, one column per system.

    Top row: mean path completion [%] over all rollouts, band = min..max of
    the per-configuration means, dotted line at the threshold. Bottom row:
    mean tracking error [m] (log axis when it spans > 2 decades), same band.
    Dashed vertical lines mark the valid-region bounds, taken from
    ``summary["systems"][system]`` when present, else computed with
    :func:`valid_region_bounds` at ``summary["completion_threshold"]`` (0.95).

    Returns:
      ``[out_dir/<name>.png, out_dir/<name>.pdf]``.
    """
    _require(df, ("system", "eps_limit", "completion", "mean_error"))
    threshold = float(summary.get("completion_threshold", 0.95))
    bounds = valid_region_bounds(df, threshold)
    saved = summary.get("systems", {}) if isinstance(summary.get("systems"), Mapping) else {}
    systems = [str(s) for s in df["system"].drop_duplicates()]
    ncol = max(len(systems), 1)
    fig = Figure(figsize=(3.6 * ncol, 5.6), layout="constrained")
    axes = fig.subplots(2, ncol, squeeze=False, sharex="col")
    for c, system in enumerate(systems):
        g = df[df["system"].astype(str) == system]
        b = saved.get(system, {}) if "lower" in saved.get(system, {}) else bounds[system]
        ax_c, ax_e = axes[0, c], axes[1, c]
        comp = _curves(g, "completion") * 100.0
        err = _curves(g, "mean_error")
        x = comp.index.to_numpy(float)
        ax_c.fill_between(x, comp["lo"], comp["hi"], color="C0", alpha=0.25, lw=0, label="range over configs")
        ax_c.plot(x, comp["mean"], "o-", color="C0", ms=3, label="mean")
        ax_c.axhline(threshold * 100.0, color="0.5", ls=":", lw=1)
        ax_c.set_ylim(-2, 102)
        xe = err.index.to_numpy(float)
        ax_e.fill_between(xe, err["lo"], err["hi"], color="C1", alpha=0.25, lw=0)
        ax_e.plot(xe, err["mean"], "o-", color="C1", ms=3)
        vals = err[["lo", "mean", "hi"]].to_numpy(float)
        vals = vals[np.isfinite(vals)]
        if vals.size and (vals > 0).all() and vals.max() / vals.min() > 100:
            ax_e.set_yscale("log")
        lower, upper = b.get("lower"), b.get("upper")
        for ax in (ax_c, ax_e):
            for v in (lower, upper):
                if v is not None:
                    ax.axvline(v, color="C3", ls="--", lw=1.2)
            ax.grid(alpha=0.3)
        region = f"valid {lower:g} to {upper:g}" if lower is not None else "no valid region at 1"
        own = saved.get(system, {}).get("protocol")
        if isinstance(own, Mapping):  # a system with its own path and controller
            ctrl, path = own.get("controller", {}), own.get("path", {})
            region += (f"\nstar {1e3 * path.get('size', float('nan')):g} mm, "
                       f"step {1e3 * ctrl.get('max_step', float('nan')):g} mm,"
                       f" tol {1e3 * ctrl.get('tol', float('nan')):g} mm, {ctrl.get('steps')} steps")
        ax_c.set_title(f"{system}\n{region}", fontsize=10 if own is None else 8)
        ax_e.set_xlabel(r"$\epsilon_{limit}$")
        if c == 0:
            ax_c.set_ylabel("mean path completion [%]")
            ax_e.set_ylabel("mean tracking error [m]")
            ax_c.legend(loc="lower left", fontsize=8)
    fig.suptitle(_protocol_text(summary), fontsize=8)
    return save_figure(fig, out_dir, name)


def ablation_figures(df: pd.DataFrame, summary: Mapping[str, Any], out_dir: str | Path) -> list[Path]:
    """Paper Fig. 5 and the noise figure of the estimation ablation.

    ``ablation``: mean path completion [%] vs self-ID iterations (log axis), one
    curve per method, noise-free rows of the first ``m_a``; band = +-1 sd of the
    per-configuration means. ``ablation_noise``: mean completion at each
    iteration count per pose-noise level, one panel per method. ``ablation_m_a``
    (only with several ``m_a``): the same per self-ID magnitude, noise-free.
    Expected columns: ``method, iterations, config_id, pose_noise, m_a, completion``.

    Returns:
      the PNG and PDF paths of every figure written.
    """
    _require(df, ("method", "iterations", "config_id", "pose_noise", "m_a", "completion"))
    methods = [str(m) for m in df["method"].drop_duplicates()]
    m_a0 = sorted(df["m_a"].unique())[0]
    clean = df[(df["pose_noise"] == df["pose_noise"].min()) & (df["m_a"] == m_a0)]
    written: list[Path] = []

    fig = Figure(figsize=(8.4, 4.2), layout="constrained")
    ax = fig.subplots()
    for i, method in enumerate(methods):
        g = clean[clean["method"] == method]
        per_cfg = g.groupby(["iterations", "config_id"])["completion"].mean().unstack() * 100.0
        mean, sd = per_cfg.mean(axis=1), per_cfg.std(axis=1).fillna(0.0)
        x = mean.index.to_numpy(float)
        color, style = f"C{i % 10}", ("-", "--", ":")[(i // 10) % 3]
        ax.fill_between(x, (mean - sd).clip(0, 100), (mean + sd).clip(0, 100), color=color, alpha=0.12, lw=0)
        ax.plot(x, mean, marker="o", ls=style, color=color, ms=3, label=method)
    ax.set_xscale("log")
    ax.set_xlabel("self-ID iterations")
    ax.set_ylabel("mean path completion [%]")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    ax.set_title(f"estimation methods, noise-free, m_a={m_a0:g} rad (band: +-1 sd over configurations)", fontsize=8)
    written += save_figure(fig, out_dir, "ablation")

    sub = df[df["m_a"] == m_a0]
    written += _per_method_panels(sub, methods, "pose_noise", lambda v: f"{v * 1e3:g} mm", "pose noise",
                                  out_dir, "ablation_noise")
    if df["m_a"].nunique() > 1:
        sub = df[df["pose_noise"] == df["pose_noise"].min()]
        written += _per_method_panels(sub, methods, "m_a", lambda v: f"{v:g} rad", "m_a", out_dir, "ablation_m_a")
    return written


def _per_method_panels(df, methods, by, label, legend_title, out_dir, name) -> list[Path]:
    """One panel per method: mean completion [%] vs iterations, one curve per value of column ``by``."""
    values = sorted(df[by].unique())
    ncol = min(len(methods), 4)
    nrow = -(-len(methods) // ncol)
    fig = Figure(figsize=(3.2 * ncol, 2.8 * nrow), layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False, sharex=True, sharey=True)).ravel()
    for ax, method in zip(axes, methods):
        g = df[df["method"] == method]
        for j, v in enumerate(values):
            curve = g[g[by] == v].groupby("iterations")["completion"].mean() * 100.0
            ax.plot(curve.index, curve.to_numpy(), "o-", ms=2, color=f"C{j % 10}", label=label(v))
        ax.set_title(method, fontsize=9)
        ax.set_xscale("log")
        ax.grid(alpha=0.3)
    for ax in axes[len(methods):]:
        ax.set_visible(False)
    axes[0].legend(title=legend_title, fontsize=7, title_fontsize=7)
    fig.supxlabel("self-ID iterations")
    fig.supylabel("mean path completion [%]")
    return save_figure(fig, out_dir, name)
