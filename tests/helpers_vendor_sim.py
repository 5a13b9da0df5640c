"""What the vendors' simulators in the tests share (tests/franka_reference.py for franky-sim, tests/trossen_reference.py
for trossen-arm-sim): a simulator started as a subprocess and ended by its process group, its port, and a session's
estimate against MuJoCo's Jacobian of the simulator's own model at the session's first joint reading."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

AXES = ("x", "y", "z", "rx", "ry", "rz")


def port_open(port: int, host: str = "127.0.0.1") -> bool:
    """Whether something accepts TCP connections at ``host:port`` (within 0.2 s)."""
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex((host, port)) == 0


@contextlib.contextmanager
def simulator(command: Sequence[str], port: int, log: Path, timeout_s: float = 30.0) -> Iterator[subprocess.Popen]:
    """``command`` (its first word found on PATH) in a process group of its own for the block, its output appended to
    ``log``, ended by :func:`kill` after; RuntimeError if ``port`` is taken before it starts or does not open within
    ``timeout_s``."""
    name = command[0]
    if port_open(port):
        raise RuntimeError(f"127.0.0.1:{port} is already in use: another {name} or the arm's own server is running")
    exe = shutil.which(name)
    if exe is None:
        raise RuntimeError(f"{name} is not on PATH")
    with open(log, "ab") as out:
        proc = subprocess.Popen([exe, *command[1:]], stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + timeout_s
        while not port_open(port):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{name} did not listen on {port} (exit {proc.poll()}); see {log}")
            time.sleep(0.05)
        yield proc
    finally:
        kill(proc, port)


def kill(proc: subprocess.Popen, port: int) -> None:
    """End a simulator by its PID's process group (SIGKILL: what a crash or a power cut looks like to the arm's
    client), then wait up to 10 s for ``port`` to close."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    deadline = time.monotonic() + 10
    while port_open(port) and time.monotonic() < deadline:
        time.sleep(0.05)


def session_error(run_dir: Path, jacobian: Callable[[np.ndarray, list[int]], np.ndarray]) -> tuple[float, np.ndarray]:
    """``(||J Ĵ - I||_F, q0)`` of a run directory's estimate against ``jacobian(q0, rows)`` (the reference's, rows
    the estimate's task axes out of :data:`AXES`) at the session's first joint reading ``q0``."""
    with open(run_dir / "session.jsonl") as lines:
        first = next(json.loads(line) for line in lines if '"e":"obs"' in line)
    q0 = np.array(first["q"])
    est = np.load(run_dir / "inverse_jacobian.npz")
    J = jacobian(q0, [AXES.index(str(a)) for a in est["task_axes"]])
    return float(np.linalg.norm(J @ est["inverse_jacobian"] - np.eye(J.shape[0]))), q0


# --------------------------------------------------------------------------- the end-to-end sessions' steps


def summary(out: Path) -> dict:
    """A run directory's ``summary.json``."""
    return json.loads((out / "summary.json").read_text())


def journal(out: Path) -> list[dict]:
    """A run directory's session log, one dict a line."""
    return [json.loads(line) for line in (out / "session.jsonl").read_text().splitlines()]


def converged_then_followed(out: Path, session_error: Callable[[Path], tuple[float, np.ndarray]],
                            max_error: float, reference_tol: float = 0.01,
                            resumed: bool = False) -> tuple[dict, np.ndarray]:
    """Check a session that converged and completed its path: ``||J Ĵ - I||_F <= max_error`` against the
    reference (and the driver's own ``reference_error`` within ``reference_tol`` of it); for one that was not
    ``resumed`` (whose log holds no move cut short by a lost link), no random move after convergence and the path
    within 1 cm. ``(summary, q0)``."""
    s = summary(out)
    assert s["status"] == "completed" and s["converged"] and s["waypoints"] == s["waypoints_total"], s
    error, q0 = session_error(out)
    assert error <= max_error, error
    assert abs(s["reference_error"] - error) < reference_tol  # the driver's own model agrees with MuJoCo's
    if not resumed:
        moves = [e for e in journal(out) if e["e"] == "move"]
        assert all(e["phase"] == "follow" for e in moves[s["samples"]:])  # no random move after convergence
        assert s["track_max_m"] < 0.01
    return s, q0


def killed_during_selfid(run: Callable[[], int], sim: subprocess.Popen, port: int, out: Path, lost: str,
                         after_samples: int = 4) -> None:
    """``run()`` (a session into ``out``) with the simulator ``sim`` killed once ``after_samples`` samples are
    logged: it exits 3 (the robot failed), its summary a ``connection`` stop whose detail names ``lost`` (the
    vendor's lost link), the journal ending with that stop and keeping the samples."""
    log = out / "session.jsonl"

    def killer() -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if log.exists() and log.read_text().count('"e":"sample"') >= after_samples:
                kill(sim, port)
                return
            time.sleep(0.02)

    import threading

    thread = threading.Thread(target=killer)
    thread.start()
    code = run()
    thread.join()
    assert code == 3, code  # the robot or its driver failed
    s = summary(out)
    assert s["status"] == "connection" and lost in s["detail"], s
    stops = [e for e in journal(out) if e["e"] == "stop"]
    assert stops and stops[-1]["reason"] == "connection"
    assert sum(1 for e in journal(out) if e["e"] == "sample") >= after_samples
