"""The real loop's non-idealities (selfid_jax.control.realism) in the follow loop, the self-ID sampler and the
experiments' ``realism`` section: closed forms of the servo, latency, noise and dropout statistics, IDEAL against
the code path without realism, one compilation for a sweep of values, and a config run through ``selfid-jax sweep``."""

import json
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
import yaml
from selfid_jax.experiments.common import realism as realistic

from selfid_jax import cli, control, runner
from selfid_jax.control import paths
from selfid_jax.control import realism as R
from selfid_jax.identify import algorithm as selfid
from selfid_jax.math import geometry
from selfid_jax.runner.config import dump_config
from selfid_jax.runner.errors import ConfigError
from selfid_jax.runner.fingerprint import config_sha256
from selfid_jax.systems import REGISTRY

ARM = REGISTRY["two_link"].factory()
PATH = paths.star(size=0.2, dim=2)
CTRL = control.ControllerParams(max_step=0.01, tol=0.002)
STEPS = 200
# the tests of `follow_batch` (a module-level jit) and `starts` run on one worker, so those are built once, not once
# per worker (not the module: a shipped_xla test must not be grouped, conftest re-runs it by its id, which
# pytest-xdist suffixes with the group)
follow_batch_group = pytest.mark.xdist_group("realism_follow_batch")


def batch(fields: dict, n: int) -> R.Realism:
    """``Realism`` of ``(n,)`` arrays: IDEAL where ``fields`` says nothing."""
    values = {f: np.broadcast_to(np.asarray(fields.get(f, 0), np.int32 if f == "latency" else float), (n,))
              for f in R.Realism._fields}
    return R.Realism(**values)


@pytest.fixture(scope="module")
def starts():
    return np.asarray(control.feasible_starts(ARM, PATH, jax.random.key(0), 4, CTRL, steps=STEPS))


@jax.jit
@chex.assert_max_traces(n=1)
def follow_batch(q0s, r, keys):
    """One compiled call for any batch of realism values (latency up to 3): the true inverse Jacobian on the star."""
    return jax.vmap(lambda q, rr, k: control.follow(ARM, control.true_inverse(ARM), PATH, q, CTRL, steps=STEPS,
                                                    return_trajectory=True, realism=rr, key=k, max_latency=3))(
        q0s, r, keys)


def keys(n, seed=1):
    return jax.random.split(jax.random.key(seed), n)


# ------------------------------------------------------------------ the model's closed forms

def test_servo_lag_alone_on_a_fixed_target_is_the_first_order_response():
    period, tau = 0.01, 0.03
    r = R.Realism(period=period, servo_tau=tau)
    q0, u = np.array([0.3, -0.2]), np.array([-0.1, 0.5])
    qs = jax.lax.scan(lambda q, _: (R.servo(q, jnp.asarray(u), r),) * 2, jnp.asarray(q0), None, length=25)[1]
    k = np.arange(1, 26)[:, None]
    np.testing.assert_allclose(qs, u + (q0 - u) * np.exp(-k * period / tau), rtol=0, atol=1e-14)
    q0, u = jnp.asarray(q0), jnp.asarray(u)
    np.testing.assert_array_equal(R.servo(q0, u, R.Realism(period=0.0, servo_tau=tau)), u)  # period 0: no lag
    np.testing.assert_array_equal(R.servo(q0, u, R.IDEAL), u)  # no lag: the target itself, bit for bit


def test_deadband_commands_below_it_never_move():
    q, db = jnp.array([0.1, 0.2]), 0.05
    r = R.Realism(deadband=db)
    np.testing.assert_array_equal(R.servo(q, q + jnp.array([0.0499, -0.05]), r), q)
    np.testing.assert_array_equal(R.servo(q, q + jnp.array([0.0501, 0.01]), r), q + jnp.array([0.0501, 0.0]))


@pytest.mark.slow
@follow_batch_group
def test_deadband_in_the_loop_every_step_below_it_never_moves(starts):
    """Each step is clipped to dq_max = 0.1 rad, below a deadband of 0.2 rad: the arm never moves (the controller
    commands from the measured q, so the small steps do not add up)."""
    res = follow_batch(starts, batch({"deadband": [0.2, 0.2, 0.0, 0.001]}, 4), keys(4))
    np.testing.assert_array_equal(res.final_q[:2], starts[:2])
    np.testing.assert_array_equal(res.completion[:2], 0.0)
    np.testing.assert_array_equal(res.steps_used[:2], STEPS)
    assert not np.any(res.failed) and np.all(res.completion[2:] == 1.0)


