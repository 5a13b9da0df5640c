"""Continuous log streams (:mod:`selfid_jax.robot.streams`): detection, settled intervals, tracker latency, and the
fit of a reduced 100 Hz stream against the fit of its settled rows."""


import numpy as np
import pytest
from helpers_logs import (  # tests/ is on the path
    _J,
    EXAMPLE,
    LATENCY,
    MOVES,
    NOISE,
    POS_COLS,
    Q_COLS,
    QUAT_COLS,
    _stream,
)
from scipy.spatial.transform import Rotation

from selfid_jax.robot import streams
from selfid_jax.robot.log import read_table, samples_from_table
from selfid_jax.robot.offline import fit_samples
from selfid_jax.robot.streams import (
    estimate_latency,
    is_continuous,
    latency_estimate,
    reduce_stream,
    settled_intervals,
    shift_tracker,
    stream_stats,
)


def _tq(table):
    return table["t"], np.stack([table[c] for c in Q_COLS], axis=1)


def _error(samples, J):
    """``||J Jinv_hat - I||_F`` of the fit of ``samples`` (every sample)."""
    est = np.asarray(fit_samples(samples.dtheta, samples.V).estimate)
    return float(np.linalg.norm(J @ est - np.eye(J.shape[0])))


@pytest.fixture(scope="module")
def stream():
    return _stream(seed=1)


@pytest.mark.slow
def test_reduced_stream_fits_as_well_as_its_settled_rows(stream):
    table, settled = stream
    J = _J()
    raw = _error(samples_from_table(table), J)
    truth = _error(samples_from_table({k: v[settled] for k, v in table.items()}), J)
    reduced, info = reduce_stream(table, Q_COLS, POS_COLS)
    ours = _error(samples_from_table(reduced), J)
    print(f"\n||J Jhat - I||_F: raw rows {raw:.4f}, settled rows {truth:.4f}, reduced stream {ours:.4f}; "
          f"{info.line()}")
    assert raw > 5 * truth  # (a) pairing the 100 Hz rows is bad
    assert ours <= 1.5 * truth  # (b) the reduced stream is as good as the settled rows
    assert info.continuous and info.detected and info.mode == "auto"
    assert info.segments == info.rows_out == MOVES + 1 == reduced["t"].shape[0]
    assert info.rows_in == table["t"].shape[0] and info.rows_dropped == 0
    assert abs(info.latency_s - LATENCY) < 3e-3 and info.latency_s == info.latency_estimate_s
    assert info.latency_correlation > streams.LATENCY_MIN_CORR
    # each settled interval ends at a settled row (the last before the next command), and so does its row's time
    np.testing.assert_allclose(reduced["t"], table["t"][settled])
    np.testing.assert_allclose(info.intervals[:, 1], table["t"][settled])
    assert np.all(np.isfinite(np.stack(list(reduced.values()))))
    # q of each representative row: the settled position (the servo is within ~1e-10 rad of its target)
    q_red = np.stack([reduced[c] for c in Q_COLS], axis=1)
    np.testing.assert_allclose(q_red, np.stack([table[c][settled] for c in Q_COLS], axis=1), atol=1e-7)


def test_latency_estimate():
    table, _ = _stream(seed=2)
    t, q = _tq(table)
    p = np.stack([table[c] for c in POS_COLS], axis=1)
    est = latency_estimate(t, q, p)
    print(f"\nlatency estimate {1e3 * est.seconds:.2f} ms (true 10 ms), correlation {est.correlation:.3f}")
    assert abs(est.seconds - LATENCY) < 3e-3  # (c)
    assert est.correlation > 0.9 and est.grid_dt == pytest.approx(0.01)
    assert estimate_latency(t, q, p) == est.seconds
    late, _ = _stream(seed=2, latency=0.035)  # a sub-frame latency (3.5 frames)
    assert abs(estimate_latency(*_tq(late), np.stack([late[c] for c in POS_COLS], 1)) - 0.035) < 3e-3
    none, _ = _stream(seed=2, latency=0.0)
    assert abs(estimate_latency(*_tq(none), np.stack([none[c] for c in POS_COLS], 1))) < 3e-3
    with pytest.raises(ValueError, match="edge of the search"):
        latency_estimate(t, q, p, max_lag_s=0.005)
    with pytest.raises(ValueError, match="never move"):
        latency_estimate(t, np.zeros_like(q), p)


