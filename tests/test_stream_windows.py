"""A stream without rests read by windows of its motion (issue 54, item 3): :func:`selfid_jax.robot.streams.
motion_windows`, :func:`selfid_jax.robot.latency.latency_fit`, and the fit of such a stream against the fit of the same
arm's rest-and-move log, both against the true Jacobian."""

import numpy as np
import pytest
from helpers_logs import _J, NOISE, POS_COLS, Q_COLS, RATE, _poses, _stream, run_fit_command  # tests/ is on the path

import selfid_jax as sj
from selfid_jax.robot import streams
from selfid_jax.robot.latency import latency_estimate, latency_fit
from selfid_jax.robot.streams import NoRestsError, motion_windows, reduce_stream
from selfid_jax.systems.ur5e import UR5E_HOME


def _smooth(seconds=20.5, latency=0.01, seed=0, amp=0.05):
    """The UR5e moving without a rest: each joint ``home + amp * sum of 3 sines`` (0.2-1 Hz, random phases), logged
    at 100 Hz; the tracker logs at ``t`` the pose of ``t - latency`` with ``NOISE`` Gaussian position noise."""
    rng = np.random.default_rng(seed)
    f, phase = rng.uniform(0.2, 1.0, (3, 6)), rng.uniform(0.0, 2 * np.pi, (3, 6))
    t = np.arange(int(round(seconds * RATE))) / RATE

    def q_at(s):
        return np.asarray(UR5E_HOME) + amp * np.sin(2 * np.pi * f * s[:, None, None] + phase).sum(axis=1)

    q = q_at(t)
    p = np.asarray(_poses()(q_at(t - latency))[0]) + NOISE * rng.normal(size=(t.size, 3))
    return {"t": t, **{c: q[:, i] for i, c in enumerate(Q_COLS)}, **{c: p[:, i] for i, c in enumerate(POS_COLS)}}


def _error(result):
    return float(np.linalg.norm(_J() @ result.estimate - np.eye(3)))


def _tqp(table):
    return (table["t"], np.stack([table[c] for c in Q_COLS], axis=1), np.stack([table[c] for c in POS_COLS], axis=1))


def test_motion_windows_length_from_the_motion():
    t = np.arange(301) / 100.0
    q = np.stack([0.2 * t, -0.05 * t], axis=1)  # a straight motion at 0.2 rad/s: a window of w moves 0.2 w
    win = motion_windows(t, q)
    assert win.window_s == pytest.approx(streams.WINDOW_MOVE / 0.2, rel=1e-6)  # 0.15 s
    assert win.median_move == pytest.approx(streams.WINDOW_MOVE, rel=1e-6) and win.move == streams.WINDOW_MOVE
    np.testing.assert_allclose(np.diff(win.edges), win.window_s)
    assert win.edges[0] == 0.0 and win.edges[-1] <= 3.0 and win.edges.size == 21
    fast = motion_windows(t, 100 * q)  # 20 rad/s: the shortest window (4 rows), moving more than WINDOW_MOVE
    assert fast.window_s == pytest.approx(streams.MIN_WINDOW_STEPS / 100.0) and fast.median_move > 0.5
    walk = np.cumsum(np.random.default_rng(0).normal(0.0, 0.01, (3000, 3)), axis=0)  # a random walk: move ~ sqrt(w)
    rw = motion_windows(np.arange(3000) / 100.0, walk)
    assert abs(rw.median_move / streams.WINDOW_MOVE - 1) < 0.1
    with pytest.raises(NoRestsError, match="no windows"):
        motion_windows(t[:8], q[:8])  # less than two windows of 4 rows
    with pytest.raises(NoRestsError, match="no windows"):
        motion_windows(t, np.zeros_like(q))


@pytest.mark.slow
@pytest.mark.parametrize("lag", [0.035, -0.02, 0.4])
def test_latency_fit_times_a_smooth_motion(lag):
    """The speed of a smooth motion changes too slowly to time a lag; the velocity map's residual does."""
    t, q, p = _tqp(_smooth(latency=lag))
    est = latency_fit(t, q, p, max_lag_s=3.0)
    assert abs(est.seconds - lag) < 3e-3 and est.correlation > 0.95 and est.grid_dt == pytest.approx(0.01)
    with pytest.raises(ValueError, match="edge of the search"):
        latency_fit(t, q, p, max_lag_s=abs(lag) / 2)


@pytest.mark.slow
def test_latency_fit_agrees_with_the_speed_correlation_on_a_stream_with_rests():
    t, q, p = _tqp(_stream(seed=2)[0])
    assert abs(latency_fit(t, q, p).seconds - latency_estimate(t, q, p).seconds) < 2e-3