@pytest.mark.slow
@follow_batch_group
def test_latency_the_reading_at_step_k_is_the_true_pose_at_k_minus_L(starts):
    lat = np.array([0, 1, 2, 3])
    res = follow_batch(starts, batch({"latency": lat}, 4), keys(4))
    for i, L in enumerate(lat):
        pos, seen = np.asarray(res.positions[i]), np.asarray(res.readings[i])
        used = int(res.steps_used[i])
        np.testing.assert_array_equal(seen[L:used], pos[: used - L])
        np.testing.assert_array_equal(seen[:L], np.repeat(pos[:1], L, axis=0))  # before the start: at rest
    assert int(res.dropouts.sum()) == 0


@pytest.mark.slow
@follow_batch_group
def test_noise_the_empirical_sd_of_the_readings_matches(starts):
    sd = np.array([1e-4, 1e-4, 3e-4, 3e-4])
    res = follow_batch(starts, batch({"noise_pos": sd}, 4), keys(4))
    for i in range(4):
        used = int(res.steps_used[i])
        err = (np.asarray(res.readings[i]) - np.asarray(res.positions[i]))[:used, :2]  # the plane's axes
        n = err.size
        assert abs(err.std() / sd[i] - 1) < 5 / math.sqrt(2 * n), (sd[i], err.std(), n)  # 5 sigma of the sd
        assert abs(err.mean()) < 5 * sd[i] / math.sqrt(n)
    # rotation noise: the rotation vector of a reading against the truth, sd per axis
    tr = R.tracker((jnp.zeros(3), jnp.eye(3)), 0)
    Rs = jax.jit(jax.vmap(lambda k: R.read(tr, k, R.Realism(noise_rot=0.02))[0][1]))(keys(4000, 7))
    w = np.asarray(geometry.so3_log(Rs))
    np.testing.assert_allclose(w.std(axis=0), 0.02, rtol=0.06)


@pytest.mark.slow
@follow_batch_group
def test_dropout_rate_within_binomial_bounds_and_every_metric_finite(starts):
    p = np.array([0.0, 0.1, 0.3, 0.6])
    res = follow_batch(starts, batch({"dropout": p, "noise_pos": 1e-4}, 4), keys(4))
    for i in range(4):
        n, k = int(res.steps_used[i]), int(res.dropouts[i])
        assert abs(k - n * p[i]) <= 4 * math.sqrt(n * p[i] * (1 - p[i])) + 1e-9, (p[i], k, n)
    for f in ("completion", "mean_error", "max_error", "waypoint_error", "final_q", "positions", "readings"):
        assert np.all(np.isfinite(np.asarray(getattr(res, f)))), f
    assert res.completion[0] == 1.0 and not np.any(res.failed)


@pytest.mark.slow
@follow_batch_group
def test_a_dropped_reading_makes_no_command_that_step(starts):
    """The live runner's rule in the simulation: a step whose reading dropped out does not move the arm (no latency,
    no noise: a reading that differs from the pose is a held, dropped one)."""
    res = follow_batch(starts, batch({"dropout": 0.3}, 4), keys(4, 5))
    held = 0
    for i in range(4):
        used = int(res.steps_used[i])
        pos, seen = np.asarray(res.positions[i]), np.asarray(res.readings[i])
        dropped = np.flatnonzero(np.any(seen[:used] != pos[:used], axis=1))
        np.testing.assert_array_equal(pos[dropped + 1], pos[dropped])
        held += dropped.size
    assert held >= 20 and not np.any(res.failed)  # (a held step still spends the step budget)


# ------------------------------------------------------------------ IDEAL is the ideal loop

@pytest.mark.slow
@follow_batch_group
def test_ideal_follow_equals_the_loop_without_realism_bit_for_bit(starts):
    plain = jax.jit(jax.vmap(lambda q: control.follow(ARM, control.true_inverse(ARM), PATH, q, CTRL, steps=STEPS,
                                                      return_trajectory=True)))(starts)
    ideal = follow_batch(starts, batch({}, 4), keys(4))  # the realism program (latency up to 3) at IDEAL values
    for f in plain._fields:
        if getattr(plain, f) is not None:
            for a, b in zip(jax.tree.leaves(getattr(ideal, f)), jax.tree.leaves(getattr(plain, f)), strict=True):
                np.testing.assert_array_equal(a, b, err_msg=f)
    np.testing.assert_array_equal(ideal.readings, ideal.positions)


