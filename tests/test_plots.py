"""Valid-region bounds and figures from a hand-made results table."""

from __future__ import annotations

import itertools

import numpy as np
import pandas as pd
import pytest
from selfid_jax.experiments.common.figures import valid_region_figure
from selfid_jax.experiments.common.region import VALID_REGION_COLUMNS, valid_region_bounds, valid_region_summary

EPS = np.round(np.arange(0.0, 2.75, 0.25), 2)  # 0.0 .. 2.5, contains 1.0


def _table(curves: dict[str, dict[float, float]], n_configs: int = 3, n_trials: int = 2) -> pd.DataFrame:
    """Rollouts whose mean completion per (system, eps) is exactly the given value."""
    rows = []
    for system, curve in curves.items():
        for eps, cfg, trial in itertools.product(curve, range(n_configs), range(n_trials)):
            c = curve[eps]
            # +-delta per trial keeps the mean exact and gives the band a width
            delta = min(c, 1 - c, 0.02) * (1 if trial % 2 else -1)
            rows.append(
                dict(system=system, eps_limit=eps, config_id=cfg, trial=trial, completion=c + delta,
                     mean_error=1e-3 / max(c, 0.05), max_error=3e-3 / max(c, 0.05),
                     waypoint_error=5e-4, steps_used=100, failed=c < 0.1)
            )
    return pd.DataFrame(rows, columns=list(VALID_REGION_COLUMNS))


def _curve(passing: set[float]) -> dict[float, float]:
    return {float(e): (1.0 if float(e) in passing else 0.5) for e in EPS}


def test_bounds_contiguous_region_around_one():
    df = _table({"arm": _curve({0.5, 0.75, 1.0, 1.25, 1.5})})
    assert valid_region_bounds(df, 0.95) == {"arm": {"lower": 0.5, "upper": 1.5, "contains_one": True}}


def test_bounds_ignore_disconnected_passing_points():
    # 2.25 passes again but is separated from the region by failing points
    df = _table({"arm": _curve({0.25, 0.5, 0.75, 1.0, 1.25, 2.25}), "hand": _curve({0.0, 1.0, 2.5})})
    b = valid_region_bounds(df, 0.95)
    assert b["arm"] == {"lower": 0.25, "upper": 1.25, "contains_one": True}
    assert b["hand"] == {"lower": 1.0, "upper": 1.0, "contains_one": True}


def test_bounds_null_when_point_nearest_one_fails():
    df = _table({"arm": _curve({0.25, 0.5, 1.5, 1.75})})
    assert valid_region_bounds(df, 0.95) == {"arm": {"lower": None, "upper": None, "contains_one": False}}


def test_bounds_grid_without_one_and_threshold_edge():
    curve = {0.0: 0.2, 0.4: 0.96, 0.8: 0.97, 1.3: 0.5, 1.6: 0.99}  # nearest to 1 is 0.8
    df = _table({"arm": curve})
    assert valid_region_bounds(df, 0.95) == {"arm": {"lower": 0.4, "upper": 0.8, "contains_one": False}}
    assert valid_region_bounds(df, 0.965)["arm"] == {"lower": 0.8, "upper": 0.8, "contains_one": False}
    assert valid_region_bounds(df, 0.98)["arm"]["lower"] is None


@pytest.mark.slow
def test_summary_and_figure_files(tmp_path):
    df = _table({"two_link": _curve({0.5, 0.75, 1.0, 1.25, 1.5}), "ur5e": _curve({0.75, 1.0, 1.25})})
    df.loc[df["eps_limit"] == 2.5, "mean_error"] = np.inf  # diverged rollouts must not break the plot
    summary = valid_region_summary(df, 0.95, controller={"max_step": 0.01, "tol": 0.001})
    assert summary["systems"]["ur5e"]["lower"] == 0.75 and summary["systems"]["ur5e"]["upper"] == 1.25
    assert summary["systems"]["two_link"]["n_rollouts"] == len(EPS) * 6
    assert summary["systems"]["two_link"]["mean_completion"][4] == pytest.approx(1.0)
    paths = valid_region_figure(df, summary, tmp_path / "figures")
    assert [p.name for p in paths] == ["valid_region.png", "valid_region.pdf"]
    png, pdf = (p.read_bytes() for p in paths)
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and len(png) > 10_000
    assert pdf.startswith(b"%PDF") and b"%%EOF" in pdf[-64:]
    # without a summary the bounds come from the table itself
    assert valid_region_figure(df, {}, tmp_path / "bare")[0].stat().st_size > 10_000
