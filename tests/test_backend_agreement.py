"""A sweep's figures do not depend on how its float32 programs were compiled (issue 44, item 4).

A GPU runs the same float32 programs as the CPU, compiled by another backend that
sums in another order. Without a GPU in CI, the CPU's own two code generators
stand in for two backends: the sweeps run once with the XLA CPU flags
``selfid_jax`` sets (no fusion emitters, no YNNPACK) and once without them
(``SELFID_JAX_NO_XLA_FLAGS=1``: XLA's fused emitters, other reduction orders),
and ``scripts/compare_runs.py`` must find every discrete figure equal and at
most 1 % of the rows differing beyond 1e-3 relative. The comparison itself is
checked on made-up run directories first.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("compare_runs", ROOT / "scripts" / "compare_runs.py")
compare_runs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(compare_runs)


def _run_dir(path: Path, table: pd.DataFrame, summary: dict) -> Path:
    path.mkdir()
    table.to_parquet(path / "results.parquet")
    (path / "summary.json").write_text(json.dumps(summary))
    return path


def _table(err, failed, steps):
    return pd.DataFrame({"config_id": np.arange(len(err)), "mean_error": np.asarray(err, np.float32),
                         "failed": np.asarray(failed), "steps_used": np.asarray(steps, np.int32),
                         "vec": [np.array([e, 2 * e]) for e in err]})


def test_compare_runs_on_made_up_runs(tmp_path):
    n = 200
    err = np.linspace(1e-3, 1e-1, n)
    summary = {"lower": 0.2, "upper": 2.0, "contains_one": True, "mean": [0.5, 0.25]}
    a = _run_dir(tmp_path / "a", _table(err, np.zeros(n, bool), np.full(n, 435)), summary)
    # round-off: every float 1e-6 relative off, one step count off by one (0.5 % of rows): agree
    b = _run_dir(tmp_path / "b", _table(err * (1 + 1e-6), np.zeros(n, bool), np.r_[434, np.full(n - 1, 435)]),
                 {**summary, "mean": [0.5 * (1 + 1e-7), 0.25]})
    res = compare_runs.compare(a, b)
    assert res["ok"], compare_runs.report(res)
    assert res["table"]["rows_differ"] == 1
    assert res["table"]["columns"]["mean_error"]["differ"] == 0
    assert res["summary"]["float_max_rel"] == pytest.approx(1e-7, rel=1e-3)
    # a valid-region bound that moved, a row that failed on one side only, 5 % of the errors off: each is found
    c = _run_dir(tmp_path / "c", _table(np.r_[err[:10] * 1.1, err[10:]], np.r_[True, np.zeros(n - 1, bool)],
                                        np.full(n, 435)), {**summary, "upper": 1.95})
    res = compare_runs.compare(a, c)
    assert not res["ok"]
    assert res["summary"]["discrete"] == []  # a float bound is a float: reported, not discrete
    assert res["summary"]["float_worst"] == "upper"
    assert res["table"]["discrete"] == ["failed"]
    assert res["table"]["columns"]["mean_error"]["differ"] == 10
    assert res["table"]["columns"]["vec"]["differ"] == 10
    assert compare_runs.main([str(a), str(c)]) == 1
    assert compare_runs.main([str(a), str(tmp_path / "nowhere")]) == 2


def _sweep(config, out, extra_env, *overrides):
    env = {**os.environ, **extra_env}
    cmd = [sys.executable, "-m", "selfid_jax.cli", "sweep", config, "--out", str(out), "--no-progress"]
    for o in overrides:
        cmd += ["--set", o]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]


@pytest.mark.slow
@pytest.mark.parametrize("config, overrides", [
    ("valid_region_two_link", ("n_configs=4",)),
    ("ablation_ekm_two_link", ("n_configs=1",)),
])
def test_sweep_figures_agree_across_code_generators(tmp_path, config, overrides):
    _sweep(config, tmp_path / "ours", {"SELFID_JAX_NO_XLA_FLAGS": "0"}, *overrides)
    _sweep(config, tmp_path / "xla", {"SELFID_JAX_NO_XLA_FLAGS": "1"}, *overrides)
    res = compare_runs.compare(tmp_path / "ours", tmp_path / "xla")
    assert res["ok"], compare_runs.report(res)
