"""Every shipped experiment documents its results columns (meaning and unit); docs/results_columns.md is current;
a run warns ``UndocumentedColumns`` for a column its experiment does not list."""

from __future__ import annotations

import importlib.util
import warnings
from pathlib import Path
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from selfid_jax import runner
from selfid_jax.runner.config import BaseConfig
from selfid_jax.runner.contract import UndocumentedColumns

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("results_columns", ROOT / "scripts" / "results_columns.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_shipped_experiment_documents_its_columns_with_units():
    script = _script()
    names = [name for name, _ in script.shipped()]
    assert {"demo", "valid_region", "ablation", "tracking", "workspace", "valid_region_workspace", "peg_in_hole",
            "design", "articulated"} <= set(names)
    for name in names:
        exp = runner.get(name)
        assert exp.columns, f"experiment {name!r} declares no columns"
        for column, text in exp.columns.items():
            meaning, unit = script.split_unit(column, text)  # one line ending in [unit]
            assert meaning and unit.strip(), (name, column)


def test_docs_results_columns_is_current():
    script = _script()
    assert (ROOT / "docs" / "results_columns.md").read_text(encoding="utf-8") == script.render(), (
        "docs/results_columns.md is out of date: run python scripts/results_columns.py")


def test_split_unit_refuses_an_entry_without_a_unit():
    script = _script()
    assert script.split_unit("x", "tool position x [m]") == ("tool position x", "m")
    for bad in ("tool position x", "tool position [m] x", "two\nlines [m]"):
        with pytest.raises(ValueError, match="unit in brackets"):
            script.split_unit("x", bad)


class _Config(BaseConfig):
    experiment: str = "cols_probe"
    chunk_size: int = 4


class _Out(NamedTuple):
    doubled: jnp.ndarray
    squared: jnp.ndarray


def _experiment(columns):
    def build(cfg):
        x = np.arange(3.0)
        return runner.Part("p", None, {"x": x}, pd.DataFrame({"i": np.arange(3)}))

    return runner.Experiment(name="cols_probe", config=_Config, build=build,
                             compute=lambda static, p: _Out(2 * p["x"], p["x"] ** 2),
                             summarize=lambda table, cfg: {}, columns=columns)


def test_a_column_missing_from_columns_warns_with_its_name(tmp_path):
    exp = _experiment({"i": "row label [id]", "doubled": "2 x [m]"})
    with pytest.warns(UndocumentedColumns, match=r"'cols_probe'.*\['squared'\]"):
        runner.run(exp, _Config(), tmp_path / "a")
    documented = _experiment({"i": "row label [id]", "doubled": "2 x [m]", "squared": "x^2 [m^2]"})
    undeclared = _experiment(None)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UndocumentedColumns)
        table, _ = runner.run(documented, _Config(), tmp_path / "b")
        runner.run(undeclared, _Config(), tmp_path / "c")
    assert list(table.columns) == ["i", "doubled", "squared"]
