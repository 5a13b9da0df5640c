"""The runner's errors, at the bottom of the runner: a config, override or run directory that cannot be used.

Every message names the file or key and says what to do; the CLI prints it as
one line and exits 2. This module imports nothing.
"""

from __future__ import annotations

__all__ = ["ConfigError", "RunDirBusy", "RunDirError", "SweepResumeError"]


class ConfigError(ValueError):
    """A config file, override or run directory that cannot be used; the message says why."""


class RunDirError(ConfigError):
    """A run directory that cannot be (re)used as asked; the message says why and what to do."""


class RunDirBusy(RunDirError):
    """Another process holds the run directory's lock; the message names its process id."""


class SweepResumeError(RunDirError):
    """``out_dir`` holds chunks of a different sweep; the message names what differs."""
