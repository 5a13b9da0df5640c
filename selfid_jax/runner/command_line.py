"""``selfid-jax`` command line: ``sweep``, ``plot``, ``demo``, ``list``.

    selfid-jax sweep CONFIG [--set key.sub=value ...] [--out DIR] [--fresh] [--no-progress]
    selfid-jax plot RUN_DIR
    selfid-jax demo [--out DIR]
    selfid-jax list

``sweep`` validates the config before any compute, creates the run directory
(default ``runs/<config stem>``), runs the experiment named by the config's
``experiment:`` key (found through the ``selfid_jax.experiments`` entry points,
:mod:`selfid_jax.runner.contract`), prints its report, then draws the figures from
the saved results, exactly as ``plot`` would. Interrupt it (Ctrl-C or ``kill``)
and run the same command again to resume; ``--fresh`` starts over.

Several hosts: run the same ``sweep`` command on every host with
``--distributed`` (SLURM/Open MPI/Kubernetes auto-detection) or with
``--coordinator HOST:PORT --num-processes P --process-id I``; see
``selfid_jax.runner.sweep`` for how the batch is sharded and who writes what.

Bad input (missing file, invalid config, run directory of another config or
in use by another process, unreadable run files, unwritable or full disk) is
reported on stderr as one line naming the path and what to do, with exit code
2 and no traceback; an interrupted sweep exits with 130 (Ctrl-C) or 143
(SIGTERM). A first SIGTERM lets the chunk in flight finish and be saved;
``kill -9`` loses at most that chunk. ``sweep`` and ``demo`` hold the run
directory's lock (:mod:`selfid_jax.runner.lock`) from before anything in it is
deleted or written until the figures are drawn.

Size: about 500 lines, the runner's whole command line (sweep, list, plot, demo and the commands a package
adds), each subcommand a few functions sharing the argument and error handling.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import functools
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

__all__ = ["Command", "main"]

_PROG = "selfid-jax"


class Command(NamedTuple):
    """A subcommand added by the package above the runner (e.g. ``fit``): argparse wiring and its body.

    ``run(args) -> exit code`` reports bad input by raising
    :class:`~selfid_jax.runner.errors.ConfigError` (or ``OSError``): one line on
    stderr, exit 2, like the runner's own commands. An exception with an integer
    ``exit_code`` attribute above 2 (a robot's driver failing,
    :class:`selfid_jax.robot.drivers.load.DriverFailure`: 3) is one line on stderr
    and that exit code.
    """

    help: str  # one line for `selfid-jax --help`
    description: str  # the subcommand's --help text
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    # ``plot(run_dir)``: redraw the figures of a run directory this command wrote (``selfid-jax plot RUN``) and
    # return their paths, or None when ``run_dir`` is not one of its own (then it writes nothing there, not even
    # a lock: it takes the directory's lock, selfid_jax.runner.lock.hold, only once it knows the directory)
    plot: Callable[[Path], list[Path] | None] | None = None


class _UsageError(Exception):
    """Bad input the user can fix; printed without traceback, exit code 2."""


class _Terminated(Exception):
    """A second SIGTERM: stop now, between Python bytecodes."""


def _parser(extra: Mapping[str, Command] | None = None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=_PROG, description="Self-identified inverse Jacobians: sweeps and figures.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser(
        "sweep", help="run an experiment sweep from a YAML config (resumable)",
        description="Validate CONFIG, run its experiment in resumable chunks into a run directory, print the "
        "report and draw the figures. Run the same command again after an interruption to resume.",
    )
    s.add_argument("config", type=Path, help="YAML config with a top-level 'experiment:' key, or the name of a "
                   "shipped config (e.g. valid_region_ur5e, found in any subfolder: ./configs first, then the "
                   "installed ones; selfid-jax list)")
    s.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a config value by dotted key, e.g. --set controller.tol=1e-3 (repeatable)",
    )
    s.add_argument("--out", type=Path, default=None, help="run directory (default: runs/<config stem>)")
    s.add_argument("--fresh", action="store_true", help="discard earlier results in the run directory")
    s.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    s.add_argument("--max-rows", type=int, metavar="N", default=None,
                   help="refuse sweeps of more rows (default $SELFID_JAX_MAX_ROWS or 20,000,000)")
    s.add_argument("--max-memory-gb", type=float, metavar="G", default=None,
                   help="refuse sweeps whose results need more memory (default $SELFID_JAX_MAX_MEMORY_GB or 12)")
    g = s.add_argument_group(
        "several hosts (jax.distributed)",
        "run the same command on every host; only process 0 writes the run directory",
    )
    g.add_argument("--distributed", action="store_true",
                   help="call jax.distributed.initialize() (auto-detects SLURM, Open MPI, Kubernetes)")
    g.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0 (implies --distributed)")
    g.add_argument("--num-processes", type=int, metavar="P", help="number of processes (implies --distributed)")
    g.add_argument("--process-id", type=int, metavar="I", help="this process, 0..P-1 (implies --distributed)")
    g.add_argument("--heartbeat-timeout", type=int, metavar="S", default=100,
                   help="seconds after which the processes give up on one that stopped answering (default 100)")

    pl = sub.add_parser(
        "plot", help="redraw every figure of a run from its saved results",
        description="Redraw every figure of RUN_DIR into RUN_DIR/figures from its saved results (no simulation): "
        "a sweep's or the demo's from results.parquet and summary.json"
        + "".join(f"; {name}'s from its own files" for name, c in (extra or {}).items() if c.plot is not None)
        + ".",
    )
    pl.add_argument("run_dir", type=Path, help="a run directory written by 'selfid-jax sweep' or 'selfid-jax demo'"
                    + "".join(f" or 'selfid-jax {name}'" for name, c in (extra or {}).items() if c.plot is not None))

    d = sub.add_parser(
        "demo",
        help="the main job: UR5e and Model O self-ID, then a star with each estimate (about 50 s on 2 CPU cores)",
        description="Self-identify a UR5e and a Model O hand, each from 4 start configurations in one compiled call, "
        "follow a star (5 cm, 1.5 mm) with each estimate and with the true inverse Jacobian, print a summary and write "
        "the run directory "
        "(results.parquet, summary.json, figures/demo.png). Always starts fresh.",
    )
    d.add_argument("--out", type=Path, default=Path("runs/demo"), help="run directory (default: runs/demo)")

    sub.add_parser(
        "list", help="list the experiments, built-in systems and shipped configs",
        description="List the installed experiments (entry-point group selfid_jax.experiments), the built-in "
        "systems and the configs under ./configs and installed with the package, with where they live.",
    )
    for name, command in (extra or {}).items():
        command.add_arguments(sub.add_parser(name, help=command.help, description=command.description))
    return p


@contextlib.contextmanager
def _graceful_sigterm() -> Iterator[list[int]]:
    """First SIGTERM: let the sweep save the chunk in flight and stop; second: stop at once.

    Raising straight from the handler could land inside a JAX host callback,
    where the exception is wrapped into an XLA runtime error.
    """
    from selfid_jax.runner.sweep import clear_stop, request_stop

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


def _saved_summary(exp, df, run_dir: Path) -> dict:
    """``summary.json``, or when it is missing the summary recomputed from the table and ``config.yaml``."""
    from selfid_jax.runner.config import load_config
    from selfid_jax.runner.errors import ConfigError
    from selfid_jax.runner.layout import CONFIG_FILE
    from selfid_jax.runner.rundir import read_run_config, read_summary

    summary = read_summary(run_dir, missing_ok=True)
    if summary:
        return summary
    try:
        return exp.summarize(df, load_config(run_dir / CONFIG_FILE, model=exp.config))
    except ConfigError:  # a config.yaml this version cannot validate: keep at least the configured threshold
        threshold = read_run_config(run_dir).get("completion_threshold")
        return {"completion_threshold": threshold} if isinstance(threshold, (int, float)) else {}


def _draw(exp, run_dir: Path) -> list[Path]:
    from selfid_jax.runner.layout import FIGURES_DIR
    from selfid_jax.runner.rundir import load_results

    if exp.plot is None:
        return []
    df = load_results(run_dir)
    return [Path(p) for p in exp.plot(df, _saved_summary(exp, df, run_dir), run_dir / FIGURES_DIR)]


def _init_distributed(args: argparse.Namespace) -> None:
    manual = (args.coordinator, args.num_processes, args.process_id)
    if not args.distributed and all(v is None for v in manual):
        return
    import jax

    # CPU hosts need a cross-process collectives backend; GPU/TPU ignore this flag
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    if not args.heartbeat_timeout > 0:
        raise _UsageError(f"--heartbeat-timeout must be positive, got {args.heartbeat_timeout}")
    jax.distributed.initialize(
        coordinator_address=args.coordinator, num_processes=args.num_processes, process_id=args.process_id,
        heartbeat_timeout_seconds=args.heartbeat_timeout,
    )


def _build(exp, cfg, source: str):
    """``exp.parts(cfg)``, before any run directory exists; a ``ValueError`` (infeasible path, bad robot) is a usage
    error."""
    try:
        return exp.parts(cfg)
    except ValueError as err:
        raise _UsageError(f"{source}: cannot set up experiment {exp.name!r}: {err}") from None


def _run(exp, cfg, run_dir: Path, *, config_path, overrides, fresh: bool, progress: bool) -> int:
    """Build the parts (every check before the run directory is made), then, holding the run directory's lock
    throughout, run the experiment into ``run_dir`` (:func:`selfid_jax.runner.execute.run`) under SIGTERM handling,
    report and draw the figures."""
    import jax

    from selfid_jax.runner import signals
    from selfid_jax.runner.execute import part_threads, run
    from selfid_jax.runner.lock import check_free, check_run_dir, hold
    from selfid_jax.runner.sweep import clear_stop, request_stop
    from selfid_jax.runner.sweep import stop_requested as sweep_stop_requested

    signals.phase("setup")
    check_run_dir(run_dir)  # before any compute: a file in the way, an unwritable folder (RunDirError, exit 2)
    check_free(run_dir)  # and a directory another process is running in (RunDirBusy, exit 2), before the build
    part_threads(1)  # and a bad $SELFID_JAX_PART_THREADS (ConfigError, exit 2)
    parts = _build(exp, cfg, str(config_path) if config_path is not None else exp.name)
    received: list[int] = []
    t0 = time.perf_counter()
    again = ("run the same command again to resume (add --fresh to start over)" if config_path is not None
             else f"{_PROG} {exp.name} always starts fresh: run it again")
    message = f"{_PROG}: interrupted; finished chunks are kept in {run_dir}; {again}"
    # One hold from before the run directory is touched until its figures are written: execute.run takes the same
    # (re-entrant) lock again, and releasing it before the figures would let another sweep into a directory still
    # being written. Only process 0 of a jax.distributed run locks (it alone writes the shared files).
    with hold(run_dir) if jax.process_index() == 0 else contextlib.nullcontext():
        try:
            if signals.installed():
                clear_stop()
                with signals.graceful(message, request_stop):
                    out = run(exp, cfg, run_dir, fresh=fresh, progress=progress, parts=parts,
                              config_path=config_path, overrides=overrides)
            else:
                with _graceful_sigterm() as received:
                    out = run(exp, cfg, run_dir, fresh=fresh, progress=progress, parts=parts,
                              config_path=config_path, overrides=overrides)
            stopped = signals.installed() and sweep_stop_requested()
        except (KeyboardInterrupt, _Terminated):
            print(message, file=sys.stderr)
            return 143 if (received or signals.installed()) else 130
        finally:
            clear_stop()
        if stopped:  # SIGTERM during the last chunk: every chunk is saved, but the user asked to stop
            print(message, file=sys.stderr)
            return 143
        if out is None:  # not process 0 of a jax.distributed run
            return 0
        _, summary = out
        if exp.report is not None:
            print(exp.report(summary))
        signals.phase("figures")
        figures = _draw(exp, run_dir)  # still under the lock: the run is not finished until its figures are
    print(f"results: {run_dir} ({time.perf_counter() - t0:.1f} s)")
    for f in figures:
        print(f"figure:  {f}")
    return 0


def _sweep(args: argparse.Namespace) -> int:
    import os

    from selfid_jax.runner import registry

    for flag, env in ((args.max_rows, "SELFID_JAX_MAX_ROWS"), (args.max_memory_gb, "SELFID_JAX_MAX_MEMORY_GB")):
        if flag is not None:
            if not flag > 0:
                raise _UsageError(f"--{env[11:].lower().replace('_', '-')} must be positive, got {flag}")
            os.environ[env] = str(flag)

    args.config = find_config(args.config, args.config_dirs)
    cfg = registry.load(args.config, args.overrides)
    exp = registry.get(cfg.experiment)
    run_dir = args.out if args.out is not None else Path("runs") / args.config.stem
    _init_distributed(args)  # after validation, before any JAX computation
    return _run(exp, cfg, run_dir, config_path=args.config, overrides=args.overrides, fresh=args.fresh,
                progress=args.progress)


def _plot(args: argparse.Namespace) -> int:
    from selfid_jax.runner import registry, signals
    from selfid_jax.runner.layout import CONFIG_FILE
    from selfid_jax.runner.lock import hold
    from selfid_jax.runner.rundir import read_run_config

    run_dir: Path = args.run_dir
    if not run_dir.is_dir():
        raise _UsageError(f"{run_dir}: run directory not found")
    if not (run_dir / CONFIG_FILE).exists():  # not a sweep's: a command's own (fit, online), through its hook
        plotters = {name: c.plot for name, c in getattr(args, "commands", {}).items() if c.plot is not None}
        signals.phase("plot")
        for plot in plotters.values():
            figures = plot(run_dir)
            if figures is not None:
                for f in figures:
                    print(f"figure: {f}")
                return 0
        kinds = ", ".join(["sweep", "demo", *plotters])
        raise _UsageError(f"{run_dir}: not a run directory of {kinds} (no {CONFIG_FILE}, and none of "
                          f"{', '.join(plotters) or 'the commands'} recognises its files); nothing to plot")
    name = read_run_config(run_dir).get("experiment")
    if not isinstance(name, str):
        raise _UsageError(f"{run_dir / 'config.yaml'}: no 'experiment' key")
    exp = registry.get(name)
    if exp.plot is None:
        raise _UsageError(f"experiment {name!r} draws no figures")
    signals.phase("plot")
    with hold(run_dir):  # not while a sweep writes (or --fresh empties) the directory: RunDirBusy names it
        figures = _draw(exp, run_dir)
    for f in figures:
        print(f"figure: {f}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    from selfid_jax.runner import registry

    exp = registry.get("demo")
    # exp.config is typed as BaseConfig, whose experiment has no default; the demo's model sets it.
    cfg = exp.config()  # type: ignore[call-arg]
    return _run(exp, cfg, args.out, config_path=None, overrides=(), fresh=True, progress=False)


def _list(args: argparse.Namespace, catalogues: Mapping[str, Callable[[], Mapping[str, str]]]) -> int:  # noqa: ARG001
    from selfid_jax.runner import registry

    print("experiments (selfid-jax sweep CONFIG with 'experiment: NAME'):")
    for name in registry.available():
        exp = registry.get(name)
        print(f"  {name:14s} {exp.description}")
    for title, entries in catalogues.items():
        print(f"{title}:")
        for name, doc in entries().items():
            print(f"  {name:14s} {doc}")
    for label, folder in args.config_dirs:
        configs = _config_files(Path(folder))
        if configs:
            print(f"configs ({label}: {folder}; selfid-jax sweep NAME runs NAME.yaml from any of its folders):")
            group = None
            for path in configs:
                sub = path.parent.relative_to(folder).as_posix()
                if sub != group:
                    group = sub
                    print(f"  {'.' if sub == '.' else sub}/")
                print(f"    {path.stem:32s} {path}")
        else:
            print(f"configs ({label}: {folder}): none")
    return 0


def _config_files(folder: Path, names: Sequence[str] | None = None) -> list[Path]:
    """The YAML files under ``folder`` and its subfolders (hidden and ``__pycache__`` folders skipped), sorted by
    folder then name; with ``names``, the files of those names instead (of any suffix), in the same order."""
    import os

    found: list[Path] = []
    if not folder.is_dir():
        return found
    for root, subdirs, files in os.walk(folder):
        subdirs[:] = sorted(d for d in subdirs if not d.startswith(".") and d != "__pycache__")
        for name in sorted(files):
            if name in names if names is not None else name.endswith((".yaml", ".yml")):
                found.append(Path(root) / name)
    return sorted(found, key=lambda p: (p.parent.relative_to(folder).parts, p.name))


def find_config(config: Path, dirs: Sequence[tuple[str, Path]]) -> Path:
    """``config`` if it is a file, else ``NAME`` or ``NAME.yaml`` from the first of ``dirs`` that has it.

    Each of ``dirs`` is searched with its subfolders (the shipped configs are grouped by experiment:
    ``configs/valid_region/valid_region_ur5e.yaml`` is found as ``valid_region_ur5e``); a name found twice under
    one of them is an error naming both files. Only a bare name (no folder part) is looked up, so a mistyped path
    is reported as that path.
    """
    from selfid_jax.runner.errors import ConfigError

    if config.exists() or config.parent != Path(".") or not dirs:
        return config
    names = [config.name] if config.suffix in (".yaml", ".yml") else [config.name + ".yaml", config.name]
    for label, folder in dirs:
        for name in names:
            found = _config_files(Path(folder), [name])
            if len(found) > 1:
                raise ConfigError(f"{config}: {name} is in more than one folder of {folder} ({label}): "
                                  f"{', '.join(map(str, found))}; give the path of the one to run")
            if found:
                return found[0]
    where = " or ".join(f"{folder}" for _, folder in dirs)
    raise ConfigError(f"{config}: config file not found, and no {names[0]} in {where} or their subfolders "
                      f"('{_PROG} list' shows the shipped configs)")


def _enable_compilation_cache() -> None:
    """Keep compiled XLA programs on disk so a re-run (or a resumed sweep) skips compilation.

    Directory: ``$SELFID_JAX_CACHE_DIR``, else ``~/.cache/selfid_jax/xla``; set
    ``SELFID_JAX_CACHE_DIR=off`` to disable. A directory the user already gave
    JAX (``JAX_COMPILATION_CACHE_DIR``) is left alone.
    """
    import os

    import jax

    if jax.config.jax_compilation_cache_dir:  # type: ignore[attr-defined]
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


_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
_DENIED = (errno.EACCES, errno.EPERM, errno.EROFS)


def _os_error(err: OSError, command: str) -> str:
    """One line for an ``OSError``: the path, what went wrong, what to do."""
    if err.errno is None:  # raised with a message of ours, e.g. FileNotFoundError("CONFIG: not found")
        return " ".join(str(err).split())
    where = f"{err.filename}: " if err.filename is not None else ""
    if err.errno in _FULL:
        todo = "free some disk space, then run the same command again" + (
            " to resume (finished chunks are kept)" if command == "sweep" else "")
    elif err.errno in _DENIED:
        folder = Path(err.filename).parent if err.filename is not None else "it"
        todo = f"make {folder} writable" + (", or choose another --out" if command != "plot" else "")
    elif err.errno in (errno.ENOTDIR, errno.EISDIR, errno.EEXIST):
        todo = "a file is in the way of a directory (or the reverse); choose another path"
    else:
        todo = "check the path, then run the same command again"
    return f"{where}{err.strerror or err}; {todo}"


def main(argv: Sequence[str] | None = None,
         catalogues: Mapping[str, Callable[[], Mapping[str, str]]] | None = None,
         *, handle_signals: bool | None = None, commands: Mapping[str, Command] | None = None,
         config_dirs: Sequence[tuple[str, Path]] = (("./configs", Path("configs")),)) -> int:
    """The ``selfid-jax`` command line; returns the exit code.

    ``catalogues``: extra sections of ``selfid-jax list``, title -> a function
    returning ``{name: one-line description}`` (the package adds its built-in systems).
    ``commands``: extra subcommands, name -> :class:`Command` (the package adds ``fit``).
    ``config_dirs``: ``(label, folder)`` pairs, in order, where ``sweep NAME`` looks for ``NAME.yaml`` (in each
    folder and its subfolders; the first folder that has it wins) and ``list`` lists configs, grouped by subfolder
    (the package adds its installed configs after ``./configs``).
    ``handle_signals``: take over SIGINT and SIGTERM (:func:`selfid_jax.runner.signals.install`:
    exit 130 / 143 with one line at any phase); default: when ``argv`` is None, i.e. as the
    console script, never when called from Python with arguments (a test, a notebook).
    """
    from selfid_jax.runner import signals

    if handle_signals if handle_signals is not None else argv is None:
        signals.install(_PROG)
    signals.phase("start")
    from selfid_jax.runner.errors import ConfigError

    args = _parser(commands).parse_args(argv)
    args.config_dirs = tuple(config_dirs)
    args.commands = dict(commands or {})
    if args.command in ("sweep", "demo", *(commands or {})):
        _enable_compilation_cache()
    table: dict[str, Callable[[argparse.Namespace], int]] = {
        "sweep": _sweep, "plot": _plot, "demo": _demo, "list": functools.partial(_list, catalogues=catalogues or {}),
        **{name: c.run for name, c in (commands or {}).items()}}
    command = table[args.command]
    try:
        return command(args)
    except (_UsageError, ConfigError) as err:
        _print_error(args.command, str(err), err)
        return 2
    except OSError as err:
        _print_error(args.command, _os_error(err, args.command), err)
        return 2
    except KeyboardInterrupt:
        print(f"{_PROG}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:
        code = getattr(err, "exit_code", None)  # an error that says its own exit code (a robot's driver failing: 3)
        if not isinstance(code, int) or isinstance(code, bool) or code in (0, 1, 2):
            raise
        _print_error(args.command, " ".join(str(err).split()), err)
        return code


def _print_error(command: str, text: str, err: BaseException) -> None:
    """The one error line on stderr, then a ``note:`` line for each note the error carries (``add_note``: a
    driver whose ``close()`` failed after the error, say)."""
    print(f"{_PROG} {command}: error: {text}", file=sys.stderr)
    for note in getattr(err, "__notes__", ()):
        print(f"note: {' '.join(str(note).split())}", file=sys.stderr)

if __name__ == "__main__":
    sys.exit(main())
