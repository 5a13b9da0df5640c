"""Trust that travels with the estimate (issue 54, item 4): the estimate files of ``selfid-jax fit`` and ``selfid-jax
online`` carry their trust figures and report; ``fit --strict`` that fails writes no estimate; ``online --estimate``
shows a file's figures and refuses a flagged one unless told; a session with a given estimate reports the file's
convergence and the reference error; warnings name actuators by the log's names and blame the right one."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers_logs import run_fit_command
from helpers_online import FakeArm, arm_pose, opts, write_config  # tests/ is on the path
from test_fit_api import no_figures  # noqa: F401 - the fixture: the run directory without its figure

import selfid_jax as sj
from selfid_jax.robot import live, options
from selfid_jax.robot.journal import read_journal
from selfid_jax.robot.quality import MIN_MOTION_RATIO, held_out, read_trust, record_flags, trust
from selfid_jax.runner.errors import ConfigError
from selfid_jax.sessions.online_run import check_estimate

UR = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
# a linear 6-joint arm p = p0 + A q [m, rad]: wrist_1 and wrist_2 move the point least, as on a UR5e
A = np.array([[0.40, 0.30, 0.10, 0.02, 0.015, 0.01],
              [-0.20, 0.35, 0.25, 0.015, 0.02, 0.01],
              [0.10, -0.15, 0.30, 0.01, 0.01, 0.02]])
P0 = np.array([0.4, 0.1, 0.3])


def _log(still_jitter=None, moves=40, seed=0):
    """A rest-to-rest time series of the linear arm, one row per move: 6 joints stepping ``uniform(+-0.03)`` rad
    and 0.02 mm tracker noise; ``still_jitter``: wrist_3 never moves, its encoder reading only this jitter [rad]."""
    rng = np.random.default_rng(seed)
    steps = rng.uniform(-0.03, 0.03, (moves, 6))
    q = np.vstack([np.zeros(6), np.cumsum(steps, axis=0)])
    if still_jitter is not None:
        q[:, 5] = still_jitter * rng.normal(size=moves + 1)
    p = P0 + q @ A.T + 2e-5 * rng.normal(size=(moves + 1, 3))
    return {"t": 0.5 * np.arange(moves + 1), **{name: q[:, i] for i, name in enumerate(UR)},
            **{c: p[:, i] for i, c in enumerate(("p_x", "p_y", "p_z"))}}


@pytest.mark.slow
@pytest.mark.parametrize("jitter", [0.0, 1e-8, 3e-6])
def test_a_joint_that_never_moved_is_named_and_no_moved_joint_is_blamed(jitter):
    """wrist_3 held (exactly, or with encoder jitter): its fitted effect is noise over noise (up to 1e4 times the
    others'), which made a moved joint look weak (the issue's wrist_1). Now wrist_3 alone is named, by the log's name,
    as not moved, against its largest step computed here."""
    table = _log(still_jitter=jitter)
    result = sj.fit(table, joint_names=",".join(UR))
    step = np.abs(np.diff(table["wrist_3_joint"])).max()
    most = max(np.abs(np.diff(table[name])).max() for name in UR)
    assert step < MIN_MOTION_RATIO * most
    assert result.trust.actuators == tuple(f"{name} (q_{i})" for i, name in enumerate(UR))
    assert len(result.warnings) == 1, result.warnings
    assert result.warnings[0].startswith("wrist_3_joint (q_5) did not move in the samples")
    np.testing.assert_allclose(result.trust.actuator_motion[5], step, rtol=1e-9, atol=1e-300)
    assert not any(name in w for w in result.warnings for name in UR[:5])


def test_a_weak_but_moved_joint_is_still_named_among_moved_ones():
    """The effect ratio is over the moved actuators: a moved joint that barely moves the point is still flagged, by
    its label, and the ratio is the one computed here from the least-squares map."""
    rng = np.random.default_rng(1)
    D = rng.uniform(-0.03, 0.03, (30, 3))
    F = np.array([[0.3, 0.1, 1e-5], [0.1, 0.3, 0.0], [0.0, 0.1, 0.0]])  # joint c acts 1e-4 of the strongest
    V = D @ F.T
    q = held_out(D, V, 0.03)
    t = trust(q, np.linalg.pinv(F + np.diag([0, 0, 1e-9])), 0, 30, names=("a", "b", "c"))
    expected = np.linalg.norm(F, axis=0)[2] / np.linalg.norm(F, axis=0).max()
    assert [w for w in t.warnings if "moves the tracked point" in w] == [
        f"c moves the tracked point {expected:.2g} of the strongest moved actuator (< 0.001): its column of the "
        "estimate is noise"]


# --------------------------------------------------------------------------- fit: the file, --strict


@pytest.fixture
def flagged_log(tmp_path):
    """A CSV whose fit converges with one trust warning (wrist_3 never moved)."""
    import pandas as pd

    path = tmp_path / "held.csv"
    pd.DataFrame(_log(still_jitter=0.0)).to_csv(path, index=False, float_format="%.17g")
    return path


@pytest.mark.slow
@pytest.mark.usefixtures("no_figures")
def test_the_estimate_file_carries_the_trust_figures_and_report(tmp_path, flagged_log):
    code, info, est = run_fit_command(tmp_path, flagged_log, "--joint-names", ",".join(UR))
    assert code == 0 and info["converged"]
    with np.load(tmp_path / "run" / "inverse_jacobian.npz") as z:
        record = read_trust(z)
    assert record == json.loads((tmp_path / "run" / "inverse_jacobian.json").read_text())["trust"]
    for key in ("heldout_error", "condition", "actuator_effect", "refused_fraction", "warnings", "converged_at",
                "actuators"):
        assert record[key] == info[key], key
    assert record["source"] == "fit" and record["log"] == str(flagged_log) and record["reference_error"] is None
    assert record["report"][0].startswith(f"{flagged_log}: 41 rows")
    assert any(line.startswith("joints shoulder_pan_joint") for line in record["report"])  # how the log was read
    assert record_flags(record) == info["warnings"] and len(info["warnings"]) == 1


@pytest.mark.slow
@pytest.mark.usefixtures("no_figures")
def test_a_failed_strict_fit_writes_no_estimate(tmp_path, flagged_log, capsys):
    """Before: exit 1 with inverse_jacobian.npz on disk. Now none, and the one an earlier fit left there goes too
    (the summary beside it is this fit's); the summary says why and holds the estimate."""
    names = ("--joint-names", ",".join(UR))
    assert run_fit_command(tmp_path, flagged_log, *names)[0] == 0
    assert (tmp_path / "run" / "inverse_jacobian.npz").is_file()
    code, info, est = run_fit_command(tmp_path, flagged_log, *names, "--strict")
    assert code == 1 and info["converged"]
    assert not (tmp_path / "run" / "inverse_jacobian.npz").exists()
    assert not (tmp_path / "run" / "inverse_jacobian.json").exists()
    assert info["estimate_withheld"] == "--strict and 1 trust warning(s)"
    np.testing.assert_array_equal(np.asarray(info["estimate_so_far"]), sj.fit(flagged_log, joint_names=UR).estimate)
    assert "--strict: 1 trust warning(s): no inverse Jacobian written" in capsys.readouterr().out


# --------------------------------------------------------------------------- online --estimate


def _estimate_file(path, estimate, record=None, axes=("x", "y", "z")):
    extra = {} if record is None else {"trust": np.array(json.dumps(record))}
    np.savez(path, inverse_jacobian=np.asarray(estimate), task_axes=np.array(list(axes)),
             converged_at=np.int64(12), **extra)
    return path


RECORD = {"source": "fit", "log": "lab.csv", "converged": True, "converged_at": 12, "heldout_error": 0.03,
          "condition": 4.0, "warnings": [], "reference_error": None, "report": []}


@pytest.mark.parametrize("content, match", [
    ("hello\n", "not an .npz file"),                     # the text file: numpy's allow_pickle before
    (b"\x93NUMPY\x01\x00", "not an .npz file"),          # a .npy array
    (b"PK\x03\x04garbage", "cannot be read as an .npz"),  # a broken zip
])
def test_a_file_that_is_no_estimate_gets_one_line_naming_it(tmp_path, content, match):
    path = tmp_path / "notes.txt"
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    with pytest.raises(ConfigError) as err:
        check_estimate(path, "x,y,z")
    text = str(err.value)
    assert text.startswith(f"--estimate {path}: ") and match in text and "\n" not in text
    assert "expected the inverse_jacobian.npz that selfid-jax fit or selfid-jax online writes" in text
    assert "pickle" not in text


def test_a_flagged_estimate_is_refused_unless_accepted_and_an_old_one_says_it_carries_none(tmp_path):
    est = np.eye(3)
    good = _estimate_file(tmp_path / "good.npz", est, RECORD)
    lines = check_estimate(good, "x,y,z")
    assert lines == [f"estimate {good} (fit of lab.csv): converged at sample 12, held-out error 0.03, condition "
                     "number 4"]
    flagged = _estimate_file(tmp_path / "flagged.npz", est, {**RECORD, "warnings": ["wrist_3 did not move"]})
    with pytest.raises(ConfigError, match="flagged, not followed .*: wrist_3 did not move.*--accept-flagged-estimate"):
        check_estimate(flagged, "x,y,z")
    assert check_estimate(flagged, "x,y,z", accept_flagged=True)[1:] == [
        "  warning: wrist_3 did not move", "  --accept-flagged-estimate: following with it despite 1 flag(s)"]
    unconverged = _estimate_file(tmp_path / "unconverged.npz", est, {**RECORD, "converged": False})
    with pytest.raises(ConfigError, match="it did not converge"):
        check_estimate(unconverged, "x,y,z")
    old = _estimate_file(tmp_path / "old.npz", est)
    assert check_estimate(old, "x,y,z") == [f"estimate {old}: carries no trust figures (written before estimate "
                                            "files carried them); followed unchecked"]
    with pytest.raises(ConfigError, match="task axes are x,y,z, the task is x,y"):
        check_estimate(old, "x,y")


def test_cli_refuses_a_text_estimate_and_a_flagged_one_before_connecting(tmp_path, driver_module, capsys):
    from selfid_jax.cli import main

    cfg = write_config(tmp_path, """
        robot: {driver: "fake_driver:make"}
        selfid: {task: "x,y,z", settle_s: 0.0, poll_s: 0.001}
        path: {size: 0.01}
    """)
    (tmp_path / "notes.txt").write_text("not an estimate\n")
    assert main(["online", str(cfg), "--out", str(tmp_path / "a"), "--estimate", str(tmp_path / "notes.txt")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith(f"--estimate {tmp_path / 'notes.txt'}: not an .npz file (expected the inverse_jacobian.npz "
                        "that selfid-jax fit or selfid-jax online writes)"), err
    assert str(cfg) not in err and "pickle" not in err
    flagged = _estimate_file(tmp_path / "f.npz", np.eye(3), {**RECORD, "warnings": ["q_2 did not move"]})
    assert main(["online", str(cfg), "--out", str(tmp_path / "b"), "--estimate", str(flagged)]) == 2
    assert "--accept-flagged-estimate" in capsys.readouterr().err
    assert driver_module.CREATED == []  # nothing connected, nothing moved


# --------------------------------------------------------------------------- a session with a given estimate


class ModelArm(FakeArm):
    """The fake arm with a driver's model: its position Jacobian by central differences (6, 3), rotation rows 0."""

    def jacobian(self, q):
        J = np.zeros((6, 3))
        for i in range(3):
            e = np.zeros(3)
            e[i] = 1e-6
            J[:3, i] = (arm_pose(q + e)[0] - arm_pose(q - e)[0]) / 2e-6
        return J


SQUARE = [[0.01, 0.0, 0.0], [0.01, 0.01, 0.0], [0.0, 0.01, 0.005], [0.0, 0.0, 0.0]]


@pytest.mark.slow  # two sessions and their figures: ~5 s
def test_a_resumed_session_with_a_given_estimate_reports_convergence_and_the_reference_error(tmp_path):
    """Before: converged false, a null reference_error and an empty convergence figure. Now the file's convergence,
    ||J Ĵ - I||_F against the model where following started (checked here from the logged start), no convergence
    figure, the estimate figure, and the path figure marks where the resumed session took up following."""
    from matplotlib.figure import Figure

    from selfid_jax.sessions import online_figures
    from selfid_jax.sessions.online_config import load_online_config
    from selfid_jax.sessions.online_run import summary

    first = ModelArm(max_step=0.05)
    start = first.q.copy()
    estimate = np.linalg.inv(first.jacobian(start)[:3]) @ np.diag([1.02, 0.99, 1.01])  # 2 % off the model
    npz = _estimate_file(tmp_path / "e.npz", estimate, RECORD)
    path = options.FollowOptions(kind="waypoints", waypoints=SQUARE, tol=0.001, max_task_step=0.004, gain=0.7,
                                 steps=400)
    run = tmp_path / "r"
    first.interrupt_at = 4
    a = live.run_online(first, opts(path=path, max_step=0.03, estimate=str(npz)), run)
    assert a.status == live.Stop.INTERRUPTED and a.moves == 0
    b = live.run_online(ModelArm(q0=first.q, max_step=0.05), opts(path=path, max_step=0.03), run, resume=True)
    assert b.status == live.Stop.COMPLETED, b.detail
    J = ModelArm().jacobian(start)[:3]
    expected = float(np.linalg.norm(J @ estimate - np.eye(3)))
    assert b.reference_error == pytest.approx(expected, rel=1e-9)
    assert b.given_trust == RECORD and b.given_converged_at == 12
    cfg = write_config(tmp_path, """
        robot: {driver: "fake_driver:make"}
        selfid: {task: "x,y,z", eps_rel: 0.05}
    """)
    info = summary(b, load_online_config(cfg))
    assert info["converged"] is True and info["converged_at"] == 12 and info["reference_at"] == "follow"
    assert info["heldout_error"] == 0.03 and info["estimate_trust"] == RECORD
    files = online_figures.write_figures(run)
    assert sorted(f.name for f in files) == ["estimate.pdf", "estimate.png", "path.pdf", "path.png"]
    records = read_journal(run / live.LOG_FILE).records
    follow = next(i for i, r in enumerate(records) if r["e"] == "follow")
    resume = next(i for i, r in enumerate(records) if r["e"] == "session" and r["resume"])
    before = sum(1 for r in records[follow:resume] if r["e"] == "track")
    fig = online_figures.draw_path(records, (0, 1, 2), "t")
    assert isinstance(fig, Figure)
    marks = [a for ax in fig.axes for a in ax.get_children() if getattr(a, "get_gid", lambda: None)() == "resumed"]
    lines = [m for m in marks if m.get_xdata()[0] == before + 0.5]
    assert len(marks) == 2 and len(lines) == 1  # the tracked point where it resumed, and the move count

