"""The articulated-object experiment as a sweep: one compiled program per object kind, whatever the number
of objects and chunks, and each row's result independent of the rows it is batched with (the native
backend's one host callback per batch applies every row's own object)."""

import collections

import numpy as np
import pytest

from selfid_jax import runner as experiment

from selfid_jax.runner import sweep


def _cfg(chunk_size):
    from selfid_jax.experiments.articulated import ArticulatedConfig

    return ArticulatedConfig(objects={"prismatic": 3, "revolute": 1}, controllers=["tacman"], arms=["true"],
                             max_time=0.4, trace_points=4, selfid_iters=4, chunk_size=chunk_size, seed=3)


@pytest.mark.slow
def test_population_compiles_once_per_kind_and_rows_do_not_depend_on_their_batch(tmp_path, monkeypatch):
    exp = experiment.get("articulated")
    monkeypatch.setattr(sweep, "_EXECUTABLES", collections.OrderedDict())
    df, _ = experiment.run(exp, _cfg(chunk_size=2), tmp_path / "a", fresh=True)
    # 3 drawers in 2 chunks (the second padded) and 1 door: two programs, one per kind
    assert len(sweep._EXECUTABLES) == 2
    assert sorted(df["kind"].value_counts().items()) == [("prismatic", 3), ("revolute", 1)]
    drawers = df[df.kind == "prismatic"].sort_values("object")
    progress = drawers["progress"].to_numpy(float)
    assert np.all(np.isfinite(progress)) and np.all(progress > 0)
    assert len(np.unique(np.round(progress, 12))) == 3  # three different drawers, three different motions

    one, _ = experiment.run(exp, _cfg(chunk_size=1), tmp_path / "b", fresh=True)  # each row alone
    alone = one[one.kind == "prismatic"].sort_values("object")
    for col in ("progress", "dev_mean_mm", "dev_max_mm"):
        np.testing.assert_allclose(alone[col].to_numpy(float), drawers[col].to_numpy(float), rtol=1e-9, atol=1e-12)
