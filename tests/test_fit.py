"""``sj.fit`` and ``selfid-jax fit``: self-ID from recorded logs (sample pairs or raw time series)."""

import json

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import selfid_jax as sj
from selfid_jax.cli import main
from selfid_jax.identify import estimator
from selfid_jax.identify.refine import refine
from selfid_jax.robot import offline as fit_mod
from selfid_jax.robot.log import LogError, read_table, samples_from_table
from selfid_jax.systems.ur5e import UR5E_HOME

TOL = 1e-9
T = 15  # one log length for the pair tables, so their fits share one compiled scan


@pytest.fixture(autouse=True)
def _no_disk_cache(monkeypatch):
    monkeypatch.setenv("SELFID_JAX_CACHE_DIR", "off")


def _linear(n=5, m=3, T=T, seed=0):
    rng = np.random.default_rng(seed)
    Jinv = rng.normal(size=(n, m))
    V = rng.normal(scale=0.01, size=(T, m))
    return Jinv, V, V @ Jinv.T


def _pairs_table(dtheta, V, t=None):
    table = {**{f"dtheta_{i}": dtheta[:, i] for i in range(dtheta.shape[1])},
             **{f"V_{j}": V[:, j] for j in range(V.shape[1])}}
    return table if t is None else {"t": t, **table}


def _time_series(Jinv, V, seed=1):
    """Raw time series whose consecutive rows have pose changes exactly V (T, 6) and q changes Jinv V."""
    rng = np.random.default_rng(seed)
    T = V.shape[0]
    R = [Rotation.from_rotvec(rng.normal(size=3))]
    p = [rng.normal(size=3)]
    q = [rng.normal(size=Jinv.shape[0])]
    for k in range(T):
        p.append(p[-1] + V[k, :3])
        R.append(Rotation.from_rotvec(V[k, 3:]) * R[-1])  # R_t = exp(w) R_{t-1}: log(R_t R_{t-1}^T) = w
        q.append(q[-1] + Jinv @ V[k])
    p, q = np.array(p), np.array(q)
    xyzw = np.array([r.as_quat() for r in R])
    rv = np.array([r.as_rotvec() for r in R])
    base = {"t": 0.1 * np.arange(T + 1), **{f"q_{i}": q[:, i] for i in range(q.shape[1])},
            "p_x": p[:, 0], "p_y": p[:, 1], "p_z": p[:, 2]}
    quat = {**base, "q_w": xyzw[:, 3], "q_x": xyzw[:, 0], "q_y": xyzw[:, 1], "q_z": xyzw[:, 2]}
    rotvec = {**base, "r_x": rv[:, 0], "r_y": rv[:, 1], "r_z": rv[:, 2]}
    return quat, rotvec


# ------------------------------------------------------------------ recovery on linear systems
@pytest.mark.slow
def test_pairs_recover_the_inverse_jacobian():
    Jinv, V, dtheta = _linear()
    result = sj.fit(_pairs_table(dtheta, V))
    np.testing.assert_allclose(result.estimate, Jinv, atol=TOL)
    assert result.estimates.shape == (T, 5, 3) and result.deltas.shape == (T,)
    assert result.samples.axes == (0, 1, 2) and result.samples.rejected == ()
    assert 3 < result.converged_at <= 6  # exact once V spans the task (3 samples), twice in a row


@pytest.mark.slow
def test_time_series_recovers_it_and_quaternion_equals_rotation_vector():
    rng = np.random.default_rng(2)
    Jinv = rng.normal(size=(7, 6))
    V = np.concatenate([rng.normal(scale=0.01, size=(30, 3)), rng.normal(scale=0.05, size=(30, 3))], axis=1)
    quat, rotvec = _time_series(Jinv, V)
    a = samples_from_table(quat, task_dim=6)
    b = samples_from_table(rotvec, task="x,y,z,rx,ry,rz")
    assert a.rotation == "quaternion" and b.rotation == "rotation_vector"
    np.testing.assert_allclose(a.V, V, atol=1e-12)
    np.testing.assert_allclose(b.V, a.V, atol=1e-12)
    np.testing.assert_allclose(b.dtheta, a.dtheta, atol=1e-12)
    fa, fb = sj.fit(a), sj.fit(rotvec, task_dim=6)
    np.testing.assert_allclose(fa.estimate, Jinv, atol=TOL)
    np.testing.assert_allclose(fb.estimate, Jinv, atol=TOL)
    assert fa.converged_at == fb.converged_at > 0
    # the same samples as pairs give the same fit
    fp = sj.fit(_pairs_table(a.dtheta, a.V))
    np.testing.assert_allclose(fp.estimates, fa.estimates, atol=1e-12)


