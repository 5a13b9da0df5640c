"""The ``selfid-jax`` console script: the runner's command line with this package's systems and ``fit`` command."""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from pathlib import Path


def _systems() -> Mapping[str, str]:
    from selfid_jax import systems

    return systems.BUILTIN


def _config_dirs() -> tuple[tuple[str, Path], ...]:
    """Where ``selfid-jax sweep NAME`` looks: ``./configs``, then the configs installed with the package.

    The installed ones are the data package ``selfid_jax.configs`` (the top-level configs/ of a checkout, installed
    by pyproject.toml's package-dir): its one folder is the first of its ``__path__``.
    """
    from importlib import import_module

    installed = Path(next(iter(import_module("selfid_jax.configs").__path__)))
    return (("./configs", Path("configs")), ("installed", installed))


def commands() -> dict:
    """The package's own subcommands ``fit``, ``calibrate``, ``online``, ``robot-sim`` (:mod:`selfid_jax.commands`)."""
    from selfid_jax.commands import calibrate, fit, online, robot_sim

    return {"fit": fit.command(), "calibrate": calibrate.command(), "online": online.command(),
            "robot-sim": robot_sim.command()}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``selfid-jax``: :func:`selfid_jax.runner.command_line.main` with the built-in systems and ``fit``
    (:mod:`selfid_jax.commands.fit`); the exit code.

    As the console script (``argv`` None) it first takes over SIGINT and SIGTERM
    (:mod:`selfid_jax.runner.signals`), before JAX or pandas are imported, and collects garbage less often while it
    traces (:func:`selfid_jax._gc.collect_less_often`); for ``demo`` it also asks XLA for quick compiles
    (:func:`selfid_jax._xla.request_quick_compile`: LLVM level 0 and whole-module compiles, unless ``XLA_FLAGS`` sets
    them).
    """
    from selfid_jax.runner import signals

    if argv is None:
        signals.install()
        from selfid_jax._gc import collect_less_often

        collect_less_often()
        if sys.argv[1:2] == ["demo"]:  # compile-bound: each of its programs runs once, on small batches
            from selfid_jax._xla import request_quick_compile

            request_quick_compile()
    from selfid_jax.runner import command_line

    return command_line.main(argv, catalogues={"systems (selfid_jax.systems)": _systems}, handle_signals=argv is None,
                    commands=commands(), config_dirs=_config_dirs())


if __name__ == "__main__":
    sys.exit(main())
