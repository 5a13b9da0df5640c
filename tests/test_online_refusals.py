"""What the online runner refuses or reports before or as it ends (issue 54): a flagged estimate file given from
Python, a driver whose close() fails while the session stops with an error, and a waypoint beyond the arm's reach.
The fake arm of tests/helpers_online.py; the virtual UR5e for the reach."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from helpers_online import L1, L2, FakeArm, opts, write_config  # tests/ is on the path

from selfid_jax.robot import live, options, quality


def _estimate_file(path, estimate, record):
    np.savez(path, inverse_jacobian=np.asarray(estimate), task_axes=np.array(["x", "y", "z"]),
             trust=np.array(json.dumps(record)))
    return path


# --------------------------------------------------------------------------- a flagged estimate from Python


@pytest.mark.parametrize("flag", ["not converged", "warning"])
def test_run_online_refuses_a_flagged_estimate_file_unless_accepted(tmp_path, converged_run, flag):
    """run_online(estimate=FILE) from Python: a file whose trust record is flagged is refused before any motion,
    naming the file and the flag and how to accept it; accepted, the path is followed with it."""
    _, ref_fake, ref = converged_run
    if flag == "not converged":
        record = quality.trust_record(source="online", log="lab/session.jsonl", converged=False, converged_at=-1,
                                      trust=None)
        named = "it did not converge (Sec. IV-D)"
    else:
        record = {**quality.trust_record(source="fit", log="lab.csv", converged=True, converged_at=12, trust=None),
                  "warnings": ["joint 3 (elbow) never moved"]}
        named = "joint 3 (elbow) never moved"
    est = _estimate_file(tmp_path / "flagged.npz", ref.estimate, record)
    o = opts(path=options.FollowOptions(size=0.01), estimate=str(est))
    fake = FakeArm(q0=ref_fake.q)
    with pytest.raises(ValueError) as err:
        live.run_online(fake, o, tmp_path / "refused")
    text = str(err.value)
    assert text.startswith(f"estimate: {est}: flagged, not followed") and named in text, text
    assert "accept_flagged_estimate=True" in text and "\n" not in text
    assert fake.moves == [] and fake.reads == 0 and fake.closed and not (tmp_path / "refused").exists()
    fake = FakeArm(q0=ref_fake.q)
    res = live.run_online(fake, o, tmp_path / "accepted", accept_flagged_estimate=True)
    assert res.status == live.Stop.COMPLETED and res.given_trust == record, res.detail
    # a file with no flag needs no acceptance
    good = _estimate_file(tmp_path / "good.npz", ref.estimate, {**record, "converged": True, "warnings": []})
    res = live.run_online(FakeArm(q0=ref_fake.q), opts(path=options.FollowOptions(size=0.01), estimate=str(good)),
                          tmp_path / "good")
    assert res.status == live.Stop.COMPLETED, res.detail


@pytest.mark.slow  # the command end to end (config, session, files, figures): ~4 s on 2 loaded cores
def test_the_command_line_follows_a_flagged_estimate_when_told(tmp_path, converged_run, driver_module, capsys):
    """``selfid-jax online --estimate FILE --accept-flagged-estimate``: the acceptance reaches run_online, which
    follows the path with it (the flag is printed); without it, exit 2 and nothing connected."""
    from selfid_jax.cli import main

    _, _, ref = converged_run
    cfg = write_config(tmp_path, """
        robot: {driver: "fake_driver:make"}
        selfid: {task: "x,y,z", settle_s: 0.0, poll_s: 0.001}
        path: {size: 0.01}
    """)
    record = {**quality.trust_record(source="fit", log="lab.csv", converged=True, converged_at=12, trust=None),
              "warnings": ["joint 3 never moved"]}
    est = _estimate_file(tmp_path / "f.npz", ref.estimate, record)
    assert main(["online", str(cfg), "--out", str(tmp_path / "a"), "--estimate", str(est)]) == 2
    assert driver_module.CREATED == []
    capsys.readouterr()
    code = main(["online", str(cfg), "--out", str(tmp_path / "b"), "--estimate", str(est),
                 "--accept-flagged-estimate"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "--accept-flagged-estimate: following with it despite 1 flag(s)" in out
    assert len(driver_module.CREATED) == 1 and driver_module.CREATED[0].moves


# --------------------------------------------------------------------------- a driver whose close() fails


CLOSE_NOTE = "closing the driver afterwards also failed: RuntimeError: fake: the vendor's disconnect failed"
CLOSING_DRIVER = '''
import numpy as np
from helpers_online import FakeArm

class ClosingArm(FakeArm):
    """The fake arm whose close() raises every time (a vendor's disconnect failing on a lost link)."""

    def close(self):
        super().close()
        raise RuntimeError("fake: the vendor's disconnect failed")

def make(**kw):
    return ClosingArm(**{k: np.array(v) if isinstance(v, list) else v for k, v in kw.items()})
'''


@pytest.fixture
def closing_driver(tmp_path, monkeypatch):
    """The driver module ``closing_driver`` (``ClosingArm``, ``make``), written in tmp_path and importable."""
    (tmp_path / "closing_driver.py").write_text(CLOSING_DRIVER)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "closing_driver", raising=False)
    import closing_driver

    yield closing_driver
    sys.modules.pop("closing_driver", None)


def test_a_close_that_fails_does_not_replace_the_stop_or_the_error(tmp_path, closing_driver):
    """The session stops (connection lost) and close() then raises: the stop is the result, the close failure
    its close_error and the log's last record; an error before any motion is raised as it was, the close failure
    a note on it."""
    arm = closing_driver.ClosingArm(fail_move_at=3)
    res = live.run_online(arm, opts(), tmp_path / "a")
    assert res.status == live.Stop.CONNECTION and res.detail == "connection lost: fake: connection reset"
    assert res.close_error == CLOSE_NOTE and arm.closed
    last = [json.loads(line) for line in (tmp_path / "a" / "session.jsonl").read_text().splitlines()][-2:]
    assert [r["e"] for r in last] == ["stop", "close"] and last[1]["error"] == CLOSE_NOTE
    arm = closing_driver.ClosingArm()
    with pytest.raises(ValueError, match=r"^m_a: 0\.5 for actuator 0 exceeds the largest step") as err:
        live.run_online(arm, opts(m_a=0.5), tmp_path / "b")
    assert err.value.__notes__ == [CLOSE_NOTE] and arm.moves == [] and arm.closed
    assert live.run_online(FakeArm(), opts(), tmp_path / "c").close_error is None


@pytest.mark.slow
def test_the_command_line_names_the_stop_then_the_close_failure(tmp_path, closing_driver, capsys):
    """selfid-jax online with that driver, the connection lost at the 4th move: exit 3 and the stop's line, the
    close failure on the line after it and in summary.json, no traceback (it was one, masking the stop)."""
    from selfid_jax.cli import main

    cfg = write_config(tmp_path, """
        robot: {driver: "closing_driver:make", args: {fail_move_at: 3}}
        selfid: {task: "x,y,z", settle_s: 0.0, poll_s: 0.001}
    """)
    code = main(["online", str(cfg), "--out", str(tmp_path / "r"), "--quiet"])
    out, err = capsys.readouterr()
    assert code == 3, (out, err)
    lines = out.splitlines()
    k = lines.index("stopped: connection: connection lost: fake: connection reset")
    assert lines[k + 1] == f"note: {CLOSE_NOTE}"
    assert "Traceback" not in err and "disconnect" not in err
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["close_error"] == CLOSE_NOTE



def test_the_command_line_prints_a_refusal_then_the_close_failure(tmp_path, closing_driver, capsys):
    """A bad m_a refused before any motion, close() then raising: exit 2, the refusal on the error line and the
    close failure on a ``note:`` line after it (it was attached to the error and not printed)."""
    from selfid_jax.cli import main

    cfg = write_config(tmp_path, """
        robot: {driver: "closing_driver:make"}
        selfid: {task: "x,y,z", m_a: 0.5, settle_s: 0.0, poll_s: 0.001}
    """)
    code = main(["online", str(cfg), "--out", str(tmp_path / "r"), "--quiet"])
    _, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if not line.startswith("connecting to ")]
    assert code == 2 and len(lines) == 2, err
    assert lines[0].startswith("selfid-jax online: error: ") and "m_a: 0.5 for actuator 0 exceeds" in lines[0]
    assert lines[1] == f"note: {CLOSE_NOTE}" and "Traceback" not in err

# --------------------------------------------------------------------------- a waypoint beyond the arm's reach


class ReachArm(FakeArm):
    """The fake arm stating its reach: its tip is |L1 e_a + L2 e_b| <= L1 + L2 from the shoulder (0, 0, H), a point
    fixed in the world; ``tool_offset`` 0 (the tip is the tracked point; None: not stated)."""

    def __init__(self, *args, reach=L1 + L2 + 1e-3, tool_offset=0.0, **kw):
        super().__init__(*args, **kw)
        self.reach, self.tool_offset = reach, tool_offset


@pytest.mark.slow
def test_a_waypoint_beyond_the_stated_reach_is_refused_before_any_motion(tmp_path, converged_run):
    """Two tips of the fake arm are at most 2 (L1 + L2) = 1.4 m apart: a waypoint 1.5 m from the start is refused
    before self-ID's first move, naming it, its distance and the bound; a star within reach completes; a driver
    that states no reach is not refused (it moves); one with no tool_offset gets the stated tool margin."""
    _, ref_fake, ref = converged_run
    far = options.FollowOptions(kind="waypoints", waypoints=[[0.01, 0.0, 0.0], [0.0, 1.5, 0.0]])
    arm = ReachArm()
    with pytest.raises(ValueError) as err:
        live.run_online(arm, opts(path=far), tmp_path / "far")
    bound = 2 * (L1 + L2 + 1e-3)
    assert str(err.value) == (
        f"path: waypoint 2 of 2 is 1500 mm from where following starts, out of the arm's reach: no two positions of "
        f"the tracked point are more than {1e3 * bound:.4g} mm apart (2 x (the driver's reach {L1 + L2 + 1e-3:.4g} m "
        "+ its tool offset 0 m)). No move was made: a path within reach")
    assert arm.moves == [] and arm.reads == 0 and arm.closed and not (tmp_path / "far").exists()
    near = options.FollowOptions(size=0.02)
    res = live.run_online(ReachArm(q0=ref_fake.q), opts(path=near, estimate=ref.estimate), tmp_path / "near")
    assert res.status == live.Stop.COMPLETED, res.detail
    unstated = FakeArm(q0=ref_fake.q)  # today's behaviour: no up-front refusal, following starts towards it
    res = live.run_online(unstated, opts(path=far, estimate=ref.estimate), tmp_path / "unstated")
    assert unstated.moves and res.status != live.Stop.COMPLETED
    margin = options.FollowOptions(kind="waypoints", waypoints=[[0.0, 2.1, 0.0]])
    with pytest.raises(ValueError, match=r"more than 2002 mm apart \(2 x \(the driver's reach 0\.701 m \+ 0\.3 m "
                                         r"allowed for a tool: the driver states none\)\)"):
        live.run_online(ReachArm(tool_offset=None), opts(path=margin), tmp_path / "margin")
    assert live.run_online(ReachArm(q0=ref_fake.q, tool_offset=None), opts(path=near, estimate=ref.estimate),
                           tmp_path / "margin_near").status == live.Stop.COMPLETED


@pytest.mark.parametrize("reach", [-1.0, 0.0, float("nan"), "far"])
def test_a_stated_reach_that_is_no_length_is_refused(tmp_path, reach):
    arm = ReachArm(reach=reach)
    with pytest.raises(ValueError, match=rf"^robot reach: the driver states {reach!r}; expected metres"):
        live.run_online(arm, opts(path=options.FollowOptions(size=0.02)), tmp_path / "r")
    assert arm.moves == []


@pytest.mark.slow  # the virtual UR5e's reach from its model (~3 s) and a 50 mm waypoint in real time
def test_virtual_ur5e_refuses_a_waypoint_2_m_away_and_follows_one_within_reach(tmp_path):
    """The virtual UR5e computes its tracked point's reach from its model: at least half the farthest apart two of
    20,000 random flange positions are (an independent sample); a waypoint 2 m away is refused with the arm never
    commanded, a 50 mm one is followed (with the model's pinv Jacobian as the estimate)."""
    import jax

    from selfid_jax.control.realism import Realism
    from selfid_jax.robot.virtual import VirtualRobot, build_system
    from selfid_jax.systems.ur5e import UR5E_HOME

    system, home = build_system("ur5e"), np.array(UR5E_HOME)
    with jax.enable_x64(True):
        flange = jax.jit(jax.vmap(lambda q: system.pose(q)[0]))
        P = np.asarray(flange(np.random.default_rng(5).uniform(-np.pi, np.pi, (20_000, 6))))
        h = 1e-6
        J = np.stack([(np.asarray(system.pose(home + h * e)[0]) - np.asarray(system.pose(home - h * e)[0])) / (2 * h)
                      for e in np.eye(6)], axis=1)  # (3, 6) central differences of the model's flange position
    widest = np.max(np.linalg.norm(P - P[np.argmax(np.linalg.norm(P - P.mean(0), axis=1))], axis=1))

    class Counted(VirtualRobot):
        def move(self, target):
            self.commanded = getattr(self, "commanded", 0) + 1
            super().move(target)

    robot = Counted(system, realism=Realism(period=0.002), q0=home, seed=1)
    reach = robot.reach
    assert reach is not None and widest <= 2 * reach and reach < 1.05  # 1.93 m sampled; UR states 850 mm
    far = options.FollowOptions(kind="waypoints", waypoints=[[0.0, 2.0, 0.0]])
    with pytest.raises(ValueError, match=r"waypoint 1 of 1 is 2000 mm from where following starts, out of the arm's "
                                         r"reach: no two positions of the tracked point are more than 19\d\d mm"):
        live.run_online(robot, opts(path=far, estimate=np.linalg.pinv(J), settle_s=0.01, max_step=0.1), tmp_path / "f")
    assert getattr(robot, "commanded", 0) == 0
    robot = Counted(system, realism=Realism(period=0.002), q0=home, seed=1)
    near = options.FollowOptions(kind="waypoints", waypoints=[[0.05, 0.0, 0.0]])
    res = live.run_online(robot, opts(path=near, estimate=np.linalg.pinv(J), settle_s=0.01, max_step=0.1),
                          tmp_path / "n")
    assert res.status == live.Stop.COMPLETED and robot.commanded == res.follow_steps, res.detail