@pytest.mark.slow
def test_a_stream_without_rests_fits_within_1_5x_of_the_same_arms_rest_and_move_log():
    """Issue 54: the issue's stream without rests (a new command every 30 ms, 100 moves; its message advised
    --mode moves) against the same 100 commands with a rest after each (0.5 s); and a smooth motion (sums of sines)
    with a 35 ms tracker lag against the rest-and-move log of tests/test_streams.py. ||J Jhat - I||_F against the
    UR5e's Jacobian at the start (home) for each."""
    rests = sj.fit(_stream(moves=100)[0])
    stepped = sj.fit(_stream(moves=100, period=0.03)[0])
    moves = sj.fit(_stream(moves=100, period=0.03)[0], mode="moves")
    info = stepped.report.stream
    print(f"\nno rests, 100 commands: windows {_error(stepped):.4f} ({info.line()}), rests {_error(rests):.4f}, "
          f"--mode moves {_error(moves):.4f}")
    assert info.reading == "windows" and abs(info.latency_s - 0.01) < 3e-3
    assert _error(stepped) <= 1.5 * _error(rests)
    assert _error(moves) > 1.3 * _error(stepped)  # what the old hint pointed at
    base = sj.fit(_stream(seed=1)[0])
    smooth = sj.fit(_smooth(latency=0.035, seed=1))
    info = smooth.report.stream
    print(f"smooth motion: windows {_error(smooth):.4f} ({info.line()}), rests {_error(base):.4f}")
    assert info.reading == "windows" and abs(info.latency_s - 0.035) < 3e-3
    assert abs(info.window_move / streams.WINDOW_MOVE - 1) < 0.1
    assert _error(smooth) <= 1.5 * _error(base) and smooth.converged and smooth.warnings == ()
    none = sj.fit(_smooth(latency=0.035, seed=1), latency=None)  # the latency left in: worse
    assert _error(none) > _error(smooth)


@pytest.mark.slow
def test_reduce_stream_by_windows_takes_the_latency_out_and_stays_inside_the_shifted_rows():
    table = _smooth(latency=0.2, seed=3)
    reduced, info = reduce_stream(table, Q_COLS, POS_COLS)
    assert info.reading == "windows" and abs(info.latency_s - 0.2) < 3e-3 and info.latency_estimate_s == info.latency_s
    t = table["t"]
    assert reduced["t"][0] >= t[0] and reduced["t"][-1] <= t[-1] - info.latency_s  # no edge in the held end values
    np.testing.assert_allclose(np.diff(info.intervals, axis=1)[:, 0], info.window_s, rtol=1e-9)
    assert info.segments == reduced["t"].shape[0] - 1 == info.intervals.shape[0]
    # each edge's q and pose are means over the same rows, so (no latency, given) the pose is the model's pose of
    # the mean q: the noise averaged over the ~0.4 w of rows, and the path's curvature over them, second order
    exact = _smooth(latency=0.0, seed=3)
    reduced, info = reduce_stream(exact, Q_COLS, POS_COLS, latency=0.0)
    q = np.stack([reduced[c] for c in Q_COLS], axis=1)
    p = np.stack([reduced[c] for c in POS_COLS], axis=1)
    rows = np.round(2 * streams.WINDOW_EDGE_FRACTION * info.window_s * 100)  # rows averaged per edge
    assert np.abs(p - np.asarray(_poses()(q)[0])).max() < 5 * NOISE / np.sqrt(rows) + 2e-5
    forced, again = reduce_stream(_stream(seed=1)[0], Q_COLS, POS_COLS, mode="windows")  # a log with rests
    assert again.reading == "windows" and again.mode == "windows" and "fewer than two rests" not in again.notes
    with pytest.raises(ValueError, match="column q_9 is missing"):  # forced, as --mode stream: not left as it is
        reduce_stream(exact, [*Q_COLS, "q_9"], POS_COLS, mode="windows")


@pytest.mark.slow
def test_selfid_jax_fit_reads_a_stream_without_rests_and_says_how(tmp_path, capsys):
    import pandas as pd

    path = tmp_path / "norests.csv"
    pd.DataFrame(_stream(moves=100, period=0.03)[0]).to_csv(path, index=False, float_format="%.17g")
    code, info, est = run_fit_command(tmp_path, path)
    assert code == 0 and info["converged"]
    assert any("without rests" in n and "windows of" in n and "tracker latency" in n for n in info["notes"])
    assert "a continuous stream without rests" in capsys.readouterr().out
    code, info, _ = run_fit_command(tmp_path / "w", path, "--mode", "windows")
    assert code == 0 and any("windows of" in n for n in info["notes"])
