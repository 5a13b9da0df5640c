"""The ``selfid-jax online`` command against the fake arm of tests/helpers_online.py (a driver module written
beside the config): its estimate, exit codes, config errors, signals, and where it finds a driver."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from helpers_online import FakeArm, opts, write_config  # tests/ is on the path

from selfid_jax.math import geometry
from selfid_jax.robot import live, options, safety, steps
from selfid_jax.robot.journal import read_journal
from selfid_jax.robot.protocol import Observation, Robot, RobotLimits

# --------------------------------------------------------------------------- the command


@pytest.mark.slow
def test_cli_runs_resumes_and_writes_the_estimate(tmp_path, driver_module, capsys):
    from selfid_jax.cli import main

    cfg = write_config(tmp_path, """
        robot: {driver: "fake_driver:make", args: {noise: 0.0}}
        selfid: {task: "x,y,z", m_a: 0.03, eps_rel: 0.05, max_samples: 40, seed: 3, settle_s: 0.0, poll_s: 0.001}
        safety: {stale_s: 1.0, max_step: 0.1}
    """)
    out = tmp_path / "run"
    assert main(["online", str(cfg), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "converged" and summary["converged_at"] > 2
    assert summary["moves"] == len(driver_module.CREATED[0].moves)
    with np.load(out / "inverse_jacobian.npz") as z:
        assert z["inverse_jacobian"].shape == (3, 3) and int(z["converged_at"]) == summary["converged_at"]
    assert json.loads((out / "inverse_jacobian.json").read_text())["task_axes"] == ["x", "y", "z"]
    assert main(["online", str(cfg), "--out", str(out)]) == 2  # a log is there: --resume or another --out
    assert "--resume" in capsys.readouterr().err
    assert main(["online", str(cfg), "--out", str(out), "--resume"]) == 0
    assert driver_module.CREATED[-1].moves == []  # converged already: no random move on resume
    assert main(["online", str(cfg), "--out", str(out), "--resume", "--set", "selfid.seed=5"]) == 2
    assert "seed" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_driver_exception_exits_3_and_writes_no_estimate(tmp_path, driver_module, capsys):
    """A vendor's ValueError mid-session: exit 3 (the robot's class, not 2), a summary, no estimate file."""
    from selfid_jax.cli import main

    cfg = write_config(tmp_path, """
        robot: {driver: "fake_driver:make", args: {fail_move_at: 3, fail_move_with: ValueError}}
        selfid: {task: "x,y,z", m_a: 0.03, eps_rel: 0.05, max_samples: 40, seed: 3, settle_s: 0.0, poll_s: 0.001}
    """)
    out = tmp_path / "run"
    assert main(["online", str(cfg), "--out", str(out)]) == 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "driver_error" and not summary["converged"] and summary["samples"] == 3
    assert np.shape(summary["estimate_so_far"]) == (3, 3)
    assert not (out / "inverse_jacobian.npz").exists() and not (out / "inverse_jacobian.json").exists()
    assert "not converged: no inverse Jacobian written" in capsys.readouterr().out
    assert driver_module.CREATED[-1].closed


@pytest.mark.parametrize("body, key", [
    ("robot: {driver: 'fake_driver:make'}\nselfid: {m_a: 0.03, bogus: 1}\n", "selfid.bogus"),
    ("robot: {driver: 'fake_driver:make'}\nsafety: {stale_s: -1}\n", "safety.stale_s"),
    ("robot: {driver: 'fake_driver:make', host: h, port: 1}\n", "robot"),
    ("selfid: {m_a: 0.03}\n", "robot"),
    ("robot: {driver: 'fake_driver:make'}\nselfid: {task: 'x,w'}\n", "selfid.task"),
    ("robot: {driver: 'fake_driver:make'}\nselfid: {task: 'x,y'}\npath: {plane: xz}\n", "path.plane"),
    ("robot: {driver: 'fake_driver:make'}\nsafety: {limits_lower: [0, 0]}\n", "safety.limits_lower"),
    ("robot: {driver: 'no_such_module:make'}\n", "robot.driver"),
])
def test_cli_bad_config_exits_2_naming_the_key(tmp_path, driver_module, capsys, body, key):
    from selfid_jax.cli import main

    assert main(["online", str(write_config(tmp_path, body)), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert key in err, err
    assert all(arm.moves == [] for arm in driver_module.CREATED)
    if key != "safety.limits_lower":  # that one needs the robot's n: checked after connecting, before motion
        assert driver_module.CREATED == []


def test_robot_protocol_fake_is_a_robot():
    assert isinstance(FakeArm(), Robot)


def test_example_config_validates():
    from selfid_jax.sessions.online_config import load_online_config, options

    path = Path(__file__).resolve().parents[1] / "configs" / "robot" / "online_ur5e.yaml"
    cfg = load_online_config(path)
    opts = options(cfg)
    assert cfg.robot.host == "127.0.0.1" and opts.path is not None and opts.path.size == 0.02
    assert opts.path.offsets((0, 1, 2)).shape == (10, 3)


@pytest.mark.slow
def test_task_difference_is_the_pose_change_with_rotation():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    r0, w = Rotation.from_rotvec(rng.normal(size=3)), rng.normal(scale=0.1, size=3)
    r1 = Rotation.from_rotvec(w) * r0  # log(R1 R0^T) = w, world frame
    wxyz = [np.roll(r.as_quat(), 1) for r in (r0, r1)]
    p0, p1 = rng.normal(size=3), rng.normal(size=3)
    a = Observation(0.0, np.zeros(1), p0, wxyz[0], 0.0, True)
    b = Observation(1.0, np.zeros(1), p1, -wxyz[1], 1.0, True)  # the quaternion's sign does not matter
    np.testing.assert_allclose(steps.task_difference(b, a, (0, 2, 3, 5)), [*(p1 - p0)[[0, 2]], w[0], w[2]],
                               atol=1e-12)
    with jax.enable_x64(True):
        R1 = np.asarray(geometry.quaternion_to_rotation(np.asarray(-wxyz[1])))
    np.testing.assert_allclose(R1, r1.as_matrix(), atol=1e-12)


def _start_online(console, cfg, out, driver_dir, record: bytes, count: int):
    """``selfid-jax online CFG --out OUT`` in a process of its own (the fake driver importable from ``driver_dir``),
    returned once its session log holds ``count`` lines with ``record`` (or it ended, or 60 s passed)."""
    import os
    import subprocess

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(driver_dir), str(Path(__file__).parent),
                                                        os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([*console, "online", str(cfg), "--out", str(out)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    log = out / live.LOG_FILE
    deadline = time.monotonic() + 60
    while proc.poll() is None and time.monotonic() < deadline and \
            not (log.exists() and log.read_bytes().count(record) >= count):
        time.sleep(0.02)
    return proc, log


@pytest.mark.slow
@pytest.mark.parametrize("signame", ["SIGTERM", "SIGINT"])
def test_cli_sigterm_or_ctrl_c_stops_cleanly_and_resumes(tmp_path, driver_module, console, signame):
    """A first SIGTERM or Ctrl-C stops after the move in flight, closes the robot and keeps the log (not os._exit)."""
    import signal

    cfg = write_config(tmp_path, """
        robot: {driver: "fake_driver:make"}
        selfid: {m_a: 0.03, eps_rel: 1.0e-15, max_samples: 100000, settle_s: 0.01, poll_s: 0.001}
    """)  # a threshold below float64 round-off: never converges, so only the signal ends it
    out = tmp_path / "run"
    proc, log = _start_online(console, cfg, out, tmp_path, b'"e":"sample"', 5)
    proc.send_signal(getattr(signal, signame))
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    last = read_journal(log).records[-1]
    assert last == {"e": "stop", "reason": "interrupted", "detail": "stop requested"}
    assert json.loads((out / "summary.json").read_text())["status"] == "interrupted"
    assert "stopped: interrupted" in stdout
    # the session continues in-process from its log: 3 more random moves, then max_samples
    from selfid_jax.cli import main

    done = sum(1 for r in read_journal(log).records if r["e"] == "sample")
    assert main(["online", str(cfg), "--out", str(out), "--resume", "--set", f"selfid.max_samples={done + 3}"]) == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "max_samples" and summary["replayed"] == summary["samples"] - 3 >= 5
    assert len(driver_module.CREATED[-1].moves) == 3


@pytest.mark.slow
def test_cli_two_sigterms_50_ms_apart_still_leave_a_stop_record(tmp_path, driver_module, console):
    """The second signal ends the process at once (143); the log still ends with a stop record (killed)."""
    import signal

    cfg = write_config(tmp_path, """
        robot: {driver: "fake_driver:make"}
        selfid: {m_a: 0.03, eps_rel: 1.0e-15, max_samples: 100000, settle_s: 0.4, poll_s: 0.001}
    """)  # a long settle: the first signal's stop is seen only after it, so the second one ends the process
    out = tmp_path / "run"
    proc, log = _start_online(console, cfg, out, tmp_path, b'"e":"move"', 2)
    proc.send_signal(signal.SIGTERM)
    time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    assert proc.returncode == 143
    last = read_journal(log).records[-1]
    assert last["e"] == "stop" and last["reason"] == "killed", last


def test_the_step_compiles_once_per_shape(tmp_path, converged_run):
    before = steps._step._cache_size()
    for i, (eps, eps_rel) in enumerate(((0.0, 0.2), (1e-3, 0.0), (0.1, 0.3))):
        result = live.run_online(FakeArm(), opts(eps=eps, eps_rel=eps_rel, max_samples=4), tmp_path / str(i))
        assert result.samples >= 2
    assert steps._step._cache_size() == before  # new thresholds, same (n, m, method, dtype): no retrace


def test_cli_and_api_give_the_same_defaults_for_every_online_option():
    """`selfid-jax online` with an empty config section runs exactly run_online's defaults (one source each)."""
    import inspect

    from selfid_jax.sessions.online_config import OnlineConfig
    from selfid_jax.sessions.online_config import options as cli_options

    cfg = OnlineConfig(robot={"host": "127.0.0.1", "port": 50007}, path={})
    assert cli_options(cfg) == options.OnlineOptions(path=options.FollowOptions())
    for name, p in inspect.signature(safety.envelope).parameters.items():
        if p.default is not inspect.Parameter.empty and name in options.OnlineOptions._fields:
            assert p.default == options.OnlineOptions._field_defaults[name], name