def test_shift_tracker_undoes_a_late_tracker():
    t = np.arange(50) * 0.01
    x = np.sin(3 * t)
    late = np.sin(3 * (t - 0.02))  # logs at t the value of t - 0.02
    shifted = shift_tracker(t, {"p_x": late}, 0.02)["p_x"]
    np.testing.assert_allclose(shifted[:-2], x[:-2], atol=1e-3)  # linear interpolation; the end value held after
    assert shifted[-1] == late[-1]
    # rotations: quaternions with flipped signs and rotation vectors interpolate the short way and stay unit
    rot = Rotation.from_rotvec(np.outer(np.sin(3 * t), [0.3, -0.2, 0.9]))
    rot_late = Rotation.from_rotvec(np.outer(np.sin(3 * (t - 0.02)), [0.3, -0.2, 0.9]))
    wxyz = rot_late.as_quat()[:, [3, 0, 1, 2]] * np.where(np.arange(50) % 3 == 0, -1.0, 1.0)[:, None]
    out = shift_tracker(t, {c: wxyz[:, i] for i, c in enumerate(QUAT_COLS)}, 0.02)
    got = Rotation.from_quat(np.stack([out[c] for c in ["q_x", "q_y", "q_z", "q_w"]], axis=1))
    np.testing.assert_allclose(np.linalg.norm(np.stack(list(out.values()), 1), axis=1), 1.0)
    assert np.max((got[:-2] * rot[:-2].inv()).magnitude()) < 1e-3
    rv = rot_late.as_rotvec()
    out = shift_tracker(t, {c: rv[:, i] for i, c in enumerate(["r_x", "r_y", "r_z"])}, 0.02)
    got = Rotation.from_rotvec(np.stack([out["r_x"], out["r_y"], out["r_z"]], axis=1))
    assert np.max((got[:-2] * rot[:-2].inv()).magnitude()) < 1e-3


def test_example_log_is_not_a_stream_and_passes_unchanged(stream):
    example = read_table(EXAMPLE)
    stats = stream_stats(*_tq(example))
    assert not stats.continuous and not is_continuous(*_tq(example))  # (d)
    assert stats.still_fraction < 0.05 and abs(stats.coherence) < 0.2
    out, info = reduce_stream(example, Q_COLS, POS_COLS + QUAT_COLS)
    assert not info.continuous and info.detected is False and info.rows_out == info.rows_in == 65
    assert list(out) == list(example)
    for c in example:
        np.testing.assert_array_equal(out[c], example[c])  # NaN row and duplicated row left to the pairing's screens
    assert "per-move log" in info.line()
    assert is_continuous(*_tq(stream[0]))
    stream_stats_ = stream_stats(*_tq(stream[0]))
    assert stream_stats_.still_fraction > 0.7 and stream_stats_.coherence > 0.9


def test_modes_force_the_behaviour(stream):
    table, _ = stream
    out, info = reduce_stream(table, Q_COLS, POS_COLS, mode="moves")  # (e) a stream used as it is
    assert not info.continuous and info.detected is None and info.rows_out == table["t"].shape[0]
    for c in table:
        assert out[c] is table[c] or np.array_equal(out[c], table[c])
    forced, info = reduce_stream(table, Q_COLS, POS_COLS, mode="stream")
    auto, _ = reduce_stream(table, Q_COLS, POS_COLS)
    assert info.continuous and info.segments == MOVES + 1
    for c in table:
        np.testing.assert_array_equal(forced[c], auto[c])
    # the example log (one row per move, 0.1 s apart) forced through the stream reduction: it never rests
    with pytest.raises(ValueError, match="no settled interval found"):
        reduce_stream(read_table(EXAMPLE), Q_COLS, POS_COLS + QUAT_COLS, mode="stream")
    with pytest.raises(ValueError, match="stream mode must be one of"):
        reduce_stream(table, Q_COLS, POS_COLS, mode="continuous")


