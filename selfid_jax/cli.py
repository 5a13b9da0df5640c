"""``selfid-jax`` command line: ``sweep``, ``plot``, ``demo``.

    selfid-jax sweep CONFIG [--set key.sub=value ...] [--out DIR] [--fresh] [--no-progress]
    selfid-jax plot RUN_DIR
    selfid-jax demo [--out DIR]

``sweep`` validates the config before any compute, creates the run directory
(default ``runs/<config stem>``), runs the experiment registered under the
config's ``experiment:`` name (``experiments/<name>.py`` registers itself with
``selfid_jax.sweep.register_experiment``), then draws the figures from the
saved results, exactly as ``plot`` would. Interrupt it (Ctrl-C or ``kill``) and
run the same command again to resume; ``--fresh`` starts over.

Several hosts: run the same ``sweep`` command on every host with
``--distributed`` (SLURM/Open MPI/Kubernetes auto-detection) or with
``--coordinator HOST:PORT --num-processes P --process-id I``; see
``selfid_jax.sweep`` for how the batch is sharded and who writes what.

Bad input (missing file, invalid config, run directory of another config) is
reported on stderr with exit code 2 and no traceback; an interrupted sweep
exits with 130 (Ctrl-C) or 143 (SIGTERM). A first SIGTERM lets the chunk in
flight finish and be saved; ``kill -9`` loses at most that chunk.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path

__all__ = ["main"]

_PROG = "selfid-jax"


class _UsageError(Exception):
    """Bad input the user can fix; printed without traceback, exit code 2."""


class _Terminated(Exception):
    """A second SIGTERM: stop now, between Python bytecodes."""


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=_PROG, description="Self-identified inverse Jacobians: sweeps and figures.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("sweep", help="run an experiment sweep from a YAML config (resumable)")
    s.add_argument("config", type=Path, help="YAML config with a top-level 'experiment:' key")
    s.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a config value by dotted key, e.g. --set controller.tol=1e-3 (repeatable)",
    )
    s.add_argument("--out", type=Path, default=None, help="run directory (default: runs/<config stem>)")
    s.add_argument("--fresh", action="store_true", help="discard earlier results in the run directory")
    s.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    g = s.add_argument_group(
        "several hosts (jax.distributed)",
        "run the same command on every host; only process 0 writes the run directory",
    )
    g.add_argument("--distributed", action="store_true",
                   help="call jax.distributed.initialize() (auto-detects SLURM, Open MPI, Kubernetes)")
    g.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0 (implies --distributed)")
    g.add_argument("--num-processes", type=int, metavar="P", help="number of processes (implies --distributed)")
    g.add_argument("--process-id", type=int, metavar="I", help="this process, 0..P-1 (implies --distributed)")

    pl = sub.add_parser("plot", help="redraw every figure of a run from its saved results")
    pl.add_argument("run_dir", type=Path)

    d = sub.add_parser("demo", help="run the small demo (experiments/demo.py)")
    d.add_argument("--out", type=Path, default=Path("runs/demo"), help="output directory (default: runs/demo)")
    return p


@contextlib.contextmanager
def _graceful_sigterm() -> Iterator[list[int]]:
    """First SIGTERM: let the sweep save the chunk in flight and stop; second: stop at once.

    Raising straight from the handler could land inside a JAX host callback,
    where the exception is wrapped into an XLA runtime error.
    """
    from selfid_jax.sweep import clear_stop, request_stop

    received: list[int] = []
    clear_stop()
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def handler(signum, frame):  # noqa: ARG001
        received.append(signum)
        if len(received) > 1:
            raise _Terminated()
        request_stop()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield received
    finally:
        signal.signal(signal.SIGTERM, previous)
        clear_stop()


def _experiment(name: str):
    from selfid_jax.sweep import get_experiment

    exp = get_experiment(name)
    if exp is None:
        raise _UsageError(
            f"no runner registered for experiment {name!r}: experiments/{name}.py is missing or does "
            "not call selfid_jax.sweep.register_experiment"
        )
    return exp


def _draw(exp, run_dir: Path) -> list[Path]:
    from selfid_jax.results import FIGURES_DIR, load_results, read_summary

    if exp.plotter is None:
        return []
    df = load_results(run_dir)
    summary = read_summary(run_dir, missing_ok=True)
    return [Path(p) for p in exp.plotter(df, summary, run_dir / FIGURES_DIR)]


def _init_distributed(args: argparse.Namespace) -> None:
    manual = (args.coordinator, args.num_processes, args.process_id)
    if not args.distributed and all(v is None for v in manual):
        return
    import jax

    # CPU hosts need a cross-process collectives backend; GPU/TPU ignore this flag
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=args.coordinator, num_processes=args.num_processes, process_id=args.process_id
    )


def _sweep(args: argparse.Namespace) -> int:
    from selfid_jax.config import load_config
    from selfid_jax.results import create_run_dir

    cfg = load_config(args.config, args.overrides)
    exp = _experiment(cfg.experiment)
    run_dir = args.out if args.out is not None else Path("runs") / args.config.stem
    _init_distributed(args)  # after validation, before any JAX computation
    create_run_dir(run_dir, cfg, args.config, overrides=args.overrides, fresh=args.fresh)
    received: list[int] = []
    try:
        with _graceful_sigterm() as received:
            exp.runner(cfg, run_dir, args.fresh, args.progress)
    except (KeyboardInterrupt, _Terminated):
        print(
            f"{_PROG}: interrupted; finished chunks are kept in {run_dir}. "
            "Run the same command again to resume (add --fresh to start over).",
            file=sys.stderr,
        )
        return 143 if received else 130
    import jax

    if jax.process_index() != 0:
        return 0
    figures = _draw(exp, run_dir)
    print(f"results: {run_dir}")
    for f in figures:
        print(f"figure:  {f}")
    return 0


def _plot(args: argparse.Namespace) -> int:
    from selfid_jax.results import read_run_config

    run_dir: Path = args.run_dir
    if not run_dir.is_dir():
        raise _UsageError(f"{run_dir}: run directory not found")
    name = read_run_config(run_dir).get("experiment")
    if not isinstance(name, str):
        raise _UsageError(f"{run_dir / 'config.yaml'}: no 'experiment' key")
    exp = _experiment(name)
    if exp.plotter is None:
        raise _UsageError(f"experiment {name!r} registers no plotter")
    for f in _draw(exp, run_dir):
        print(f"figure: {f}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    try:
        demo = importlib.import_module("experiments.demo")
    except ModuleNotFoundError as err:
        if err.name not in ("experiments.demo", "experiments"):
            raise
        raise _UsageError("the demo is not available (experiments/demo.py is missing)") from None
    result = demo.main(args.out)
    return result if isinstance(result, int) else 0


def _enable_compilation_cache() -> None:
    """Keep compiled XLA programs on disk so a re-run (or a resumed sweep) skips compilation.

    Directory: ``$SELFID_JAX_CACHE_DIR``, else ``~/.cache/selfid_jax/xla``; set
    ``SELFID_JAX_CACHE_DIR=off`` to disable. A directory the user already gave
    JAX (``JAX_COMPILATION_CACHE_DIR``) is left alone.
    """
    import os

    import jax

    if jax.config.jax_compilation_cache_dir:
        return
    where = os.environ.get("SELFID_JAX_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "selfid_jax", "xla"))
    if where.lower() in ("off", "0", "none", ""):
        return
    try:
        os.makedirs(where, exist_ok=True)
    except OSError:
        return  # read-only home: run without the cache
    jax.config.update("jax_compilation_cache_dir", where)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``selfid-jax`` console script; returns the exit code."""
    from selfid_jax.config import ConfigError

    args = _parser().parse_args(argv)
    if args.command in ("sweep", "demo"):
        _enable_compilation_cache()
    command = {"sweep": _sweep, "plot": _plot, "demo": _demo}[args.command]
    try:
        return command(args)
    except (_UsageError, ConfigError, FileNotFoundError) as err:
        print(f"{_PROG} {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{_PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
