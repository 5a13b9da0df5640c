"""Figures drawn from saved results only (a results DataFrame and a summary dict).

Nothing here simulates: ``selfid-jax plot RUN_DIR`` loads ``results.parquet``
and ``summary.json`` and calls these functions. Figures are written as PNG and
PDF through matplotlib's ``Figure`` API (Agg/PDF canvases, no pyplot state, no
display needed).

The valid region's statistics (bounds, curves) are in
:mod:`selfid_jax.experiments.common.region`; the figures each experiment
alone draws are in ``selfid_jax.experiments.figures.<experiment>``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from selfid_jax.runner.figures import save_figure

from .region import (
    curves,
    finite,
    require,
    valid_region_bounds,
    valid_region_summary,  # noqa: F401 - callers that draw and summarise
)

__all__ = [
    "ablation_error_curves",
    "ablation_figures",
    "method_styles",
    "save_figure",
    "valid_region_figure",
]


def _fmt_controller(ctrl: Mapping[str, Any]) -> str:
    return ", ".join(f"{k}={v}" for k, v in ctrl.items())


def _protocol_text(summary: Mapping[str, Any], systems: list[str] | None = None) -> str:
    """The suptitle: the threshold and the controller the plotted systems ran.

    The top-level ``summary["controller"]`` is named only when at least one of
    ``systems`` ran it (has no ``protocol`` of its own); systems with their own
    path and controller state them in their panel titles instead.
    """
    ctrl = summary.get("controller")
    saved = summary.get("systems")
    saved = saved if isinstance(saved, Mapping) else {}
    own = [s for s in (systems or []) if isinstance(saved.get(s, {}).get("protocol"), Mapping)]
    parts = [f"valid: mean completion >= {summary.get('completion_threshold', 0.95):g}"]
    if systems and len(own) == len(systems):
        parts.append("each system's own path and controller (in its title)")
    elif isinstance(ctrl, Mapping):
        shared = [s for s in (systems or []) if s not in own]
        who = f" ({', '.join(shared)})" if own else ""
        parts.append(f"controller{who}: {_fmt_controller(ctrl)}")
    return "; ".join(parts)


def valid_region_figure(
    df: pd.DataFrame, summary: Mapping[str, Any], out_dir: str | Path, *, name: str = "valid_region"
) -> list[Path]:
    """Paper Fig. 2: path completion and tracking error vs ``eps_limit``, one column per system.

    Top row: mean path completion [%] over all rollouts, band = min..max of
    the per-configuration means, dotted line at the threshold. Bottom row:
    mean tracking error [mm] (log axis when it spans > 2 decades), same band.
    Dashed vertical lines mark the valid-region bounds, taken from
    ``summary["systems"][system]`` when present, else computed with
    :func:`valid_region_bounds` at ``summary["completion_threshold"]`` (0.95).

    Returns:
      ``[out_dir/<name>.png, out_dir/<name>.pdf]``.
    """
    require(df, ("system", "eps_limit", "completion", "mean_error"))
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
        comp = curves(g, "completion") * 100.0
        err = curves(g, "mean_error") * 1e3
        x = comp.index.to_numpy(float)
        ax_c.fill_between(x, comp["lo"], comp["hi"], color="C0", alpha=0.25, lw=0, label="range over configs")
        ax_c.plot(x, comp["mean"], "o-", color="C0", ms=3, label="mean")
        ax_c.axhline(threshold * 100.0, color="0.5", ls=":", lw=1, label=f"threshold {threshold * 100:g} %")
        ax_c.set_ylim(-2, 102)
        xe = err.index.to_numpy(float)
        ax_e.fill_between(xe, err["lo"], err["hi"], color="C1", alpha=0.25, lw=0)
        ax_e.plot(xe, err["mean"], "o-", color="C1", ms=3, gid=f"mean_error:{system}")
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
            ax_e.set_ylabel("mean tracking error [mm]")
            ax_c.legend(loc="lower left", fontsize=8)
    fig.suptitle(_protocol_text(summary, systems), fontsize=8)
    return save_figure(fig, out_dir, name)


_MARKERS = ("o", "s", "^", "D", "v", "P", "X")
_LINESTYLES = ("-", "--", "-.", ":")


def _iteration_ticks(ax, iterations) -> None:
    """Log x axis with one plain tick per checkpoint (``1, 2, 5, 10``), not ``2 x 10^0``."""
    from matplotlib.ticker import NullLocator

    its = np.sort(np.unique(np.asarray(iterations, float)))
    ax.set_xscale("log")
    ax.set_xticks(its, [f"{v:g}" for v in its])
    ax.xaxis.set_minor_locator(NullLocator())


def method_styles(methods: list[str]) -> dict[str, tuple[str, str, str]]:
    """A distinct ``(colour, linestyle, marker)`` per method, in the order given.

    Colour ``C{i % 10}``, marker ``i % 7`` of ``o s ^ D v P X`` and linestyle
    ``(i // 10) % 4`` of ``- -- -. :``: the (colour, marker) pair alone is
    unique for up to 70 methods (10 and 7 are coprime), the triple for up to
    280, so no two curves of a legend look alike.

    Raises:
      ValueError: more than 280 methods, or a name given twice.
    """
    if len(set(methods)) != len(methods):
        raise ValueError(f"method names must be unique to get one style each, got {methods}")
    if len(methods) > 280:
        raise ValueError(f"{len(methods)} methods: at most 280 distinct (colour, linestyle, marker) styles")
    return {m: (f"C{i % 10}", _LINESTYLES[(i // 10) % 4], _MARKERS[i % len(_MARKERS)]) for i, m in enumerate(methods)}


def ablation_error_curves(df: pd.DataFrame) -> pd.DataFrame:
    """Mean distance to the path [mm] per (method, iterations), the rollouts that did not fail.

    The mean of ``1e3 * mean_error`` over the rows of ``df`` whose
    ``failed`` is False (all rows without a ``failed`` column) and whose error
    is finite; a (method, iterations) cell with no such row is NaN.

    Returns:
      a DataFrame indexed by ``iterations`` (sorted) with one column per method
      (in order of first appearance) [mm].
    """
    require(df, ("method", "iterations", "mean_error"))
    ok = df if "failed" not in df.columns else df[~df["failed"].astype(bool)]
    err = ok.assign(_mm=1e3 * finite(ok["mean_error"]))
    table = err.groupby(["iterations", "method"])["_mm"].mean().unstack("method")
    methods = [str(m) for m in df["method"].drop_duplicates()]
    its = np.sort(df["iterations"].unique())
    return table.reindex(index=its, columns=methods)


def ablation_figures(df: pd.DataFrame, summary: Mapping[str, Any], out_dir: str | Path) -> list[Path]:
    """Paper Fig. 5 and the noise figure of the estimation ablation.

    ``ablation``: left, mean path completion [%] vs self-ID iterations (log
    axis), one curve per method, noise-free rows of the first ``m_a``; band =
    +-1 sd of the per-configuration means. Right, the mean distance to the path
    [mm] of the same rows that did not fail (:func:`ablation_error_curves`;
    log axis when it spans more than 2 decades). Each method has its own
    (colour, linestyle, marker) (:func:`method_styles`). ``ablation_noise``:
    mean completion at each iteration count per pose-noise level, one panel per
    method. ``ablation_m_a`` (only with several ``m_a``): the same per self-ID
    magnitude, noise-free. Expected columns: ``method, iterations, config_id,
    pose_noise, m_a, completion`` (and ``mean_error``, ``failed`` for the
    error panel, which is left out without ``mean_error``).

    Returns:
      the PNG and PDF paths of every figure written.
    """
    require(df, ("method", "iterations", "config_id", "pose_noise", "m_a", "completion"))
    methods = [str(m) for m in df["method"].drop_duplicates()]
    styles = method_styles(methods)
    m_a0 = sorted(df["m_a"].unique())[0]
    clean = df[(df["pose_noise"] == df["pose_noise"].min()) & (df["m_a"] == m_a0)]
    written: list[Path] = []

    with_error = "mean_error" in df.columns
    fig = Figure(figsize=(12.0 if with_error else 8.4, 4.4), layout="constrained")
    axes = fig.subplots(1, 2 if with_error else 1, squeeze=False)[0]
    ax = axes[0]
    for method in methods:
        g = clean[clean["method"] == method]
        per_cfg = g.groupby(["iterations", "config_id"])["completion"].mean().unstack() * 100.0
        mean, sd = per_cfg.mean(axis=1), per_cfg.std(axis=1).fillna(0.0)
        x = mean.index.to_numpy(float)
        color, style, marker = styles[method]
        ax.fill_between(x, (mean - sd).clip(0, 100), (mean + sd).clip(0, 100), color=color, alpha=0.10, lw=0)
        ax.plot(x, mean, marker=marker, ls=style, color=color, ms=4, label=method, gid=f"completion:{method}")
    _iteration_ticks(ax, clean["iterations"])
    ax.set_xlabel("self-ID iterations")
    ax.set_ylabel("mean path completion [%]")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.set_title("path completion (band: +-1 sd over configurations)", fontsize=9)
    if with_error:
        ax_e = axes[1]
        err = ablation_error_curves(clean)
        for method in methods:
            color, style, marker = styles[method]
            ax_e.plot(err.index.to_numpy(float), err[method].to_numpy(float), marker=marker, ls=style,
                      color=color, ms=4, gid=f"path_error:{method}")
        vals = err.to_numpy(float)
        vals = vals[np.isfinite(vals)]
        if vals.size and (vals > 0).all() and vals.max() / vals.min() > 100:
            ax_e.set_yscale("log")
        _iteration_ticks(ax_e, clean["iterations"])
        ax_e.set_xlabel("self-ID iterations")
        ax_e.set_ylabel("mean distance to the path [mm]")
        ax_e.grid(alpha=0.3)
        ax_e.set_title("path error (rollouts that did not fail)", fontsize=9)
    fig.legend(*ax.get_legend_handles_labels(), fontsize=7, loc="outside right center")
    fig.suptitle(f"estimation methods, noise-free, m_a={m_a0:g}", fontsize=9)
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
        _iteration_ticks(ax, df["iterations"])
        ax.grid(alpha=0.3)
    for k, ax in enumerate(axes[len(methods):], start=len(methods)):
        ax.set_visible(False)
        axes[k - ncol].xaxis.set_tick_params(labelbottom=True)  # the panel above is its column's lowest
    axes[0].legend(title=legend_title, fontsize=7, title_fontsize=7)
    fig.supxlabel("self-ID iterations")
    fig.supylabel("mean path completion [%]")
    return save_figure(fig, out_dir, name)