def test_long_rests_and_encoder_noise():
    table, settled = _stream(seed=4, moves=9, period=2.05)  # rests 97 % of the rows (same row count: one compile)
    rng = np.random.default_rng(5)
    for c in Q_COLS:
        table[c] = table[c] + 1e-5 * rng.normal(size=table[c].shape)  # encoder noise, 1e-5 rad
    stats = stream_stats(*_tq(table))
    assert stats.continuous and stats.still_fraction > 0.9
    reduced, info = reduce_stream(table, Q_COLS, POS_COLS)
    assert info.segments == 10 and abs(info.latency_s - LATENCY) < 3e-3
    np.testing.assert_allclose(reduced["t"], table["t"][settled])
    q_red = np.stack([reduced[c] for c in Q_COLS], axis=1)  # a mean of ~100 rows: the noise / 10
    np.testing.assert_allclose(q_red, np.stack([table[c][settled] for c in Q_COLS], axis=1), atol=5e-5)


@pytest.mark.slow
def test_a_stream_that_never_rests_is_read_by_windows():
    table, _ = _stream(moves=100, period=0.03)  # a new command every 3 rows: the servo never settles
    assert is_continuous(*_tq(table))  # its steps follow one smooth motion (coherence), although it never rests
    with pytest.raises(streams.NoRestsError, match=r"no settled interval found: .*v_tol=.*--settle-speed"):  # (f)
        settled_intervals(*_tq(table))
    for mode, settle in (("auto", None), ("stream", None), ("auto", 0.02)):  # 0.02 s: only the rest before the first
        reduced, info = reduce_stream(table, Q_COLS, POS_COLS, mode=mode, min_settle_s=settle)
        assert info.continuous and info.reading == "windows" and info.v_tol is None
        assert "fewer than two rests" in info.notes[0] and ("--settle-time 0.02 s" in info.notes[0]) == bool(settle)
        assert info.segments == reduced["t"].shape[0] - 1 > 30 and "without rests" in info.line()


@pytest.mark.slow
def test_jittered_stamps(stream):
    table, settled = _stream(seed=1, jitter=1e-3)  # (g) stamps +-1 ms around the 100 Hz grid
    J = _J()
    truth = _error(samples_from_table({k: v[settled] for k, v in table.items()}), J)
    reduced, info = reduce_stream(table, Q_COLS, POS_COLS)
    ours = _error(samples_from_table(reduced), J)
    print(f"\njittered: settled rows {truth:.4f}, reduced stream {ours:.4f}; {info.line()}")
    assert info.continuous and info.segments == MOVES + 1
    assert ours <= 1.5 * truth
    assert abs(info.latency_estimate_s - LATENCY) < 3e-3


@pytest.mark.slow
def test_quaternions_are_averaged_consistently():
    table, settled = _stream(seed=3, quaternion=True, moves=30)
    reduced, info = reduce_stream(table, Q_COLS, POS_COLS + QUAT_COLS)
    assert info.segments == 31
    wxyz = np.stack([reduced[c] for c in QUAT_COLS], axis=1)
    np.testing.assert_allclose(np.linalg.norm(wxyz, axis=1), 1.0)
    truth = np.stack([table[c][settled] for c in QUAT_COLS], axis=1)  # noise-free, random signs
    angle = (Rotation.from_quat(wxyz[:, [1, 2, 3, 0]]) * Rotation.from_quat(truth[:, [1, 2, 3, 0]]).inv()).magnitude()
    assert angle.max() < 1e-7  # rad: the settled rotation (the servo creeps ~1e-8 rad in the averaged half)
    # paired, the rotation part of V (noise-free here) is the settled rows' (to the creep); the position part differs
    # by the tracker noise (0.1 mm per settled row, averaged away in the reduced rows)
    ours = samples_from_table(reduced, task_dim=6).V
    truth = samples_from_table({k: v[settled] for k, v in table.items()}, task_dim=6).V
    np.testing.assert_allclose(ours[:, 3:], truth[:, 3:], atol=1e-7)
    np.testing.assert_allclose(ours[:, :3], truth[:, :3], atol=6 * NOISE)