@pytest.mark.slow
def test_time_series_task_axes_select_components():
    rng = np.random.default_rng(3)
    Jinv = rng.normal(size=(4, 6))
    V = rng.normal(scale=0.01, size=(20, 6))
    quat, _ = _time_series(Jinv, V)
    s = samples_from_table(quat, task="z,rx")
    np.testing.assert_allclose(s.V, V[:, [2, 3]], atol=1e-12)
    assert s.axis_names == ("z", "rx")
    pos_only = {k: v for k, v in quat.items() if not k.startswith("q_") or k[2:].isdigit()}
    np.testing.assert_allclose(samples_from_table(pos_only).V, V[:, :3], atol=1e-12)  # default task x,y,z


# ------------------------------------------------------------------ convergence: an independent loop
_update, _record = jax.jit(estimator.update), jax.jit(estimator.record)
_guess = jax.jit(lambda s: refine(s, estimator.initial_guess(s), method="closed_form"))


@pytest.mark.slow
@pytest.mark.parametrize("eps,eps_rel", [(0.0, 0.05), (0.5, 0.0), (0.1, 0.02)])
def test_convergence_iteration_equals_a_python_loop(eps, eps_rel):
    Jinv, V, dtheta = _linear(n=6, m=3, T=60, seed=4)
    rng = np.random.default_rng(5)
    V_noisy = V + rng.normal(scale=2e-4, size=V.shape)  # tracker noise: the estimate keeps moving
    result = sj.fit(_pairs_table(dtheta, V_noisy), eps=eps, eps_rel=eps_rel)
    state = estimator.init(6, 3, capacity=0, dtype=jnp.float64)
    estimates = []
    for k in range(60):  # one Python iteration per sample, each a separate call
        state = _update(state, dtheta[k], V_noisy[k])
        J = _guess(state)
        state = _record(state, J, eps, eps_rel)
        estimates.append(np.asarray(J))
    assert result.converged_at == int(state.converged_at)
    assert result.converged_at == int(estimator.convergence_iteration(jnp.asarray(estimates), eps, eps_rel))
    assert result.converged_at > 3  # the noise makes it a real test, not the exact-recovery shortcut
    np.testing.assert_allclose(result.estimates, np.array(estimates), atol=1e-12)


# ------------------------------------------------------------------ bad rows
@pytest.mark.slow
def test_each_kind_of_bad_row_is_rejected_and_counted():
    Jinv, V, dtheta = _linear(T=40, seed=6)
    quat, _ = _time_series(np.pad(Jinv, ((0, 0), (0, 3))), np.pad(V, ((0, 0), (0, 3))))
    table = {k: np.array(v, dtype=np.float64) for k, v in quat.items()}
    table["p_y"][5] = np.nan
    table["q_1"][9] = np.inf
    table["t"][15] = table["t"][14]  # duplicated timestamp
    table["t"][20] = table["t"][18]  # non-monotonic (before row 19's)
    table["t"][30:] += 2.0  # one gap of 2.1 s
    s = samples_from_table(table, task_dim=3)
    reasons = {r.reason.split(" (")[0]: r.count for r in s.rejected}
    assert reasons == {"non-finite value": 2, "duplicated timestamp": 1, "non-monotonic timestamp": 1,
                       "gap longer than 0.3 s": 1}
    first = {r.reason.split(" (")[0]: r.first for r in s.rejected}
    assert first["non-finite value"] == "row 6, column p_y"
    assert s.rows == 41 and s.used_rows == 37 and s.dtheta.shape[0] == 35
    # what is left is a sequence of valid pairs of the linear system (differences across dropped rows too)
    np.testing.assert_allclose(s.dtheta, s.V @ Jinv.T, atol=1e-12)
    np.testing.assert_allclose(sj.fit(s).estimate, Jinv, atol=TOL)
    assert samples_from_table(table, task_dim=3, max_gap=float("inf")).dtheta.shape[0] == 36


