"""An online session from Python (selfid_jax.sessions.online_run.run_session) gives the files ``selfid-jax online``
gives on the same config: against the fake arm of helpers_online (a driver class, with a path) and against the
virtual robot served over TCP in this process (a real-time clock); and it refuses bad input before any motion."""

from __future__ import annotations

import json
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest
from helpers_online import write_config  # tests/ is on the path

from selfid_jax.robot import live
from selfid_jax.robot.journal import read_journal
from selfid_jax.sessions.online_config import load_online_config
from selfid_jax.sessions.online_run import run_session

# wall times and where the log is: the only values of two identical sessions that differ
TIMING = {"selfid_s", "follow_s", "step_ms_p50", "step_ms_p99", "log"}


def _files(run: Path) -> set[str]:
    return {p.relative_to(run).as_posix() for p in run.rglob("*") if p.is_file() and p.name != ".lock"}


def _samples(run: Path) -> list[dict]:
    keep = ("k", "accepted", "reason", "dtheta", "V", "delta", "threshold", "converged_at")
    return [{k: r.get(k) for k in keep} for r in read_journal(run / live.LOG_FILE).records if r["e"] == "sample"]


def assert_same_run(cli_run: Path, api_run: Path, api_files: dict[str, Path]) -> None:
    """The two run directories hold the same files with the same results (wall times and the log's path apart)."""
    names = _files(cli_run)
    assert names == _files(api_run), (names, _files(api_run))
    assert set(api_files) | {"online_config.json", live.LOG_FILE} == names  # every file it wrote, by name
    assert (cli_run / "online_config.json").read_bytes() == (api_run / "online_config.json").read_bytes()
    a, b = (json.loads((r / "summary.json").read_text()) for r in (cli_run, api_run))
    assert {k: v for k, v in a.items() if k not in TIMING} == {k: v for k, v in b.items() if k not in TIMING}
    assert _samples(cli_run) == _samples(api_run)
    if (cli_run / "inverse_jacobian.npz").exists():
        with np.load(cli_run / "inverse_jacobian.npz") as za, np.load(api_run / "inverse_jacobian.npz") as zb:
            assert sorted(za.files) == sorted(zb.files)
            for k in za.files:
                if k == "trust":  # the trust record: the same but for where the log is
                    ta, tb = (json.loads(str(z[k])) for z in (za, zb))
                    assert {**ta, "log": None} == {**tb, "log": None}
                else:
                    np.testing.assert_array_equal(za[k], zb[k], err_msg=k)
        ja, jb = (json.loads((r / "inverse_jacobian.json").read_text()) for r in (cli_run, api_run))
        ja["trust"]["log"] = jb["trust"]["log"] = None
        assert {k: v for k, v in ja.items() if k != "log"} == {k: v for k, v in jb.items() if k != "log"}


@pytest.mark.slow  # two sessions and their four figures: 17 s on 2 loaded cores, mostly drawing
def test_run_session_writes_what_the_command_writes(tmp_path, driver_module):
    from selfid_jax.cli import main

    cfg = write_config(tmp_path, """
        robot: {driver: "fake_driver:make", args: {noise: 0.0}}
        selfid: {task: "x,y,z", m_a: 0.02, eps_rel: 0.05, max_samples: 60, seed: 3, settle_s: 0.0, poll_s: 0.001}
        safety: {stale_s: 1.0, max_step: 0.03}
        path: {size: 0.02, tol: 0.001, max_task_step: 0.004, gain: 0.7, steps: 400}
    """)
    (tmp_path / "cli").mkdir()
    assert main(["online", str(cfg), "--out", str(tmp_path / "cli" / "run"), "--quiet"]) == 0
    events: list[dict] = []
    result, files = run_session(load_online_config(cfg), tmp_path / "api" / "run", config_path=cfg,
                                progress=events.append)
    assert result.status == live.Stop.COMPLETED and events[-1]["phase"] == "stop", result.detail
    assert all(f.is_file() for f in files.values()) and "figures/path.png" in files
    assert_same_run(tmp_path / "cli" / "run", tmp_path / "api" / "run", files)
    assert len(driver_module.CREATED) == 2 and all(arm.closed for arm in driver_module.CREATED)
    assert len(driver_module.CREATED[0].moves) == len(driver_module.CREATED[1].moves) > 0