@pytest.mark.slow
def test_ideal_self_id_samples_equal_run_bit_for_bit():
    """The samples (actuations, pose changes, where self-ID ended, the estimator's sums) are ``run``'s bit for bit;
    the refined estimate to rounding: XLA's CPU backend contracts multiply-adds into FMAs where it fuses them, and
    a program with the realism values traced may fuse the refinement differently."""
    n = 3
    q0 = ARM.sample_configs(jax.random.key(3), n)
    noise = np.array([0.0, 1e-4, 5e-4])
    rows = dict(eps=np.full(n, 1e-3), eps_rel=np.zeros(n), m_a=np.full((n, 2), 0.02), pose_noise=noise,
                rot_noise=noise)

    def old(k, q, c):
        return selfid.run(ARM, k, q, iters=15, **c)

    def new(k, q, c, r):
        return realistic.self_identify(ARM, k, q, iters=15, **c, realism=r, settle=1, max_latency=1, max_settle=2)

    a = jax.jit(jax.vmap(old))(keys(n, 4), q0, rows)
    b, dropouts = jax.jit(jax.vmap(new))(keys(n, 4), q0, rows, batch({}, n))
    for f in ("dtheta", "V", "env", "converged_at"):
        np.testing.assert_array_equal(getattr(b, f), getattr(a, f), err_msg=f)
    for f in ("S_vv", "S_tv", "sign_net", "mag_sum", "count", "rejected"):
        np.testing.assert_array_equal(getattr(b.state, f), getattr(a.state, f), err_msg=f)
    np.testing.assert_allclose(b.estimates, a.estimates, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(dropouts, 0)


@pytest.mark.slow
def test_self_id_sampler_servo_lag_dropouts_and_no_nan():
    q0 = jnp.array([0.4, 0.9])
    r = R.Realism(period=0.01, servo_tau=0.02)
    observe, env = R.self_id_sampler(ARM, r, q0, settle=3, max_settle=4)
    env1, V = jax.jit(observe)(env, jax.random.key(0), jnp.array([0.02, -0.01]))  # one program, not op by op
    np.testing.assert_allclose(env1.q, q0 + (1 - np.exp(-3 * 0.01 / 0.02)) * np.array([0.02, -0.01]), atol=1e-14)
    assert int(env1.tracker.t) == 3 and np.all(np.isfinite(V))  # three control steps, each pose recorded
    # dropouts: the sample is rejected and counted, the estimate stays finite
    res, drops = jax.jit(lambda k, q, r: realistic.self_identify(
        ARM, k, q, iters=40, eps=1e-12, eps_rel=0.0, m_a=0.02, pose_noise=0.0, rot_noise=0.0, realism=r,
        max_latency=0))(jax.random.key(1), q0, R.Realism(dropout=0.3, noise_pos=1e-5))
    lost = np.isnan(np.asarray(res.V)).any(axis=1)
    assert 0 < lost.sum() < 40 and int(res.state.rejected) == lost.sum() and int(res.state.count) == 40 - lost.sum()
    assert int(drops) >= lost.sum() and np.all(np.isfinite(res.estimate)) and np.all(np.isfinite(res.deltas))


def test_check_realism_names_the_field_and_passes_traced_values():
    with pytest.raises(ValueError, match="realism.dropout"):
        R.check_realism(R.Realism(dropout=1.0))
    with pytest.raises(ValueError, match="realism.latency"):
        R.check_realism(R.Realism(latency=1.5))
    with pytest.raises(ValueError, match="realism.noise_pos"):
        R.check_realism(R.Realism(noise_pos=np.array([0.0, -1.0])))
    assert R.check_realism(R.Realism(latency=np.float64(2.0))).latency == 2
    jax.jit(lambda r: R.check_realism(r).period)(R.Realism(period=0.01, dropout=0.5, latency=1))
    with pytest.raises(ValueError, match="max_latency"):
        control.follow(ARM, control.true_inverse(ARM), PATH, jnp.zeros(2), CTRL, steps=5,
                       realism=R.Realism(latency=3), key=jax.random.key(0), max_latency=2)
    with pytest.raises(ValueError, match="key"):
        control.follow(ARM, control.true_inverse(ARM), PATH, jnp.zeros(2), CTRL, steps=5, realism=R.IDEAL)


# ------------------------------------------------------------------ the experiments' realism section

VR = {"experiment": "valid_region", "seed": 0, "systems": ["two_link"], "eps_limits": {"start": 0.5, "stop": 1.5,
      "num": 3}, "n_configs": 2, "n_trials": 2, "path": {"kind": "star", "size": 0.2},
      "controller": {"max_step": 0.01, "tol": 0.002, "steps": 200}, "chunk_size": 64}


@pytest.mark.slow  # end to end through the CLI
@pytest.mark.shipped_xla  # bit for bit holds for the shipped build (at LLVM level 0: within 1 ulp)
def test_a_realism_sweep_runs_through_the_cli_and_its_ideal_level_is_the_run_without_realism(tmp_path):
    """One compiled program per system serves every level; the level with every value 0 (IDEAL) reproduces the
    study without a realism section bit for bit (its rows come first, so they draw the same keys)."""
    cfg = {**VR, "realism": {"latency": [0, 2], "noise_pos": [0.0, 0.001], "dropout": [0.0, 0.2]}}
    path = tmp_path / "vr_realism.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert cli.main(["sweep", str(path), "--out", str(tmp_path / "run"), "--no-progress"]) == 0
    df = pd.read_parquet(tmp_path / "run" / "results.parquet")
    assert len(df) == 8 * 3 * 2 * 2 and sorted(df["realism_level"].unique()) == list(range(8))
    levels = df.groupby("realism_level")[["latency", "noise_pos", "dropout"]].first()
    assert set(levels.itertuples(index=False)) == {(a, b, c) for a in (0, 2) for b in (0.0, 0.001) for c in (0, 0.2)}
    assert (df[df["dropout"] == 0.2]["dropouts"] > 0).all() and (df[df["dropout"] == 0]["dropouts"] == 0).all()
    assert np.all(np.isfinite(df[["completion", "mean_error", "max_error", "waypoint_error"]].to_numpy()))
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert len(summary["systems"]) == 8 and summary["systems"][
        "two_link (latency=2, noise_pos=0.001, dropout=0.2)"]["realism"]["latency"] == 2
    assert (tmp_path / "run" / "figures" / "valid_region.png").stat().st_size > 1000
    exp = runner.get("valid_region")
    plain, _ = runner.run(exp, exp.config(**VR), tmp_path / "plain")
    ideal = df[df["realism_level"] == 0].reset_index(drop=True)
    for c in plain.columns:
        np.testing.assert_array_equal(ideal[c].to_numpy(), plain[c].to_numpy(), err_msg=c)
    assert len(exp.parts(exp.config(**cfg))) == 1  # one part (one compiled program) for the whole sweep
    hashes = {config_sha256(dump_config(exp.config(**c))) for c in (
        VR, {**VR, "realism": {}}, cfg, {**cfg, "realism": {**cfg["realism"], "dropout": 0.1}})}
    assert len(hashes) == 4  # any change to the section is a new run, never mixed with old rows


def test_realism_config_errors_name_the_key(tmp_path):
    path = tmp_path / "vr.yaml"
    path.write_text(yaml.safe_dump(VR))
    for override, key in (("realism.latency=1.5", "realism.latency[0]"), ("realism.noise_pos=-1", "realism.noise_pos"),
                          ("realism.dropout=1", "realism.dropout"), ("realism.settle=2", "realism.settle"),
                          ("realism.latency=[1,1]", "realism.latency"), ("realism.servo_tau=0.1", "servo_tau")):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.").replace("[", r"\[")):
            runner.load(path, [override])
    exp = runner.get("tracking")
    base = dict(system="two_link", path={"kind": "star", "size": 0.05}, n_configs=1)
    with pytest.raises(ValueError, match="realism.noise_pos"):
        exp.config(**base, pose_noise=[0.0, 1e-4], rot_noise=[0.0, 0.0], realism={"noise_pos": 1e-4})
    assert exp.config(**base, realism={"settle": [1, 3], "latency": 1}).realism.levels()[1] == {
        "period": 0.0, "latency": 1, "noise_pos": 0.0, "noise_rot": 0.0, "dropout": 0.0, "servo_tau": 0.0,
        "deadband": 0.0, "settle": 3}


@pytest.mark.slow
def test_tracking_under_realism_gives_columns_summaries_and_figures_per_level(tmp_path):
    """The tracking experiment with a two-level realism section (ideal, and one step of latency with a self-ID
    settle of 2): the realism and dropout columns, one summary entry and one figure per level, finite metrics."""
    exp = runner.get("tracking")
    cfg = exp.config(system="two_link", path={"kind": "text", "text": "L", "height": 0.12},
                     controller={"max_step": 0.01, "tol": 0.002, "steps": 120}, n_configs=1, iters=12, m_a=0.02,
                     eps=0.05, realism={"latency": [0, 1], "settle": 2, "dropout": 0.05, "noise_pos": 1e-5})
    table, summary = runner.run(exp, cfg, tmp_path)
    assert len(table) == 2 * 2 and set(table["latency"]) == {0, 1} and (table["settle"] == 2).all()
    assert {"selfid_dropouts", "selfid_rejected", "dropouts", "realism_level"} <= set(table.columns)
    assert (table["selfid_rejected"] >= table["selfid_dropouts"].clip(upper=1)).all()
    assert np.all(np.isfinite(table[["completion", "waypoint_error_mm", "error_x_mm", "error_y_mm"]].to_numpy()))
    assert set(summary["systems"]) == {"two_link (latency=0)", "two_link (latency=1)"}
    assert summary["systems"]["two_link (latency=1)"]["realism"]["settle"] == 2
    written = exp.plot(table, summary, tmp_path / "figures")
    assert sorted(p.name for p in written if p.suffix == ".png") == [
        "tracking_two_link_realism0.png", "tracking_two_link_realism1.png"]
    assert "two_link (latency=1)" in exp.report(summary)
