"""Valid region per start configuration: the spectral-radius prediction against numpy and closed forms; a small run."""

import jax

jax.config.update("jax_enable_x64", True)

import json  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
from selfid_jax.experiments import valid_region_workspace as vrw  # noqa: E402
from selfid_jax.experiments.common.schema import ControllerConfig, EpsLimits, PathConfig  # noqa: E402

from selfid_jax import runner as experiment  # noqa: E402
from selfid_jax.systems.ets import arm5  # noqa: E402


@pytest.mark.slow
def test_spectral_radius_matches_numpy_eigenvalues():
    rng = np.random.default_rng(0)
    mats = [rng.normal(size=(k, k)) * s for k in (2, 3, 3, 6) for s in (0.1, 1.0, 30.0)]
    mats += [np.array([[0.0, 2.0], [-2.0, 0.0]]),  # a complex pair of modulus 2
             np.array([[0.0, 1.0], [0.0, 0.0]]),  # nilpotent: 0
             np.zeros((3, 3)),
             np.array([[0.9, 5.0], [0.0, 0.9]])]  # defective (Jordan block): 0.9
    for A in mats:
        want = np.max(np.abs(np.linalg.eigvals(A)))
        got = float(jax.jit(vrw.spectral_radius)(jnp.asarray(A)))
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-12, err_msg=str(A))


@pytest.mark.slow
def test_uniform_scaling_is_stable_below_two():
    """``m_eps = c`` everywhere: ``I - J (c J^+) = (1 - c) I``, so ``rho = |1 - c|`` (the issue's 'diverges at 2')."""
    s = arm5()
    q = jnp.array([0.2, 0.4, 0.9, 0.6, 0.0])
    J, Jinv = s.jacobian(q), s.true_inverse_jacobian(q)
    cs = jnp.array([0.3, 1.0, 1.9, 2.1])
    rho = jax.jit(jax.vmap(lambda c: vrw.spectral_radius(jnp.eye(3) - J @ (c * Jinv))))(cs)
    np.testing.assert_allclose(rho, np.abs(1.0 - np.asarray(cs)), atol=1e-9)


def _cfg(**kw):
    base = dict(n_configs=4, n_bins=2, candidates=400, eps_limits=EpsLimits(start=0.5, stop=2.5, num=3), n_trials=2,
                prediction_draws=8, path=PathConfig(size=0.05),
                controller=ControllerConfig(max_step=0.005, tol=0.001, steps=120), chunk_size=64)
    base.update(kw)
    return vrw.ValidRegionWorkspaceConfig(**base)


@pytest.mark.slow
def test_starts_span_manipulability_bins():
    s = arm5()
    q, table = vrw.stratified_starts(s, jax.random.key(0), _cfg(n_configs=12, n_bins=4, candidates=2000))
    assert q.shape == (12, 5) and table["manipulability_bin"].value_counts().tolist() == [3, 3, 3, 3]
    np.testing.assert_allclose(table["manipulability"], jax.vmap(s.manipulability)(jnp.asarray(q)), rtol=1e-10)
    means = table.groupby("manipulability_bin")["manipulability"].max().to_numpy()
    lows = table.groupby("manipulability_bin")["manipulability"].min().to_numpy()
    assert np.all(means[:-1] <= lows[1:])  # bins are ordered quantiles
    with pytest.raises(ValueError, match="multiple of n_bins"):
        vrw.stratified_starts(s, jax.random.key(0), _cfg(n_configs=5, n_bins=2))


@pytest.mark.slow
def test_small_run_bounds_prediction_and_figures(tmp_path):
    cfg = _cfg()
    table, summary = experiment.run(vrw.EXPERIMENT, cfg, tmp_path / "run")
    assert len(table) == 4 * 3 * 2
    assert set(summary["configs"]) >= {"lower", "upper", "predicted_upper", "manipulability", "condition"}
    # eps_limit 0.5 and 2.5: uniform(1, eps) entries; at 2.5 most draws have rho > 1 (diverging one-step map)
    hi = table[np.isclose(table.eps_limit, 2.5)]
    assert hi["predicted_stable"].mean() < 0.5
    lo = table[np.isclose(table.eps_limit, 0.5)]
    assert (lo["spectral_radius"] < 1).mean() > 0.75  # non-uniform m_eps can push rho past 1 even below 1
    saved = pd.read_parquet(tmp_path / "run" / "results.parquet")
    paths = vrw.plot(saved, json.loads((tmp_path / "run" / "summary.json").read_text()), tmp_path / "figs")
    assert [p.name for p in paths] == ["valid_region_workspace.png", "valid_region_workspace.pdf"]