@pytest.mark.slow
def test_zero_quaternion_window_and_pairs_with_time():
    rng = np.random.default_rng(7)
    quat, _ = _time_series(rng.normal(size=(3, 6)), rng.normal(scale=0.01, size=(20, 6)))
    quat = {k: np.array(v) for k, v in quat.items()}
    for c in ("q_w", "q_x", "q_y", "q_z"):
        quat[c][4] = 0.0
    s = samples_from_table(quat, task_dim=6, start=0.15, stop=1.55)
    assert [(r.reason, r.count) for r in s.rejected] == [("zero quaternion", 1)]
    assert s.outside_window == 7 and s.t.min() > 0.15 and s.t.max() <= 1.55
    Jinv, V, dtheta = _linear(T=10, seed=8)
    t = np.arange(10.0)
    t[3] = t[2]
    p = samples_from_table(_pairs_table(dtheta, V, t))
    assert [(r.reason, r.count) for r in p.rejected] == [("duplicated timestamp", 1)]
    assert p.max_gap is None and p.dtheta.shape[0] == 9


def test_log_errors_name_file_column_and_row(tmp_path):
    Jinv, V, dtheta = _linear(T=6)
    table = _pairs_table(dtheta, V)
    with pytest.raises(LogError, match="column dtheta_2 is missing"):
        samples_from_table({k: v for k, v in table.items() if k != "dtheta_2"})
    with pytest.raises(LogError, match="task has 2 axes .* 3 V columns"):
        samples_from_table(table, task="x,y")
    bad = dict(table, V_1=np.array(["0.1", "0.2", "abc", "0.4", "0.5", "0.6"], dtype=object))
    with pytest.raises(LogError, match=r"row 3, column V_1: 'abc' is not a number"):
        samples_from_table(bad)


