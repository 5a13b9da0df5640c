"""The articulated-object experiment as a sweep: one compiled program per object kind, whatever the number
of objects and chunks, and each row's result independent of the rows it is batched with (the native
backend's one host callback per batch applies every row's own object)."""

import collections

import numpy as np
import pytest

from selfid_jax import runner as experiment
from selfid_jax.runner import sweep


def _cfg(chunk_size, revolute=1):
    from selfid_jax.experiments.articulated import ArticulatedConfig

    return ArticulatedConfig(objects={"prismatic": 3, "revolute": revolute}, controllers=["tacman"], arms=["true"],
                             max_time=0.4, trace_points=4, selfid_iters=4, chunk_size=chunk_size, seed=3)


@pytest.mark.slow
def test_population_compiles_once_per_kind_and_rows_do_not_depend_on_their_batch(tmp_path, monkeypatch):
    exp = experiment.get("articulated")
    monkeypatch.setattr(sweep, "_EXECUTABLES", collections.OrderedDict())
    df, _ = experiment.run(exp, _cfg(chunk_size=1), tmp_path / "a", fresh=True)
    # 3 drawers in 3 chunks and 1 door: two programs, one per kind
    assert len(sweep._EXECUTABLES) == 2
    assert sorted(df["kind"].value_counts().items()) == [("prismatic", 3), ("revolute", 1)]
    alone = df[df.kind == "prismatic"].sort_values("object")
    progress = alone["progress"].to_numpy(float)
    assert np.all(np.isfinite(progress)) and np.all(progress > 0)
    assert len(np.unique(np.round(progress, 12))) == 3  # three different drawers, three different motions

    # the drawers two to a chunk, the second padded (a kind's population does not depend on the other kinds, so
    # the door is left out): one more program, and each drawer's row as when it ran alone
    two, _ = experiment.run(exp, _cfg(chunk_size=2, revolute=0), tmp_path / "b", fresh=True)
    assert len(sweep._EXECUTABLES) == 3
    drawers = two[two.kind == "prismatic"].sort_values("object")
    for col in ("progress", "dev_mean_mm", "dev_max_mm"):
        np.testing.assert_allclose(drawers[col].to_numpy(float), alone[col].to_numpy(float), rtol=1e-9, atol=1e-12)
