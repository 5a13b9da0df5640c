"""``sj.fit`` and ``selfid-jax fit`` are one fit: same options, same defaults, same estimate, same trust figures.

The command parses flags and prints; the library reads the log (files, bags, units, continuous streams), fits it
and says how far to trust it. Each case runs both on the same log and requires the same estimate to 1e-12, the same
trust figures and warnings, and the same notes on how the log was read: a per-move CSV (the shipped example), a
100 Hz continuous stream of a UR5e (tests/test_streams.py's generator) and a ROS 2 bag (tests/test_bags.py's
writer). On the stream, ``sj.fit`` now gives the settled-sample answer instead of pairing its 2,049 rows.
"""

from __future__ import annotations

import argparse
import inspect
import json

import numpy as np
import pytest
from helpers_logs import _J, ARM, MOVES, A, _stream, run_fit_command, write_bag  # tests/ is on the path

import selfid_jax as sj
from selfid_jax.cli import main
from selfid_jax.commands import fit as fit_command
from selfid_jax.robot.fit_options import FitOptions, ReadOptions
from selfid_jax.robot.log import LogError
from selfid_jax.robot.read import example_log, read_log
from selfid_jax.sessions.fit_run import fit_to_run

SAME = 1e-12  # the command and the function run one program on one table: equal to round-off (in fact bit for bit)


@pytest.fixture
def no_figures(monkeypatch):
    """The run directory without its figure: matplotlib takes ~2 s per file here, and the figure is
    tests/test_fit.py's (the agreement is in the numbers)."""
    from selfid_jax.runner import figures

    monkeypatch.setattr(figures, "save_figure", lambda fig, folder, name: [])


_command = run_fit_command


def _agree(result, info, est):
    """The function's result against the command's files: estimate, trust figures, warnings, notes, counts."""
    np.testing.assert_allclose(result.estimate, est, rtol=0, atol=SAME)
    figures = result.trust.figures()
    for key, value in figures.items():
        np.testing.assert_allclose(info[key], value, rtol=0, atol=SAME, err_msg=key)
    assert info["warnings"] == list(result.warnings)
    assert info["notes"] == list(result.notes) and info["converted_from"] == result.report.units
    assert (info["converged_at"], info["samples"], info["rows"]) == (result.converged_at, result.deltas.shape[0],
                                                                     result.samples.rows)


def _error(result):
    return float(np.linalg.norm(_J() @ result.estimate - np.eye(3)))


def test_options_defaults_and_flags_have_one_source():
    """Every reading option is a keyword of sj.fit and a flag of the command, with ReadOptions' default; the
    estimator's (eps, eps_rel, method / --refine) FitOptions'."""
    params = inspect.signature(sj.fit).parameters
    parser = argparse.ArgumentParser()
    fit_command.add_arguments(parser)
    args = parser.parse_args(["log.csv"])
    defaults = {**ReadOptions()._asdict(), **FitOptions()._asdict()}
    for name, default in defaults.items():
        assert params[name].default == default, name
        assert params[name].kind is inspect.Parameter.KEYWORD_ONLY
    kwargs = fit_command.options(args)
    assert set(kwargs) == set(defaults) and kwargs == defaults  # the flags' defaults, read as sj.fit reads them
    assert ReadOptions().check() == ReadOptions(latency="auto").check()


@pytest.mark.slow
def test_per_move_csv(tmp_path, no_figures):
    """The shipped example (65 rows of a UR5e, one per move, three bad rows): one answer both ways, and through
    fit_to_run (the command's library call), which writes the same files."""
    code, info, est = _command(tmp_path, example_log())
    result = sj.fit(example_log())
    assert code == 0 and result.converged and result.report.stream is not None and not result.report.stream.continuous
    _agree(result, info, est)
    again, files = fit_to_run(example_log(), tmp_path / "api")
    np.testing.assert_array_equal(again.estimate, result.estimate)
    assert json.loads(files["summary.json"].read_text()) == info
    assert sorted(files) == ["estimates.npz", "inverse_jacobian.json", "inverse_jacobian.npz", "summary.json"]


@pytest.fixture(scope="module")
def stream():
    """tests/test_streams.py's log: a UR5e at 100 Hz, 40 moves every 0.5 s, 20 ms servo lag, tracker one frame late,
    0.1 mm noise; 2,050 rows."""
    return _stream(seed=1)


