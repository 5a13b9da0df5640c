"""The names of a run directory's files, at the bottom of the runner; imports nothing.

Layout of a run directory ``RUN``::

    RUN/config.yaml       resolved config (every default filled in)
    RUN/versions.json     package versions, git revision, devices, command
    RUN/parts/<part>/     per compiled part of an experiment (e.g. per system):
                          manifest.json (what its chunks hold) and chunks/, one
                          Parquet file per finished chunk (sweep.run_chunked)
    RUN/results.parquet   tidy table, one row per batch element (rollout)
    RUN/summary.json      per-system summaries (e.g. valid-region bounds)
    RUN/figures/          PNG and PDF figures, redrawn by ``selfid-jax plot RUN``
    RUN/.lock             lock of the process running in RUN (selfid_jax.runner.lock); never removed
"""

from __future__ import annotations

CONFIG_FILE = "config.yaml"
VERSIONS_FILE = "versions.json"
MANIFEST_FILE = "manifest.json"
CHUNKS_DIR = "chunks"
PARTS_DIR = "parts"
RESULTS_FILE = "results.parquet"
SUMMARY_FILE = "summary.json"
FIGURES_DIR = "figures"
LOCK_FILE = ".lock"

SAFE_NAME = r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,99}$"
"""What a part's (and so a system's) name may be: one path component inside the run directory, no separator,
no leading dot (so never ``..``), no character a filesystem refuses, at most 100 characters."""

OWNED = (CONFIG_FILE, VERSIONS_FILE, MANIFEST_FILE, CHUNKS_DIR, PARTS_DIR, RESULTS_FILE, SUMMARY_FILE, FIGURES_DIR)
"""Everything create_run_dir/run_chunked may write; ``--fresh`` removes exactly these."""
