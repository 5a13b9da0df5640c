"""A synthetic sweep for the runner's tests: a noisy recursion per row, its inputs, and a user-registered experiment.

Shared by tests/test_sweep.py, tests/test_rundir.py and the subprocesses they start (which put :data:`TESTS` on
``sys.path`` and import this module). Importing it registers the experiment ``synthetic_cli_test``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pydantic
from selfid_jax.experiments.common.figures import save_figure

from selfid_jax import runner as experiment
from selfid_jax.runner.config import BaseConfig
from selfid_jax.runner.sweep import grid_table, row_keys

TESTS = Path(__file__).resolve().parent  # on a subprocess's sys.path, to import this module


def synthetic_fn(p):
    """Per row: a noisy 3-state nonlinear recursion, 6 steps (lax.scan), from the row's key."""

    def row(a, key):
        k = jax.random.wrap_key_data(key)
        m = jax.random.normal(k, (3, 3))
        def step(x, t):
            x = jnp.tanh(a * (m @ x) + jnp.sin(t))
            return x, x[0]
        x_final, traj = jax.lax.scan(step, jnp.ones(3), jnp.arange(6.0))
        return {"final": jnp.sum(x_final), "traj": traj, "negative": x_final[0] < 0}

    return jax.vmap(row)(p["a"], p["key"])


def make_inputs(seed: int = 0):
    """23 rows: 2 systems x 3 gains x 4 trials, minus one row (so the last chunk is short)."""
    meta = grid_table({"system": ["s1", "s2"], "a": [0.3, 0.8, 1.4], "trial": range(4)}).iloc[:23]
    params = {"a": meta["a"].to_numpy(), "key": row_keys(seed, len(meta))}
    return meta, params


def reference(params) -> dict[str, np.ndarray]:
    """:func:`synthetic_fn` of every row at once, one jit (what a chunked sweep must reproduce)."""
    return {k: np.asarray(v) for k, v in jax.jit(synthetic_fn)(params).items()}


def subprocess_env(**extra) -> dict[str, str]:
    """This process's environment for a sweep subprocess, updated with ``extra``: the same x64 setting, and without
    this process's XLA_FLAGS (the tests' quick-compile level), so only XLA flags in ``extra`` apply."""
    env = dict(os.environ)
    env["JAX_ENABLE_X64"] = "1" if jax.config.jax_enable_x64 else "0"
    env.pop("XLA_FLAGS", None)
    env.update(extra)
    return env


# --------------------------------------------------------------------------- a user's experiment


class SyntheticConfig(BaseConfig):
    experiment: str = "synthetic_cli_test"
    gains: list[float] = pydantic.Field(min_length=1)
    n_trials: int = pydantic.Field(ge=1)


RUNS: list[dict] = []  # the sweep record of each run's tabulate, latest last (what was computed, skipped)


class SyntheticParams(NamedTuple):
    a: jax.Array  # () gain
    key: jax.Array  # (2,) key data


def synthetic_build(cfg):
    meta = grid_table({"a": cfg.gains, "trial": range(cfg.n_trials)})
    return experiment.Part("synthetic", None, SyntheticParams(meta["a"].to_numpy(), row_keys(cfg.seed, len(meta))),
                           meta)


def synthetic_compute(static, p):
    return jax.tree.map(lambda x: x[0], synthetic_fn({"a": p.a[None], "key": p.key[None]}))


def synthetic_tabulate(wide, part, cfg):
    RUNS.append(wide.attrs["sweep"])
    return wide


def synthetic_summarize(df, cfg):
    return {"mean_final": df.groupby("a")["final"].mean().to_dict(), "nan": float("nan")}


def synthetic_plotter(df, summary, fig_dir):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(3, 2))
    ax = fig.subplots()
    ax.plot(df["a"], df["final"], "o")
    ax.set_title(f"{len(summary['mean_final'])} gains")
    return save_figure(fig, fig_dir, "synthetic")


# A user's experiment, registered at run time (a package would use the selfid_jax.experiments entry point).
SYNTHETIC = experiment.register(experiment.Experiment(
    name="synthetic_cli_test", config=SyntheticConfig, build=synthetic_build, compute=synthetic_compute,
    summarize=synthetic_summarize, tabulate=synthetic_tabulate, plot=synthetic_plotter,
    report=lambda summary: f"{len(summary['mean_final'])} gains", description="a user-registered test experiment",
))