# ------------------------------------------------------------------ files and the command line
def _write_csv(path, table):
    keys = list(table)
    rows = np.stack([np.asarray(table[k], np.float64) for k in keys], axis=1)
    path.write_text(",".join(keys) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n")
    return path


@pytest.mark.slow
def test_csv_parquet_and_npz_give_the_same_fit(tmp_path):
    import pandas as pd

    Jinv, V, dtheta = _linear(seed=9)
    table = _pairs_table(dtheta, V)
    csv = _write_csv(tmp_path / "log.csv", table)
    pd.DataFrame(table).to_parquet(tmp_path / "log.parquet")
    np.savez(tmp_path / "log.npz", **table)
    fits = [sj.fit(tmp_path / name) for name in ("log.csv", "log.parquet", "log.npz")]
    for f in fits:
        np.testing.assert_allclose(f.estimate, Jinv, atol=TOL)
        np.testing.assert_allclose(f.estimates, fits[0].estimates, atol=1e-13)
    assert fits[0].samples.source == str(csv)


def _one_line_error(capsys, argv):
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_duplicated_column_names_exit_2_naming_the_column(tmp_path, capsys):
    """Two columns of one name: refused (pandas would read the second as q_0.1 and fit the first), in every format."""
    import zipfile

    import pandas as pd

    Jinv, V, dtheta = _linear(T=6)
    quat, _ = _time_series(np.pad(Jinv, ((0, 0), (0, 3))), np.pad(V, ((0, 0), (0, 3))))
    path = _write_csv(tmp_path / "twice.csv", quat)
    keys = list(quat)
    text = path.read_text().splitlines()
    text[0] = ",".join(k if k != "q_3" else "q_0" for k in keys)  # the second q_0 where q_3 was
    path.write_text("\n".join(text) + "\n")
    line = _one_line_error(capsys, ["fit", str(path), "--out", str(tmp_path / "o")])
    assert str(path) in line and "column q_0 appears 2 times" in line, line
    assert f"header columns {keys.index('q_0') + 1} and {keys.index('q_3') + 1}" in line
    spaced = tmp_path / "spaced.csv"  # the space after a comma is skipped, as when the file is read
    spaced.write_text("dtheta_0, V_0, dtheta_0\n0.1, 0.2, 0.3\n0.3, 0.1, 0.2\n")
    assert "column dtheta_0 appears 2 times" in _one_line_error(capsys, ["fit", str(spaced)])
    legit = tmp_path / "legit.csv"  # a column really named q_0.1 next to q_0 is no duplicate
    legit.write_text("dtheta_0,V_0,dtheta_0.1\n0.1,0.2,0.3\n0.3,0.1,0.2\n")
    assert list(read_table(legit)) == ["dtheta_0", "V_0", "dtheta_0.1"]

    npz = tmp_path / "twice.npz"  # a zip may hold two members of one name
    np.savez(npz, **quat)
    with zipfile.ZipFile(npz, "a") as z, pytest.warns(UserWarning, match="Duplicate name"):
        z.writestr("q_0.npy", z.read("q_3.npy"))
    assert "column q_0 appears 2 times" in _one_line_error(capsys, ["fit", str(npz), "--out", str(tmp_path / "o")])
    frame = pd.DataFrame(quat).rename(columns={"q_3": "q_0"})  # from Python: a DataFrame may repeat a name
    with pytest.raises(LogError, match="column q_0 appears 2 times"):
        samples_from_table(frame)
    assert not (tmp_path / "o" / "summary.json").exists()


def test_unusable_logs_exit_2_with_one_line(tmp_path, capsys):
    Jinv, V, dtheta = _linear(T=6)
    quat, _ = _time_series(np.pad(Jinv, ((0, 0), (0, 3))), np.pad(V, ((0, 0), (0, 3))))
    holed = {k: v for k, v in quat.items() if k != "q_2"}
    path = _write_csv(tmp_path / "holed.csv", holed)
    line = _one_line_error(capsys, ["fit", str(path), "--out", str(tmp_path / "o")])
    assert str(path) in line and "column q_2 is missing" in line
    path = _write_csv(tmp_path / "norot.csv", {k: v for k, v in quat.items() if k not in ("q_w", "q_x")})
    line = _one_line_error(capsys, ["fit", str(path), "--task-dim", "6", "--out", str(tmp_path / "o")])
    assert "column q_w is missing" in line
    text = tmp_path / "text.csv"
    text.write_text("dtheta_0,V_0\n0.1,0.2\n0.3,oops\n")
    line = _one_line_error(capsys, ["fit", str(text), "--out", str(tmp_path / "o")])
    assert f"{text}: line 3, column V_0: 'oops' is not a number" in line
    junk = tmp_path / "junk.parquet"
    junk.write_bytes(b"\x00not parquet at all")
    assert "cannot read as parquet" in _one_line_error(capsys, ["fit", str(junk), "--out", str(tmp_path / "o")])
    assert "no such file" in _one_line_error(capsys, ["fit", str(tmp_path / "missing.csv")])
    assert "unknown log format" in _one_line_error(capsys, ["fit", str(tmp_path / "log.txt")])
    assert "no log given" in _one_line_error(capsys, ["fit"])
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    assert str(empty) in _one_line_error(capsys, ["fit", str(empty), "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o" / "summary.json").exists()


@pytest.mark.slow
def test_example_converges_and_writes_every_file(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["fit", "--example", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "converged at sample" in printed and str(out / "inverse_jacobian.npz") in printed
    for name in ("estimates.npz", "inverse_jacobian.npz", "inverse_jacobian.json", "summary.json",
                 "figures/convergence.png", "figures/convergence.pdf"):
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["converged_at"] > 0 and summary["n"] == 6 and summary["m"] == 3
    assert {r["reason"].split(" (")[0] for r in summary["rejected"]} == {
        "non-finite value", "duplicated timestamp", "gap longer than 0.3 s"}
    assert all(r["count"] == 1 for r in summary["rejected"])
    assert summary["heldout_error"] < 0.2 and len(summary["actuator_effect"]) == 6  # the samples explain each other
    with np.load(out / "inverse_jacobian.npz") as z:
        J = z["inverse_jacobian"]
        assert J.shape == (6, 3) and int(z["converged_at"]) == summary["converged_at"]
    with np.load(out / "estimates.npz") as z:
        assert z["estimates"].shape == (summary["samples"], 6, 3)
        np.testing.assert_array_equal(z["estimates"][-1], J)
    meta = json.loads((out / "inverse_jacobian.json").read_text())
    assert meta["task_axes"] == ["x", "y", "z"] and np.allclose(meta["inverse_jacobian"], J, atol=1e-10)
    # the estimate inverts the UR5e's position Jacobian at its home configuration to a few percent
    ur5e = sj.ur5e(task_dim=3)
    JJ = np.asarray(ur5e.jacobian(jnp.asarray(UR5E_HOME)))
    assert np.abs(JJ @ J - np.eye(3)).max() < 0.15


# ------------------------------------------------------------------ jit / vmap
@pytest.mark.slow
def test_step_is_traced_once_across_thresholds_and_data(monkeypatch):
    chex.clear_trace_counter()
    monkeypatch.setattr(fit_mod, "sample_step", chex.assert_max_traces(fit_mod.sample_step, n=1))
    fit_mod._scan.clear_cache()
    for seed, (eps, eps_rel) in enumerate([(0.0, 0.05), (0.3, 0.0), (0.1, 0.2)]):
        Jinv, V, dtheta = _linear(seed=seed)
        trace = fit_mod.fit_samples(dtheta, V, eps, eps_rel)
        np.testing.assert_allclose(trace.estimate, Jinv, atol=TOL)
    fit_mod._scan.clear_cache()


@pytest.mark.slow
def test_vmap_over_logs_equals_a_loop():
    data = [_linear(seed=s) for s in range(3)]
    rng = np.random.default_rng(0)
    dtheta = jnp.stack([d[2] for d in data])
    V = jnp.stack([d[1] + rng.normal(scale=1e-4, size=d[1].shape) for d in data])
    eps_rel = jnp.array([0.01, 0.05, 0.2])
    batched = jax.vmap(lambda a, b, r: fit_mod.fit_samples(a, b, 0.0, r))(dtheta, V, eps_rel)
    for k in range(3):
        one = fit_mod.fit_samples(dtheta[k], V[k], 0.0, eps_rel[k])
        np.testing.assert_allclose(batched.estimates[k], one.estimates, atol=1e-12)
        assert int(batched.converged_at[k]) == int(one.converged_at)


@pytest.mark.slow
def test_refine_methods():
    Jinv, V, dtheta = _linear(seed=11)
    table = _pairs_table(dtheta, V)
    for method in ("optax", "slsqp"):
        np.testing.assert_allclose(sj.fit(table, method=method).estimate, Jinv, atol=1e-4)  # SLSQP: ftol 1e-12
    with pytest.raises(ValueError, match="refine method"):
        sj.fit(table, method="newton")


def test_held_out_error_is_exact_leave_one_out_and_sees_samples_that_do_not_explain_each_other():
    """robot.quality.held_out against a numpy refit without each sample; unrelated V gives an error near 1 or more."""
    from selfid_jax.robot.quality import held_out

    rng = np.random.default_rng(0)
    D = rng.uniform(-0.03, 0.03, (20, 4))
    F = rng.normal(size=(3, 4))
    V = D @ F.T + 1e-4 * rng.normal(size=(20, 3))
    q = held_out(D, V, 0.03)
    loo = [np.linalg.norm(V[k] - np.linalg.lstsq(np.delete(D, k, 0), np.delete(V, k, 0), rcond=None)[0].T @ D[k])
           for k in range(20)]
    np.testing.assert_allclose(q.heldout_error, np.sum(loo) / np.linalg.norm(V, axis=1).sum(), rtol=1e-9)
    np.testing.assert_allclose(q.effect, np.linalg.norm(F, axis=0) * 0.03, rtol=0.02)
    assert held_out(D, rng.normal(size=(20, 3)), 0.03).heldout_error > 0.9
    assert np.isnan(held_out(D[:4], V[:4], 0.03).heldout_error)  # no more samples than actuators: nothing held out


@pytest.mark.slow
def test_plot_redraws_a_fit_run_directory(tmp_path, capsys):
    from selfid_jax.cli import main
    from selfid_jax.sessions.fit_run import draw_convergence

    out = tmp_path / "fit"
    assert main(["fit", "--example", "--out", str(out)]) == 0
    figures = out / "figures"
    before = (figures / "convergence.png").stat().st_size
    for f in figures.iterdir():
        f.unlink()
    capsys.readouterr()
    assert main(["plot", str(out)]) == 0  # no config.yaml: the fit command's own hook redraws it
    assert sorted(p.name for p in figures.iterdir()) == ["convergence.pdf", "convergence.png"]
    assert abs((figures / "convergence.png").stat().st_size - before) < 0.05 * before  # the same figure
    assert capsys.readouterr().out.count("figure: ") == 2
    fig = draw_convergence([1.0, 0.1, 0.01], [0.5, 0.5, 0.5], eps=0.0, eps_rel=0.05, converged_at=3, title="t")
    assert len(fig.axes[0].get_lines()) == 3  # deltas, threshold, convergence mark