def test_bad_rows_other_columns_and_explicit_thresholds(stream):
    table, settled = stream
    table = {k: v.copy() for k, v in table.items()}
    table["p_x"][120] = np.nan  # a tracker glitch mid-rest
    table["t"][230] = table["t"][229]  # a duplicated stamp
    table["status"] = np.arange(table["t"].shape[0])  # another column: taken at each interval's last row
    reduced, info = reduce_stream(table, Q_COLS, POS_COLS, latency=None, v_tol=0.02, min_settle_s=0.2)
    assert info.rows_dropped == 2 and info.latency_s is None and info.latency_estimate_s is None
    assert info.v_tol == 0.02 and info.min_settle_s == 0.2 and info.segments == MOVES + 1
    np.testing.assert_array_equal(reduced["status"], settled)
    assert all(np.isfinite(v).all() for v in reduced.values())
    _, fixed = reduce_stream(table, Q_COLS, POS_COLS, latency=0.01)
    assert fixed.latency_s == 0.01 and fixed.latency_estimate_s is None
    with pytest.raises(ValueError, match="v_tol"):
        reduce_stream(table, Q_COLS, POS_COLS, v_tol=-1.0)
    with pytest.raises(ValueError, match="latency must be"):
        reduce_stream(table, Q_COLS, POS_COLS, latency="late")
    with pytest.raises(ValueError, match="column q_9 is missing"):
        reduce_stream(table, [*Q_COLS, "q_9"], POS_COLS, mode="stream")
    same, info = reduce_stream(table, [*Q_COLS, "q_9"], POS_COLS)  # auto: left to the pairing's screens
    assert same["t"] is table["t"] and not info.continuous and "q_9" in info.notes[0] and "not checked" in info.line()
    seg = settled_intervals(*_tq(stream[0]))
    assert seg.v_tol == pytest.approx(streams.SETTLE_SPEED_RATIO * seg.v_ref)
    assert seg.min_settle_s >= streams.MIN_SETTLE_STEPS * 0.01
    with pytest.raises(ValueError, match="joints never move"):
        settled_intervals(np.arange(10.0), np.zeros((10, 2)))


@pytest.mark.slow
def test_selfid_jax_fit_reads_a_lagged_stream_with_no_hand_editing(stream, tmp_path, capsys):
    """The issue's log: 100 Hz while moving, 20 ms servo lag, the tracker one frame late, 0.1 mm noise, as a CSV.
    selfid-jax fit detects the stream, reduces it, reports it and the latency, and its estimate is within 1.5x the
    error of the settled rows' own fit (also through the command)."""
    import json

    import pandas as pd

    from selfid_jax.cli import main

    table, settled = stream
    J = _J()
    path, rows = tmp_path / "stream.csv", tmp_path / "settled.csv"
    pd.DataFrame(table).to_csv(path, index=False, float_format="%.17g")
    pd.DataFrame({k: v[settled] for k, v in table.items()}).to_csv(rows, index=False, float_format="%.17g")
    errors = {}
    for name, log in (("stream", path), ("settled", rows)):
        out = tmp_path / name
        assert main(["fit", str(log), "--out", str(out)]) in (0, 1)
        info = json.loads((out / "summary.json").read_text())
        est = np.load(out / "inverse_jacobian.npz")["inverse_jacobian"] if info["converged"] else \
            np.asarray(info["estimate_so_far"])
        errors[name] = float(np.linalg.norm(J @ est - np.eye(3)))
        if name == "stream":
            assert any("a continuous stream" in n and "tracker latency" in n for n in info["notes"]), info["notes"]
            assert info["samples"] == MOVES
    print(f"\nselfid-jax fit: stream {errors['stream']:.4f}, settled rows {errors['settled']:.4f}")
    assert errors["stream"] <= 1.5 * errors["settled"]
    assert "a continuous stream" in capsys.readouterr().out


