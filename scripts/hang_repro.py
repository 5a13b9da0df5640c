"""Reproducer: two sweep parts executing compiled programs from two threads on XLA's CPU backend.

``selfid-jax sweep`` runs a config's parts side by side in threads (``runner.execute._run_parts``), each through
:func:`selfid_jax.runner.sweep.run_chunked`, the next chunk dispatched while the last one is written; two programs
in flight from two threads hung XLA's CPU client for good in 3 of 3 runs of ``valid_region_all.yaml`` (jaxlib
0.10.2, 2 cores), hence the parts' shared execution lock. Each trial here is a child process that runs two such
parts from two threads: by default synthetic ones, both under ``jax.enable_x64`` (as the two hands of
``valid_region_all.yaml``; ``--float32-part``: the first in float32, as an arm), each chunk a ``while_loop`` then a
``scan`` of batched LU solves and matrix products;
with ``--config CONFIG [--set KEY=VALUE ...]`` a real ``selfid-jax sweep`` of that config. A trial is hung when it
has no result after ``--timeout`` seconds and then uses under 0.05 s of CPU in 10 s (or still runs at 3x the
timeout); it is then killed with SIGKILL (SIGTERM did not stop the hung sweep). With ``--stacks DIR`` a hung
trial's stacks are saved first: ``DIR/trial<k>.native.txt`` (``py-spy dump --native`` for the Python threads,
``gdb -batch -ex "thread apply all bt"`` for every thread, XLA's pools included, each if on ``PATH``) and
``DIR/trial<k>.python.txt`` (``faulthandler`` on SIGUSR1). A trial that fails (a non-zero exit) stops the run with
exit status 3 and its stderr: for a crash or an abort, ``faulthandler``'s Python stack of every thread. A child
that finished its parts leaves with ``os._exit(0)``, skipping the interpreter's teardown.

Configurations (one switch at a time, as upstream reports name them for CPU hangs):

  ``--mode none``       no lock, jaxlib's defaults
  ``--mode lock``       a shared ``execution_lock``: one program in flight at a time (the workaround)
  ``--mode no-async``   no lock, ``jax.config.update('jax_cpu_enable_async_dispatch', False)``
  ``--mode no-eigen``   no lock, ``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false``

Usage::

  python scripts/hang_repro.py --mode none --trials 1 --timeout 400 --stacks /tmp/stacks \
      --config configs/valid_region/valid_region_all.yaml     # hung in 1 of 1 (and with each switch), 2026-12-06
  python scripts/hang_repro.py --mode none --trials 5 --timeout 90    # synthetic, ~20 s a trial: has not hung yet

Prints one line per trial (``finished in 4.1 s`` or ``HUNG``) and a summary. Exit status: 0 every trial
finished, 1 at least one hung, 2 a usage error, 3 a trial failed.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

MODES = ("none", "lock", "no-async", "no-eigen")


def child(mode: str, rows: int, chunk: int, steps: int, width: int, out: Path, config: list[str],
          x64: bool = True) -> None:
    """One trial: two ``run_chunked`` sweeps (float32 and float64) in two threads, as ``_run_parts`` runs parts;
    with ``config`` (a sweep config and ``--set`` overrides) ``selfid-jax sweep`` of that config, its lock
    shared by the parts only in mode ``lock``."""
    import faulthandler

    faulthandler.register(signal.SIGUSR1, all_threads=True)
    faulthandler.enable(all_threads=True)  # a trial that aborts or crashes prints every thread's Python stack
    if mode == "no-eigen":
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()
    import threading

    import jax
    import jax.numpy as jnp
    import numpy as np

    import selfid_jax  # noqa: F401 - sets the library's XLA flags before the backend starts
    from selfid_jax.runner.execute import precision, side_by_side
    from selfid_jax.runner.sweep import run_chunked

    if mode == "no-async":
        jax.config.update("jax_cpu_enable_async_dispatch", False)

    if config:
        import contextlib

        from selfid_jax.cli import main as cli_main
        from selfid_jax.runner import execute

        if mode != "lock":  # the parts' shared execution lock, as the sweep had it before 2026-12-05: none
            execute.threading = type("NoLock", (), {"Lock": staticmethod(contextlib.nullcontext)})  # type: ignore
        sys.argv = ["selfid-jax", "sweep", config[0], "--out", str(out / "run"), "--no-progress", *config[1:]]
        code = cli_main(sys.argv[1:])
        if code:
            raise SystemExit(code)
        return

    w = np.sin(np.arange(width * width).reshape(width, width)) / np.sqrt(width)

    def rollout(p):
        """(B,) gains -> (B,) iterations and final norm of ``x <- tanh(g W x + 0.1)`` per row, run as a Newton
        solve is (a ``while_loop`` until the step is under 1e-6 or ``steps`` iterations), then ``steps`` more
        in a ``scan``.

        Under ``vmap`` each iteration is two independent batched LU solves of B (width, width) systems, which XLA
        may run at once on its intra-op thread pool and which jaxlib's LAPACK kernel each splits over that pool and
        waits for (``ParallelBatchMap``), as the hands' batched Newton solves are, and matrix products.
        """

        def one(g):
            a = g * jnp.asarray(w, g.dtype)

            eye = jnp.eye(width, dtype=g.dtype)

            def step(x):  # two independent LU solves (LAPACK getrf through XLA's FFI) and matrix products per row
                b = a @ x + 0.1
                return jnp.tanh(jnp.linalg.solve(a + 2.0 * eye, b) + jnp.linalg.solve(a.T + 3.0 * eye, b))

            def cond(c):
                i, x, dx = c
                return (i < steps) & (dx > 1e-6)

            def body(c):
                i, x, _ = c
                y = step(x)
                return i + 1, y, jnp.max(jnp.abs(y - x))

            i, x, _ = jax.lax.while_loop(cond, body, (0, jnp.ones(width, g.dtype), jnp.asarray(1.0, g.dtype)))
            x, trace = jax.lax.scan(lambda x, _: (step(x), jnp.sum(x * x)), x, None, length=steps)
            return {"iterations": i, "final": jnp.sum(x), "peak": jnp.max(trace)}

        return jax.vmap(one)(p["g"])

    gains = np.linspace(0.5, 2.0, rows)
    lock = threading.Lock() if mode == "lock" else None

    def part(i: int, x64: bool):
        with precision(x64):
            return run_chunked(rollout, {"g": gains}, chunk_size=chunk, out_dir=out / f"part{i}", progress=False,
                               execution_lock=lock)

    tables = side_by_side(part, [x64, True], threads=2)
    assert all(len(t) == rows for t in tables)


def cpu_seconds(pid: int) -> float:
    """User + system CPU time (s) ``pid`` has used so far, all threads (``/proc/PID/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def native_stacks(pid: int) -> str:
    """Every thread's stack of ``pid``: the Python threads' Python and native frames (``py-spy dump --native``)
    and all threads' native frames, XLA's pools included (``gdb -batch -ex "thread apply all bt"``), each
    where the tool is on ``PATH``."""
    text = ""
    for cmd in (["py-spy", "dump", "--native", "--pid", str(pid)],
                ["gdb", "-p", str(pid), "-batch", "-ex", "set sysroot /", "-ex", "thread apply all bt 40"]):
        if shutil.which(cmd[0]) is None:
            text += f"== {cmd[0]}: not on PATH\n"
            continue
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
        text += f"== {' '.join(cmd)}\n{done.stdout}{done.stderr}\n"
    return text


IDLE_WINDOW_S = 10.0
"""A trial past ``--timeout`` counts as hung once it uses under 0.05 s of CPU in this many seconds."""


def idle_window(proc: subprocess.Popen, budget_s: float) -> float | None:
    """Watch a running child in windows of :data:`IDLE_WINDOW_S`: the CPU seconds of the first idle window (hung),
    None if it exits first. A child still computing when ``budget_s`` runs out counts as hung too (its last
    window's CPU returned)."""
    t_end = time.perf_counter() + max(budget_s, IDLE_WINDOW_S)
    while True:
        cpu0 = cpu_seconds(proc.pid)
        try:
            proc.wait(timeout=IDLE_WINDOW_S)
            return None
        except subprocess.TimeoutExpired:
            used = cpu_seconds(proc.pid) - cpu0
        if used < 0.05 or time.perf_counter() > t_end:
            return used


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mode", choices=MODES, default="none")
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds before a trial counts as hung")
    ap.add_argument("--rows", type=int, default=4096, help="rows per part")
    ap.add_argument("--chunk", type=int, default=1024, help="rows per chunk (the shipped configs' 1024)")
    ap.add_argument("--steps", type=int, default=20, help="loop steps per row")
    ap.add_argument("--width", type=int, default=6, help="state size per row")
    ap.add_argument("--float32-part", action="store_true",
                    help="run the first part in float32 (default: both in float64, as the two hands)")
    ap.add_argument("--stacks", type=Path, help="folder for a hung trial's stacks")
    ap.add_argument("--config", nargs="+", default=[], metavar="ARG",
                    help="run a sweep config instead: CONFIG [--set KEY=VALUE ...] (e.g. "
                         "configs/valid_region/valid_region_all.yaml --set n_trials=2)")
    ap.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if min(args.trials, args.rows, args.chunk, args.steps, args.width) < 1 or args.timeout <= 0:
        ap.error("--trials, --rows, --chunk, --steps, --width and --timeout must be positive")
    if args.child is not None:
        child(args.mode, args.rows, args.chunk, args.steps, args.width, args.child, args.config,
              not args.float32_part)
        # The trial's work is done and checked: the child leaves without the interpreter's teardown, which
        # destroys XLA's thread pools with the module state. One no-async child of 47 here aborted with "terminate
        # called without an active exception", where in its run unrecorded (faulthandler was not on); the trials
        # reproduce a hang while programs run, not the process's exit. An abort before this line still fails.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)

    hung = 0
    for k in range(args.trials):
        with tempfile.TemporaryDirectory(prefix="hang_repro_") as tmp:
            cmd = [sys.executable, __file__, "--child", tmp, "--mode", args.mode, "--rows", str(args.rows),
                   "--chunk", str(args.chunk), "--steps", str(args.steps), "--width", str(args.width)]
            cmd += ["--float32-part"] if args.float32_part else []
            cmd += ["--config", *args.config] if args.config else []
            t0 = time.perf_counter()
            proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
            try:
                _, err = proc.communicate(timeout=args.timeout)
            except subprocess.TimeoutExpired:
                cpu = idle_window(proc, 3 * args.timeout - (time.perf_counter() - t0))
                if cpu is None:  # it finished while we watched
                    _, err = proc.communicate()
                else:
                    hung += 1
                    print(f"trial {k}: HUNG (no result after {time.perf_counter() - t0:.0f} s; {cpu:.2f} s of CPU in "
                          f"its last {IDLE_WINDOW_S:.0f} s)", flush=True)
                    if args.stacks is not None:
                        args.stacks.mkdir(parents=True, exist_ok=True)
                        (args.stacks / f"trial{k}.native.txt").write_text(native_stacks(proc.pid))
                        proc.send_signal(signal.SIGUSR1)  # faulthandler: every thread's Python stack to stderr
                        time.sleep(2.0)
                    proc.kill()  # SIGTERM did not stop the hung sweep
                    _, err = proc.communicate()
                    if args.stacks is not None:
                        (args.stacks / f"trial{k}.python.txt").write_text(err)
                    continue
            if proc.returncode != 0:
                sys.stderr.write(err)
                print(f"trial {k}: FAILED (exit {proc.returncode})", flush=True)
                return 3
            print(f"trial {k}: finished in {time.perf_counter() - t0:.1f} s", flush=True)
    print(f"mode {args.mode}: {hung} of {args.trials} hung")
    return 1 if hung else 0


if __name__ == "__main__":
    sys.exit(main())