@pytest.mark.slow
def test_a_continuous_stream_gives_the_settled_answer_both_ways(stream, tmp_path, no_figures):
    """The CSV through the command and the table through sj.fit: the same reduced fit (40 settled samples, the
    tracker latency taken out), whose error against the UR5e's Jacobian is the settled rows' (0.053)."""
    import pandas as pd

    table, _ = stream
    path = tmp_path / "stream.csv"
    pd.DataFrame(table).to_csv(path, index=False, float_format="%.17g")  # float64 round-trips exactly
    code, info, est = _command(tmp_path, path)
    result = sj.fit(table)
    _agree(result, info, est)
    assert result.deltas.shape[0] == MOVES and result.report.stream.continuous
    assert abs(result.report.stream.latency_s - 0.01) < 3e-3
    assert any("a continuous stream" in n for n in result.notes) and not result.warnings
    print(f"\n||J Jhat - I||_F on the 100 Hz stream: sj.fit {_error(result):.4f}, selfid-jax fit "
          f"{float(np.linalg.norm(_J() @ est - np.eye(3))):.4f}")
    assert _error(result) < 0.1


@pytest.mark.slow
def test_a_stream_paired_row_by_row_is_what_sj_fit_no_longer_does(stream):
    """mode="moves" reads the stream as sj.fit read every table before: 2,049 pairs of consecutive rows, an error
    ~10x the settled fit's, which the held-out error flags."""
    table, _ = stream
    raw, settled = sj.fit(table, mode="moves"), sj.fit(table)
    before, after = _error(raw), _error(settled)
    print(f"\n||J Jhat - I||_F of sj.fit on the 100 Hz stream: {before:.4f} paired row by row "
          f"({raw.deltas.shape[0]} pairs, held-out error {raw.trust.heldout_error:.2f}, converged at "
          f"{raw.converged_at}) -> {after:.4f} settled ({settled.deltas.shape[0]} samples)")
    assert raw.deltas.shape[0] == 2049 and raw.report.stream.mode == "moves" and not raw.report.stream.continuous
    assert before > 5 * after
    assert any("held-out error" in w for w in raw.warnings)


@pytest.mark.slow
def test_a_ros2_bag(tmp_path, no_figures):
    """A ROS 2 sqlite3 bag of a linear arm (A q + p0): the command's flags and sj.fit's keywords give one fit,
    with the bag's lines among the notes, and A Ĵ = I."""
    bag = write_bag(tmp_path / "rec", "sqlite3")
    topics = dict(joints="/joint_states", tracker="/tracker", joint_names=",".join(ARM))
    code, info, est = _command(tmp_path, bag, "--joints", topics["joints"], "--tracker", topics["tracker"],
                               "--joint-names", topics["joint_names"])
    result = sj.fit(bag, **topics)
    assert code == 0
    _agree(result, info, est)
    assert result.report.bag is not None and result.report.bag.joint_names == ARM
    assert result.notes[0] == f"bag: {bag}: {result.report.bag.rows} rows"
    assert np.linalg.norm(A @ result.estimate - np.eye(3)) < 1e-6
    with pytest.raises(LogError, match="a bag needs --joints TOPIC"):
        sj.fit(bag)


@pytest.mark.slow
def test_bad_options_are_refused_by_keyword_and_flag_before_the_log_is_read(tmp_path, capsys):
    """Each message names the keyword and the flag; the log (which does not exist) is never opened."""
    missing = tmp_path / "missing.csv"
    for kwargs, flags, message in [
        (dict(latency="late"), ["--latency", "late"], "latency (--latency): expected auto, none or a number"),
        (dict(mode="continuous"), ["--mode", "continuous"],
         "mode (--mode): expected one of auto, stream, windows, moves"),
        (dict(settle_speed=-1.0), ["--settle-speed", "-1"], "settle_speed (--settle-speed) must be a positive"),
        (dict(max_gap=0.0), ["--max-gap", "0"], "max_gap (--max-gap) must be positive seconds"),
        (dict(start=2.0, stop=1.0), ["--start", "2", "--stop", "1"], "--stop 1 is before --start 2"),
        (dict(length="km"), ["--length", "km"], "--length: unknown unit 'km'"),
        (dict(eps_rel=-0.1), ["--eps-rel", "-0.1"], "eps_rel"),
        (dict(method="newton"), ["--refine", "newton"], "refine method (method=, --refine)"),
    ]:
        with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
            sj.fit(missing, **kwargs)
        assert main(["fit", str(missing), "--out", str(tmp_path / "o"), *flags]) == 2
        err = capsys.readouterr().err
        assert message in err and "no such file" not in err, err
    assert not (tmp_path / "o").exists()
    samples, _ = read_log(example_log())
    assert sj.fit(samples).estimate.shape == (6, 3)  # Samples read already: fitted as they are
    with pytest.raises(ValueError, match="task= reads a log; these Samples were read already"):
        sj.fit(samples, task="x,y")
    with pytest.raises(TypeError, match="unknown option 'latncy'"):
        read_log(example_log(), latncy=0.01)
    import pandas as pd

    twice = pd.read_csv(example_log()).rename(columns={"q_3": "q_0"})  # a DataFrame may repeat a name; a dict not
    with pytest.raises(LogError, match="<table>: column q_0 appears 2 times"):
        sj.fit(twice)
