"""The workspace experiment: per-configuration rows against numpy, cell binning by hand, configs, run and plot."""

import jax

jax.config.update("jax_enable_x64", True)

import json  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
from selfid_jax.experiments import workspace  # noqa: E402

from selfid_jax import runner as experiment  # noqa: E402
from selfid_jax.runner.errors import ConfigError  # noqa: E402
from selfid_jax.runner.registry import load as load_config  # noqa: E402
from selfid_jax.systems.ets import ARM5_Q_HIGH, ARM5_Q_LOW  # noqa: E402

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "workspace"


def test_shipped_configs_validate():
    small = load_config(CONFIGS / "workspace_arm5.yaml")
    full = load_config(CONFIGS / "workspace_arm5_full.yaml")
    assert small.system == full.system == "arm5"
    assert full.n_configs >= 10**6 and small.n_configs <= 10**5
    assert experiment.get("workspace") is workspace.EXPERIMENT


@pytest.mark.parametrize(
    "override, match",
    [
        ("n_configs=0", "n_configs"),
        ("cell=-0.01", "cell"),
        ("sample=grid", "sample"),
        ("system=three_link", "system"),
    ],
)
def test_bad_config_is_named(override, match):
    with pytest.raises(ConfigError, match=match):
        load_config(CONFIGS / "workspace_arm5.yaml", [override])


def test_system_without_orientation_is_refused(monkeypatch):
    from selfid_jax.systems import from_pose_fn

    tip = from_pose_fn(lambda params, q: jax.numpy.stack([q[0], q[1], 0.0 * q[0]]), 2, task_dim=3, q_low=-1.0,
                       q_high=1.0, dq_max=0.1, m_a=0.01)  # a position-only pose map: no Jw
    monkeypatch.setattr(workspace, "build_system", lambda spec: tip)
    with pytest.raises(ValueError, match="no orientation"):
        workspace.build(workspace.WorkspaceConfig(n_configs=4))


def test_cell_maps_by_hand():
    # four configurations: two share the r-z cell (1, 0), one at r = 0.25 (cell 2), one at r = 0.05 (cell 0)
    table = pd.DataFrame({
        "x": [0.1, 0.0, 0.25, 0.05], "y": [0.05, 0.13, 0.0, 0.0], "z": [0.02, 0.01, 0.05, 0.15],
        "sqrt_manipulability": [1.0, 3.0, 2.0, 5.0], "condition": [10.0, 4.0, 7.0, np.inf],
    })
    cm = workspace.cell_maps(table, 0.1, "rz")
    assert cm.extent == (0.0, 0.30000000000000004, 0.0, 0.2)
    assert cm.count.tolist() == [[0, 2, 1], [1, 0, 0]]
    assert cm.max_manipulability[0, 1] == 3.0 and cm.mean_manipulability[0, 1] == 2.0
    assert cm.min_condition[0, 1] == 4.0 and np.isinf(cm.min_condition[1, 0])
    assert np.isnan(cm.max_manipulability[1, 1])  # nothing fell there
    xz = workspace.cell_maps(table, 0.1, "xz")  # projected along y: x = 0.0 and 0.05 share a cell
    assert int(xz.count.sum()) == 4 and xz.extent[0] == 0.0
    with pytest.raises(ValueError, match="plane"):
        workspace.cell_maps(table, 0.1, "xy")


@pytest.mark.slow
def test_run_rows_match_numpy_and_figures_redraw_from_saved_results(tmp_path):
    cfg = workspace.WorkspaceConfig(n_configs=3000, x64=True, chunk_size=1000, cell=0.02)
    table, summary = experiment.run(workspace.EXPERIMENT, cfg, tmp_path / "run")
    assert len(table) == 3000
    # rows: redraw q from the row's key, numpy SVD of the arm's geometric Jacobian
    part = workspace.build(cfg)
    system = part.static.system
    for i in (0, 1, 2999):
        key = jax.random.wrap_key_data(part.params.key[i])
        q = np.asarray(jax.random.uniform(key, (5,), dtype=part.static.low.dtype, minval=part.static.low,
                                          maxval=part.static.high))
        assert np.all(q >= ARM5_Q_LOW) and np.all(q <= ARM5_Q_HIGH)
        (p, _), J = system.pose_and_jacobian(q)
        J = np.asarray(J)
        s6, s3 = np.linalg.svd(J, compute_uv=False), np.linalg.svd(J[:3], compute_uv=False)
        Ju = np.vstack([J[:3], 0.1 * J[3:]])
        su = np.linalg.svd(Ju, compute_uv=False)
        row = table.iloc[i]
        np.testing.assert_allclose([row.x, row.y, row.z], p, atol=1e-12)
        np.testing.assert_allclose(row.sqrt_manipulability, np.sqrt(s6.prod()), rtol=1e-9)
        np.testing.assert_allclose(row.yoshikawa, s6.prod(), rtol=1e-9)
        np.testing.assert_allclose(row.condition, s6[0] / s6[-1], rtol=1e-9)
        np.testing.assert_allclose(row.position_condition, s3[0] / s3[-1], rtol=1e-9)
        np.testing.assert_allclose(row.unit_consistent_condition, su[0] / su[-1], rtol=1e-9)
    # closed form: the tool stays within 0.40 m of the shoulder (0, 0, 0.10)
    reach = np.sqrt(table.x**2 + table.y**2 + (table.z - 0.1) ** 2)
    assert reach.max() <= 0.4 + 1e-12 and reach.max() > 0.38
    assert summary["cells_reached"]["rz"] == int((workspace.cell_maps(table, 0.02, "rz").count > 0).sum())
    assert summary["metrics"]["condition"]["min"] > 16.0  # mixed units (see manipulability)
    # plot from the saved files only
    saved = pd.read_parquet(tmp_path / "run" / "results.parquet")
    summary_saved = json.loads((tmp_path / "run" / "summary.json").read_text())
    paths = workspace.plot(saved, summary_saved, tmp_path / "figs")
    assert sorted(p.name for p in paths) == ["workspace.pdf", "workspace.png", "workspace_position.pdf",
                                             "workspace_position.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)