def test_a_position_only_tracker_serves_a_position_task_and_is_refused_for_rotation(tmp_path):
    res = live.run_online(FakeArm(no_quaternion=True), opts(), tmp_path / "p")
    assert res.status == live.Stop.CONVERGED, res.detail
    fake = FakeArm(no_quaternion=True)
    res = live.run_online(fake, opts(task="x,y,rz"), tmp_path / "r")
    assert res.status == live.Stop.ROBOT_ERROR and "quaternion None" in res.detail and fake.moves == []


def test_scalar_limits_broadcast_beside_a_vector_and_are_refused_alone():
    from selfid_jax.robot.protocol import check_limits

    lim = check_limits(RobotLimits(np.full(3, -3.0), 3.0, 0.2))
    assert [x.shape for x in lim] == [(3,)] * 3 and np.all(lim.upper == 3.0) and np.all(lim.max_step == 0.2)
    with pytest.raises(ValueError, match="all single numbers"):
        check_limits(RobotLimits(-3.0, 3.0, 0.2))
    with pytest.raises(ValueError, match="different lengths"):
        check_limits(RobotLimits(np.full(3, -3.0), np.full(2, 3.0), 0.2))


@pytest.mark.slow
@pytest.mark.parametrize("where", ["config_folder", "cwd"])
def test_a_driver_module_beside_the_config_or_in_the_current_directory_is_found(tmp_path, monkeypatch, where):
    from selfid_jax.cli import main

    monkeypatch.syspath_prepend(str(Path(__file__).parent))  # the driver wraps helpers_online's FakeArm
    name = f"lab_driver_{where}"
    folder = tmp_path / "lab"
    folder.mkdir()
    (folder / f"{name}.py").write_text("from helpers_online import FakeArm\n\n"
                                       "def make(**kw):\n    return FakeArm(**kw)\n")
    cfg_dir = folder if where == "config_folder" else tmp_path / "configs"
    cfg_dir.mkdir(exist_ok=True)
    if where == "cwd":
        monkeypatch.chdir(folder)
    cfg = cfg_dir / "online.yaml"
    cfg.write_text(f"robot: {{driver: '{name}:make'}}\n"
                   "selfid: {m_a: 0.03, max_samples: 40, seed: 3, settle_s: 0.0, poll_s: 0.001}\n")
    monkeypatch.delitem(sys.modules, name, raising=False)
    assert main(["online", str(cfg), "--out", str(tmp_path / "run")]) == 0
    assert name not in " ".join(sys.path)  # looked there for the import only