def test_run_session_refuses_bad_input_before_connecting(tmp_path, driver_module):
    from selfid_jax.runner.errors import ConfigError, RunDirError

    cfg_file = write_config(tmp_path, """
        robot: {driver: "fake_driver:make"}
        selfid: {m_a: [0.03, 0.03], settle_s: 0.0, poll_s: 0.001}
    """)
    cfg = load_online_config(cfg_file)
    with pytest.raises(ConfigError, match="needs a path section"):
        run_session(cfg, tmp_path / "a", config_path=cfg_file, estimate=tmp_path / "none.npz")
    (tmp_path / "sweep").mkdir()
    (tmp_path / "sweep" / "config.yaml").write_text("experiment: x\n")
    with pytest.raises(RunDirError, match="sweep's run directory"):
        run_session(cfg, tmp_path / "sweep")
    with pytest.raises(RunDirError, match="no session log"):
        run_session(cfg, tmp_path / "b", resume=True)
    assert driver_module.CREATED == []  # none of these connected
    with pytest.raises(ConfigError, match=r"^config: key 'selfid.m_a': 2 values, but the robot has 3 actuators"):
        run_session(cfg, tmp_path / "c")  # checked once connected, before any motion; named "config" from Python
    assert driver_module.CREATED[-1].moves == [] and driver_module.CREATED[-1].closed
    bad = cfg.model_copy(update={"robot": cfg.robot.model_copy(update={"driver": "no_such_module:make"})})
    with pytest.raises(ConfigError, match="robot.driver: cannot import 'no_such_module:make'"):
        run_session(bad, tmp_path / "d")


def test_connect_takes_plain_values_and_names_the_argument_at_fault(tmp_path, monkeypatch):
    """selfid_jax.robot.drivers.connect: the robot section's values without pydantic; a driver beside the config."""
    import socket
    import sys

    from selfid_jax.robot.drivers import ConnectError, check_robot_args, connect
    from selfid_jax.robot.protocol import Robot

    for kw, match in ((dict(host="h", port=1, driver="a:b"), "not both"), (dict(), "give host and port, or driver"),
                      (dict(host="h"), "needs both host and port"), (dict(host="h", port=1, args={"a": 1}),
                                                                     "args are for a driver class"),
                      (dict(driver="module_only"), "'package.module:Class'")):
        with pytest.raises(ValueError, match=match):
            check_robot_args(**kw)
    with pytest.raises(ConnectError, match="cannot import 'no_such_module_x:make'") as err:
        connect(driver="no_such_module_x:make")
    assert err.value.key == "driver"
    with pytest.raises(ConnectError, match="dict does not implement the Robot protocol") as err:
        connect(driver="builtins:dict")
    assert err.value.key == "driver"
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ConnectError, match=f"cannot connect to 127.0.0.1:{port}") as err:
        connect(host="127.0.0.1", port=port, timeout_s=1.0)
    assert err.value.key == "host"
    monkeypatch.syspath_prepend(str(Path(__file__).parent))  # the driver wraps helpers_online's FakeArm
    (tmp_path / "lab_driver_plain.py").write_text("from helpers_online import FakeArm\n\ndef make(**kw):\n"
                                                  "    return FakeArm(**kw)\n")
    monkeypatch.delitem(sys.modules, "lab_driver_plain", raising=False)
    robot = connect(driver="lab_driver_plain:make", args={"max_step": 0.1}, config_dir=tmp_path)
    assert isinstance(robot, Robot) and float(robot.limits().max_step[0]) == 0.1
    assert str(tmp_path) not in sys.path  # looked there for the import only


@pytest.mark.slow
@pytest.mark.xdist_group("realtime")  # a real-time clock: beside test_robot_sim's, not against it
def test_run_session_against_the_virtual_robot_matches_the_command(tmp_path):
    """Both sessions against one in-process ``robot-sim`` (a UR5e, exact servo, no noise, reset for each client):
    the same draws, samples, estimate and files."""
    from selfid_jax.cli import main
    from selfid_jax.sessions.online_sim import listen, load_sim_config

    sim = tmp_path / "sim.yaml"
    sim.write_text("system: ur5e\nmax_step: 0.05\nreset_on_connect: true\nrealism: {period: 0.005}\nport: 0\n")
    robot, server = listen(load_sim_config(sim))
    robot.start()
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        cfg = tmp_path / "online.yaml"
        cfg.write_text(textwrap.dedent(f"""\
            robot: {{host: 127.0.0.1, port: {server.port}, timeout_s: 10.0}}
            selfid: {{task: "x,y,z", m_a: 0.03, eps_rel: 0.05, max_samples: 60, seed: 1, settle_s: 0.05,
                     poll_s: 0.005}}
            safety: {{stale_s: 2.0}}
            """))
        (tmp_path / "cli").mkdir()
        assert main(["online", str(cfg), "--out", str(tmp_path / "cli" / "run"), "--quiet"]) == 0
        result, files = run_session(load_online_config(cfg), tmp_path / "api" / "run", config_path=cfg)
    finally:
        server.shutdown()
    assert result.status == live.Stop.CONVERGED and result.converged_at >= 3, result.detail
    assert_same_run(tmp_path / "cli" / "run", tmp_path / "api" / "run", files)