@pytest.mark.slow
def test_a_latency_beyond_the_old_search_is_found_not_aliased():
    """Issue 54: a 400 ms tracker lag, beyond the old +-0.25 s search, was taken for its alias -100 ms (a move every
    0.5 s) and fitted at ||J Jhat - I|| ~2 with exit 0; the search now covers a quarter of the log."""
    import selfid_jax as sj

    J = _J()
    base = sj.fit(_stream(seed=1)[0])
    late = sj.fit(_stream(seed=1, latency=0.4)[0])
    assert abs(late.report.stream.latency_s - 0.4) < 3e-3
    err = lambda r: float(np.linalg.norm(J @ r.estimate - np.eye(3)))
    assert err(late) < 1.5 * err(base)


@pytest.mark.slow
def test_rests_past_the_latency_shift_are_not_paired_with_a_held_pose():
    """A 2 s tracker lag: the shifted pose is undefined over the log's last 2 s (held at its end value), so the 4
    rests there give no row, not samples whose tracked motion is 0."""
    from helpers_logs import _poses

    table, settled = _stream(seed=1, latency=2.0)
    reduced, info = reduce_stream(table, Q_COLS, POS_COLS)
    assert abs(info.latency_s - 2.0) < 3e-3 and "4 rests beyond the rows the tracker latency" in info.notes[0]
    assert info.rows_out == info.segments == MOVES + 1 - 4 == info.intervals.shape[0]
    np.testing.assert_allclose(reduced["t"], table["t"][settled[:-4]])
    q = np.stack([reduced[c] for c in Q_COLS], axis=1)
    p = np.stack([reduced[c] for c in POS_COLS], axis=1)
    assert np.abs(p - np.asarray(_poses()(q)[0])).max() < 5 * NOISE  # every row's pose is its q's, averaged


def test_a_latency_at_the_edge_of_the_search_is_refused(stream, monkeypatch):
    from selfid_jax.robot import streams

    monkeypatch.setattr(streams, "LATENCY_SEARCH_FRACTION", 0.0)  # a search narrower than the lag (10 ms)
    with pytest.raises(ValueError, match=r"tracker latency is beyond what the log can show .* --latency S"):
        reduce_stream(stream[0], Q_COLS, POS_COLS, max_lag_s=0.005)


@pytest.mark.slow
def test_no_rests_advice_never_points_at_mode_moves():
    """Issue 54: the no-rests message advised --mode moves, which pairs the motion's rows (||J Jhat - I|| 0.78); a
    stream without rests is now read by windows, and one too short for them names windows and rests, never moves."""
    table, _ = _stream(moves=100, period=0.03)
    short = {k: v[:8] for k, v in table.items()}  # 8 rows: less than two windows of 4 rows
    with pytest.raises(streams.NoRestsError) as err:
        reduce_stream(short, Q_COLS, POS_COLS, mode="windows")
    assert "record the moves with a rest after each" in str(err.value) and "--mode windows" in str(err.value)
    assert "(--mode moves)" not in str(err.value) and "--mode moves would pair" in str(err.value)
    with pytest.raises(ValueError, match="read it with --mode auto"):  # a per-move log forced through as a stream
        reduce_stream(read_table(EXAMPLE), Q_COLS, POS_COLS + QUAT_COLS, mode="stream")
