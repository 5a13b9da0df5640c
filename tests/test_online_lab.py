"""What a lab sees of an online session and can reuse from it: progress events and lines, the tracking error and
wall times over a resume, the figures and ``selfid-jax plot``; waypoint and CSV paths, an estimate given from an
earlier session, and a driver's model Jacobian as the estimate's reference."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from helpers_online import START, FakeArm, arm_pose, opts, write_config  # tests/ is on the path

from selfid_jax.robot import live, options, session
from selfid_jax.robot.journal import floats, read_journal

# --------------------------------------------------------------------------- a loop a lab can watch (issue 42, item 3)


def test_progress_events_arrive_in_order_and_match_the_log(tmp_path):
    events = []
    fake = FakeArm(dropouts=(6,))
    path = options.FollowOptions(size=0.02, tol=0.001, max_task_step=0.004, gain=0.7, steps=400)
    result = live.run_online(fake, opts(path=path, max_step=0.03, m_a=0.02), tmp_path / "run", progress=events.append)
    assert result.status == live.Stop.COMPLETED, result.detail
    phases = [e["phase"] for e in events]
    n_sel, n_fol = phases.count("selfid"), phases.count("follow")
    assert phases == ["selfid"] * n_sel + ["follow"] * n_fol + ["stop"]  # in order, one stop, last
    sel, fol = events[:n_sel], events[n_sel:-1]
    assert n_sel == result.moves and [e["move"] for e in sel] == list(range(1, n_sel + 1))
    accepted = [e for e in sel if e["accepted"]]
    assert len(accepted) == result.samples and [e["sample"] for e in accepted] == list(range(1, result.samples + 1))
    assert [e["reason"] for e in sel if not e["accepted"]] == ["dropout"] * result.rejected["dropout"]
    logged = [r for r in read_journal(result.log).records if r["e"] == "sample" and r["accepted"]]
    assert [e["delta"] for e in accepted] == [r["delta"] for r in logged]
    assert [e["threshold"] for e in accepted] == [r["threshold"] for r in logged]
    assert accepted[-1]["converged_at"] == result.converged_at and accepted[-2]["converged_at"] < 1
    assert [e["step"] for e in fol] == list(range(1, result.follow_steps + 1))
    assert all(e["waypoints"] == 10 for e in fol) and fol[-1]["waypoint"] == 10
    assert [e["waypoint"] for e in fol] == sorted(e["waypoint"] for e in fol)
    assert events[-1] == {"phase": "stop", "status": "completed", "detail": result.detail}
    # the tracking error and wall times of the result: the events' path distances, each logged
    d = np.array([e["distance"] for e in fol])
    np.testing.assert_array_equal(result.track, d)
    assert [r["distance"] for r in read_journal(result.log).records if r["e"] == "track"] == d.tolist()
    assert 0 < d.max() < 0.01 and result.selfid_s > 0 and result.follow_s > 0


def test_tracking_error_and_wall_times_add_up_over_a_resume(tmp_path, converged_run):
    run, ref_fake, ref = converged_run
    shutil.copytree(run, tmp_path / "r")
    path = options.FollowOptions(size=0.02, tol=0.001, max_task_step=0.004, gain=0.7, steps=400)
    fake = FakeArm(q0=ref_fake.q, max_step=0.05, fail_move_at=5)
    first = live.run_online(fake, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert first.status == live.Stop.CONNECTION and first.track.size == 5
    stops = [r for r in read_journal(first.log).records if r["e"] == "times"]  # one per session, before its stop
    assert len(stops) == 2 and all("selfid_s" in r and "follow_s" in r for r in stops)
    fake = FakeArm(q0=fake.q, max_step=0.05)
    second = live.run_online(fake, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert second.status == live.Stop.COMPLETED, second.detail
    # one distance per move read back: the move the connection lost has none
    assert second.track.size == second.follow_steps - 1 and np.array_equal(second.track[:5], first.track)
    assert second.selfid_s == pytest.approx(sum(r["selfid_s"] for r in stops), rel=0.5)  # no self-ID since
    assert second.follow_s > first.follow_s


def _follow_config(tmp_path):
    return write_config(tmp_path, """
        robot: {driver: "fake_driver:make", args: {noise: 0.0}}
        selfid: {task: "x,y,z", m_a: 0.02, eps_rel: 0.05, max_samples: 60, seed: 3, settle_s: 0.0, poll_s: 0.001}
        safety: {stale_s: 1.0, max_step: 0.03}
        path: {size: 0.02, tol: 0.001, max_task_step: 0.004, gain: 0.7, steps: 400}
    """)


@pytest.mark.slow
def test_cli_prints_progress_and_quiet_prints_only_the_report(tmp_path, driver_module, capsys):
    from selfid_jax.cli import main

    cfg = _follow_config(tmp_path)
    assert main(["online", str(cfg), "--out", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out.splitlines()
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    sel = [ln for ln in out if ln.startswith("self-ID  move")]
    fol = [ln for ln in out if ln.startswith("follow   move")]
    assert len(sel) == summary["moves"] and len(fol) == summary["follow_steps"]  # one line per event, not a tty
    assert "threshold" in sel[0] and sel[-1].endswith("converged") and "waypoint 10/10" in fol[-1]
    assert "path distance" in fol[0] and out.index(sel[-1]) < out.index(fol[0])
    assert any(ln.startswith("stop: completed") for ln in out) and any(ln.startswith("tracking error") for ln in out)
    # the summary: tracking error and wall times
    assert 0 < summary["track_mean_m"] <= summary["track_max_m"] < 0.01
    assert summary["selfid_s"] > 0 and summary["follow_s"] > 0
    assert main(["online", str(cfg), "--out", str(tmp_path / "b"), "--quiet"]) == 0
    quiet = capsys.readouterr().out
    assert "self-ID  move" not in quiet and "follow   move" not in quiet and "stop: completed" not in quiet
    assert "follow: 10/10 waypoints" in quiet and "stopped: completed" in quiet and "tracking error" in quiet


def test_progress_line_on_a_terminal_rewrites_one_line_per_phase():
    import io

    from selfid_jax.sessions.online_progress import ProgressLine

    buf = io.StringIO()
    show = ProgressLine(buf, tty=True)
    show({"phase": "selfid", "move": 1, "sample": 1, "accepted": True, "delta": 1.0, "threshold": 0.1,
          "converged_at": -1})
    show({"phase": "selfid", "move": 2, "sample": 1, "accepted": False, "reason": "dropout"})
    show({"phase": "follow", "step": 1, "waypoint": 0, "waypoints": 10, "distance": 1e-4})
    show({"phase": "stop", "status": "completed", "detail": "done"})
    text = buf.getvalue()
    assert text.count("\n") == 3 and text.count("\r") == 3 and text.endswith("stop: completed: done\n")
    assert "rejected (dropout)" in text and "0.100 mm" in text


@pytest.mark.slow
def test_online_run_writes_figures_and_plot_redraws_them(tmp_path, driver_module, capsys):
    from selfid_jax.cli import main

    run = tmp_path / "run"
    assert main(["online", str(_follow_config(tmp_path)), "--out", str(run), "--quiet"]) == 0
    figures = {f"{name}.{ext}" for name in ("convergence", "path") for ext in ("png", "pdf")}
    assert {p.name for p in (run / "figures").iterdir()} == figures
    assert "figure: " in capsys.readouterr().out
    for name in figures:
        (run / "figures" / name).unlink()
    assert main(["plot", str(run)]) == 0
    assert {p.name for p in (run / "figures").iterdir()} == figures
    assert all((run / "figures" / n).stat().st_size > 1000 for n in figures)
    assert "figure: " in capsys.readouterr().out


@pytest.mark.slow
def test_online_run_without_a_path_has_only_the_convergence_figure(tmp_path, converged_run, capsys):
    from selfid_jax.cli import main

    run, _, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    assert main(["plot", str(tmp_path / "r")]) == 0
    assert sorted(p.name for p in (tmp_path / "r" / "figures").iterdir()) == ["convergence.pdf", "convergence.png"]


@pytest.mark.slow
def test_path_figure_titles_say_tracked_point(converged_run, tmp_path):
    from selfid_jax.sessions import online_figures

    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    path = options.FollowOptions(size=0.02, tol=0.001, max_task_step=0.004, gain=0.7, steps=400)
    live.run_online(FakeArm(q0=ref_fake.q, max_step=0.05), opts(path=path, max_step=0.03), tmp_path / "r",
                    resume=True)
    log = read_journal(tmp_path / "r" / "session.jsonl")
    fig = online_figures.draw_path(log.records, [0, 1, 2], "t")
    titles = " ".join(ax.get_title() for ax in fig.axes)
    assert "tracked point" in titles and "POM" not in titles
    assert online_figures.tracking(log.records)["track_moves"] > 0


def test_plot_refuses_an_unknown_directory_clearly(tmp_path, capsys):
    from selfid_jax.cli import main

    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("x")
    assert main(["plot", str(tmp_path / "junk")]) == 2
    err = capsys.readouterr().err
    assert "not a run directory" in err and "config.yaml" in err and "online" in err and "fit" in err
    assert sorted(p.name for p in (tmp_path / "junk").iterdir()) == ["notes.txt"]  # nothing written there
    assert main(["plot", str(tmp_path / "missing")]) == 2
    assert "not found" in capsys.readouterr().err


# --------------------------------------------------------------------------- paths and estimates a lab can reuse


SQUARE = [[0.01, 0.0, 0.0], [0.01, 0.01, 0.0], [0.0, 0.01, 0.005], [0.0, 0.0, 0.0]]  # m, x y z offsets
FOLLOW = dict(tol=0.001, max_task_step=0.004, gain=0.7, steps=400)


def _write_estimate(path, estimate, axes=("x", "y", "z")):
    np.savez(path, inverse_jacobian=np.asarray(estimate), task_axes=np.array(list(axes)))
    return path


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["waypoints", "csv"])
def test_waypoints_and_csv_paths_are_followed_to_completion(tmp_path, converged_run, kind):
    run, ref_fake, ref = converged_run
    shutil.copytree(run, tmp_path / "r")
    if kind == "waypoints":
        path = options.FollowOptions(kind="waypoints", waypoints=SQUARE, **FOLLOW)
    else:  # columns in another order than the task's: matched by the header's names
        rows = "\n".join(f"{z},{x},{y}" for x, y, z in SQUARE)
        (tmp_path / "square.csv").write_text(f"# a square with a step up, m\nz, x, y\n{rows}\n")
        path = options.FollowOptions(kind="csv", file=str(tmp_path / "square.csv"), **FOLLOW)
    np.testing.assert_array_equal(path.offsets((0, 1, 2)), SQUARE)
    fake = FakeArm(q0=ref_fake.q, max_step=0.05)
    p0, _ = arm_pose(fake.q)
    result = live.run_online(fake, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert result.status == live.Stop.COMPLETED, result.detail
    assert result.waypoints == result.waypoints_total == 4 and result.moves == ref.moves  # no random move
    follow = [r for r in read_journal(tmp_path / "r" / live.LOG_FILE).records if r["e"] == "follow"]
    np.testing.assert_array_equal([floats(o) for o in follow[0]["offsets"]], SQUARE)
    np.testing.assert_allclose(arm_pose(fake.q)[0], p0, atol=0.0015)  # the last waypoint is the start
    # resumed again with the same path: nothing left to do; with another path: refused, naming the path keys
    again = live.run_online(FakeArm(q0=fake.q), opts(path=path), tmp_path / "r", resume=True)
    assert again.status == live.Stop.COMPLETED and again.follow_steps == result.follow_steps
    other = options.FollowOptions(kind="waypoints", waypoints=SQUARE[:3], **FOLLOW)
    with pytest.raises(session.ResumeError, match="path.waypoints"):
        live.run_online(FakeArm(q0=fake.q), opts(path=other), tmp_path / "r", resume=True)


def _bad_csv(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    return dict(kind="csv", file=str(tmp_path / name))


@pytest.mark.parametrize("case, key, match", [
    ("columns", "path.waypoints", "has 2 values; the task has 3 axes"),
    ("nan", "path.waypoints", "not finite"),
    ("empty", "path.waypoints", "at least 1"),
    ("none", "path.waypoints", "needs it"),
    ("missing_file", "path.file", "no such file"),
    ("header", "path.file", "does not name the task axes x,y,z"),
    ("csv_columns", "path.file", "waypoint 2 has 2 values"),
    ("csv_inf", "path.file", "not finite"),
    ("csv_empty", "path.file", "at least 1"),
    ("file_with_star", "path.file", "only used with path.kind 'csv'"),
])
def test_bad_paths_are_refused_before_any_move(tmp_path, case, key, match):
    kw = {"columns": dict(kind="waypoints", waypoints=[[0.01, 0.0, 0.0], [0.01, 0.0]]),
          "nan": dict(kind="waypoints", waypoints=[[0.01, float("nan"), 0.0]]),
          "empty": dict(kind="waypoints", waypoints=[]),
          "none": dict(kind="waypoints"),
          "missing_file": dict(kind="csv", file=str(tmp_path / "nope.csv")),
          "header": _bad_csv(tmp_path, "header.csv", "x,y,rz\n0.01,0,0\n"),
          "csv_columns": _bad_csv(tmp_path, "csv_columns.csv", "x,y,z\n0.01,0,0\n0.01,0\n"),
          "csv_inf": _bad_csv(tmp_path, "csv_inf.csv", "x,y,z\n0.01,inf,0\n"),
          "csv_empty": _bad_csv(tmp_path, "csv_empty.csv", "x,y,z\n"),
          "file_with_star": dict(file="square.csv")}[case]
    fake = FakeArm()
    with pytest.raises(ValueError, match=key) as err:
        live.run_online(fake, opts(path=options.FollowOptions(**kw)), tmp_path / "r")
    assert match in str(err.value)
    assert fake.moves == [] and fake.closed and not (tmp_path / "r").exists()


def test_the_box_check_uses_the_given_waypoints(tmp_path, converged_run):
    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    fake = FakeArm(q0=ref_fake.q)
    p0, _ = arm_pose(fake.q)
    path = options.FollowOptions(kind="waypoints", waypoints=[[0.01, 0.0, 0.0], [0.0, 0.0, 0.03]], **FOLLOW)
    result = live.run_online(fake, opts(path=path, box_low=(p0 - 0.02).tolist(), box_high=(p0 + 0.02).tolist()),
                             tmp_path / "r", resume=True)
    assert result.status == live.Stop.BOX and "waypoint 2 of 2" in result.detail, result.detail
    assert fake.moves == []


def test_a_given_estimate_follows_without_any_random_move_and_resumes(tmp_path, converged_run):
    _, ref_fake, ref = converged_run
    npz = _write_estimate(tmp_path / "inverse_jacobian.npz", ref.estimate)
    path = options.FollowOptions(kind="waypoints", waypoints=SQUARE, **FOLLOW)
    fake = FakeArm(q0=ref_fake.q, max_step=0.05, interrupt_at=3)
    first = live.run_online(fake, opts(path=path, max_step=0.03, estimate=str(npz)), tmp_path / "r")
    assert first.status == live.Stop.INTERRUPTED and first.moves == first.samples == 0
    recs = read_journal(tmp_path / "r" / live.LOG_FILE).records
    est = [r for r in recs if r["e"] == "estimate"]
    assert len(est) == 1 and est[0]["source"] == str(npz)
    assert {r["phase"] for r in recs if r["e"] == "move"} == {"follow"}  # no self-ID move at all
    # resumed without the file: the log's estimate; with it: the same; the path is completed
    fake2 = FakeArm(q0=fake.q, max_step=0.05)
    second = live.run_online(fake2, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert second.status == live.Stop.COMPLETED, second.detail
    assert second.moves == 0 and second.estimate_source == str(npz) and second.waypoints == 4
    np.testing.assert_array_equal(second.estimate, ref.estimate)
    # a different estimate on resume is refused naming both sources
    other = _write_estimate(tmp_path / "other.npz", 2 * ref.estimate)
    with pytest.raises(session.ResumeError, match="other.npz differs"):
        live.run_online(FakeArm(q0=fake2.q), opts(path=path, estimate=str(other)), tmp_path / "r", resume=True)


def test_a_given_estimate_is_refused_on_a_self_identified_log(tmp_path, converged_run):
    run, ref_fake, ref = converged_run
    shutil.copytree(run, tmp_path / "r")
    npz = _write_estimate(tmp_path / "e.npz", ref.estimate)
    fake = FakeArm(q0=ref_fake.q)
    path = options.FollowOptions(kind="waypoints", waypoints=SQUARE, **FOLLOW)
    with pytest.raises(session.ResumeError, match="self-identified"):
        live.run_online(fake, opts(path=path, estimate=str(npz)), tmp_path / "r", resume=True)
    assert fake.moves == []


@pytest.mark.parametrize("shape, axes, task, match", [
    ((3, 2), ("x", "y"), "x,y,z", "task axes are x,y, the task is x,y,z"),
    ((2, 3), ("x", "y", "z"), "x,y,z", r"is \(2, 3\), expected \(3, 3\)"),
    ((3, 3), ("x", "y", "z"), "x,y,rz", "task axes are x,y,z, the task is x,y,rz"),
    (None, None, "x,y,z", "no such file"),
])
def test_an_estimate_of_the_wrong_shape_or_axes_is_refused_before_any_move(tmp_path, shape, axes, task, match):
    npz = tmp_path / "e.npz"
    if shape is not None:
        _write_estimate(npz, np.ones(shape), axes)
    fake = FakeArm()
    path = options.FollowOptions(kind="waypoints", waypoints=[[0.01] * len(task.split(","))], **FOLLOW)
    with pytest.raises(ValueError, match=match) as err:
        live.run_online(fake, opts(task=task, path=path, estimate=str(npz)), tmp_path / "r")
    assert str(npz) in str(err.value)
    assert fake.moves == [] and fake.closed


@pytest.mark.slow
def test_cli_follows_a_csv_beside_the_config_with_the_estimate_of_an_earlier_session(tmp_path, driver_module, capsys):
    from selfid_jax.cli import main

    assert main(["online", str(_follow_config(tmp_path)), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    npz = tmp_path / "a" / "inverse_jacobian.npz"
    rows = "\n".join(",".join(map(str, r)) for r in SQUARE)
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "square.csv").write_text(f"x,y,z\n{rows}\n")
    cfg = write_config(tmp_path / "cfg", """
        robot: {driver: "fake_driver:make", args: {noise: 0.0}}
        selfid: {task: "x,y,z", settle_s: 0.0, poll_s: 0.001}
        safety: {stale_s: 1.0, max_step: 0.03}
        path: {kind: csv, file: square.csv, tol: 0.001, max_task_step: 0.004, gain: 0.7, steps: 400}
    """)
    capsys.readouterr()
    assert main(["online", str(cfg), "--out", str(tmp_path / "b"), "--estimate", str(npz), "--quiet"]) == 0
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["moves"] == 0 and summary["samples"] == 0
    assert summary["waypoints"] == 4 and summary["estimate_source"] == str(npz)
    assert "no self-ID" in capsys.readouterr().out
    assert not (tmp_path / "b" / "inverse_jacobian.npz").exists()  # not this session's result
    # the self-identified run resumed with an estimate: refused (exit 2), naming the cause
    assert main(["online", str(_follow_config(tmp_path)), "--out", str(tmp_path / "a"), "--resume",
                 "--estimate", str(npz)]) == 2
    assert "self-identified" in capsys.readouterr().err
    # wrong axes in the file: exit 2 naming the file, no move
    bad = _write_estimate(tmp_path / "xy.npz", np.ones((3, 2)), ("x", "y"))
    assert main(["online", str(cfg), "--out", str(tmp_path / "c"), "--estimate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "xy.npz" in err and "task axes" in err
    assert all(arm.moves == [] for arm in driver_module.CREATED[2:])
    # a header that does not match the task: exit 2 naming path.file, before connecting
    (tmp_path / "cfg" / "square.csv").write_text(f"x,y\n{rows}\n")
    n_arms = len(driver_module.CREATED)
    assert main(["online", str(cfg), "--out", str(tmp_path / "d"), "--estimate", str(npz)]) == 2
    assert "path.file" in capsys.readouterr().err and len(driver_module.CREATED) == n_arms


class ModelArm(FakeArm):
    """FakeArm with a model: jacobian(q) by central differences of arm_pose (position rows; rotation rows zero,
    the task has none), or a broken one."""

    def __init__(self, *a, broken=False, **kw):
        super().__init__(*a, **kw)
        self.broken, self.asked = broken, []

    def jacobian(self, q):
        self.asked.append(np.array(q))
        if self.broken:
            return np.zeros((3, 3))
        h = 1e-6
        cols = [(arm_pose(q + h * e)[0] - arm_pose(q - h * e)[0]) / (2 * h) for e in np.eye(3)]
        return np.vstack([np.array(cols).T, np.zeros((3, 3))])


@pytest.mark.slow
def test_a_driver_model_jacobian_is_the_estimate_s_reference(tmp_path):
    """jacobian() is asked once, at the first reading; summary-level reference_error equals numpy's ||J Ĵ - I||_F
    (a few % here: the estimate averages J over the moves around the start) and figures/estimate is drawn from
    the log; a malformed one stops before any move; a driver without one has no reference."""
    from selfid_jax.sessions import online_figures

    arm = ModelArm()
    res = live.run_online(arm, opts(), tmp_path / "a")
    assert res.converged and len(arm.asked) == 1 and np.array_equal(arm.asked[0], START)
    h = 1e-6
    J = np.array([(arm_pose(START + h * e)[0] - arm_pose(START - h * e)[0]) / (2 * h) for e in np.eye(3)]).T
    want = np.linalg.norm(J @ res.estimate - np.eye(3))
    assert res.reference_error == pytest.approx(want, rel=1e-6) and 0 < want < 0.15
    paths = online_figures.write_figures(tmp_path / "a")
    assert any(p.name == "estimate.png" for p in paths)
    resumed = live.run_online(ModelArm(q0=arm.q), opts(), tmp_path / "a", resume=True)
    assert resumed.reference_error == pytest.approx(want, rel=1e-6)  # from the log
    bad = ModelArm(broken=True)
    res = live.run_online(bad, opts(), tmp_path / "b")
    assert res.status == live.Stop.DRIVER_ERROR and "jacobian() raised ValueError" in res.detail, res.detail
    assert bad.moves == []
    assert live.run_online(FakeArm(), opts(), tmp_path / "c").reference_error is None
