"""A sweep's figures do not depend on how its float32 programs were compiled (issue 44, item 4).

A GPU runs the same float32 programs as the CPU, compiled by another backend that
sums in another order. Without a GPU in CI, the CPU's own two code generators
stand in for two backends: the sweeps run once with the XLA CPU flags
``selfid_jax`` sets (no fusion emitters, no YNNPACK) and once without them
(``SELFID_JAX_NO_XLA_FLAGS=1`` and those flags taken out of the ``XLA_FLAGS``
the child inherits: XLA's fused emitters, other reduction orders), and
``scripts/compare_runs.py`` must find every discrete figure equal and at most
1 % of the rows differing beyond 1e-3 relative. The comparison itself is
checked on made-up run directories first."""

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

from selfid_jax._xla import defaults_for, jaxlib_version

PACKAGE_FLAGS = set(defaults_for(jaxlib_version()))  # the flags selfid_jax sets on this jaxlib
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


# What ``selfid-jax sweep`` runs, without drawing the figures (compare_runs reads results.parquet and summary.json
# only): the console script's collector thresholds, validate the config with the overrides, run the experiment into
# the run directory; print the XLA flags the process ran under.
_RUN = ("import os, sys; from selfid_jax._gc import collect_less_often; collect_less_often(); "
        "from selfid_jax.runner import execute, registry; "
        "cfg = registry.load(sys.argv[1], sys.argv[3:]); execute.run(registry.get(cfg.experiment), cfg, sys.argv[2]); "
        "print(os.environ.get('XLA_FLAGS', ''))")


def _env(ours: bool) -> dict[str, str]:
    """The environment of one sweep. This process has imported ``selfid_jax``, so its ``XLA_FLAGS`` already holds
    the package's flags and a child would inherit them whatever ``SELFID_JAX_NO_XLA_FLAGS`` says: the XLA run
    takes them out (any other flag, such as the tests' optimisation level, stays)."""
    if ours:
        return {**os.environ, "SELFID_JAX_NO_XLA_FLAGS": "0"}
    kept = [f for f in os.environ.get("XLA_FLAGS", "").split() if f.split("=", 1)[0] not in PACKAGE_FLAGS]
    return {**os.environ, "SELFID_JAX_NO_XLA_FLAGS": "1", "XLA_FLAGS": " ".join(kept)}


def _sweep(config, out, ours, *overrides):
    path = next((ROOT / "configs").glob(f"*/{config}.yaml"))
    proc = subprocess.run([sys.executable, "-c", _RUN, str(path), str(out), *overrides], cwd=ROOT, env=_env(ours),
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ran_with = {f.split("=", 1)[0] for f in proc.stdout.split()}
    assert ran_with >= PACKAGE_FLAGS if ours else not ran_with & PACKAGE_FLAGS, proc.stdout


# The E-KM ablation at one config and trial, two checkpoints, and one row of each code path: the model-free methods,
# E-KM fixed and online (the two programs), the nominal model alone (the fixed program with a silent GP). The
# config's other three rows rerun these programs with other nominal models.
EKM_METHODS = ("methods=["
               '{name: "true", method: "true"}, {name: ours, method: ours}, '
               "{name: ours (Eq. 13 only), method: ours, options: {refine: false}}, {name: direct, method: direct}, "
               "{name: E-KM fixed (easy), method: ekm, options: {mode: fixed}, "
               "nominal: {scale: [1.2, 0.8], offset: [0.1, -0.1]}}, "
               "{name: E-KM online (hard), method: ekm, options: {mode: online}, "
               "nominal: {scale: [1.5, 0.6], offset: [0.6, -0.6]}}, "
               "{name: nominal only (hard), method: ekm, options: {signal: 1.0e-6}, "
               "nominal: {scale: [1.5, 0.6], offset: [0.6, -0.6]}}]")


@pytest.mark.slow
@pytest.mark.parametrize("config, overrides", [
    ("valid_region_two_link", ("n_configs=4",)),
    ("ablation_ekm_two_link", ("n_configs=1", "n_trials=1", "iterations=[2, 10]", EKM_METHODS)),
])
def test_sweep_figures_agree_across_code_generators(tmp_path, config, overrides):
    _sweep(config, tmp_path / "ours", True, *overrides)
    _sweep(config, tmp_path / "xla", False, *overrides)
    res = compare_runs.compare(tmp_path / "ours", tmp_path / "xla")
    assert res["ok"], compare_runs.report(res)
