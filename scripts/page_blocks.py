"""Generated blocks of the results pages: the text between ``<!-- PREFIX:NAME -->`` and ``<!-- /PREFIX:NAME -->``,
written by the scripts that render tables from runs (``gap_study.py``, ``tracking_page.py``,
``valid_region_page.py``, ``articulated_page.py``) and read back by ``tests/test_results_pages.py``; and the
provenance of their numbers (issue 55).

Provenance: a page's data file (``docs/results/data/NAME.json``) holds, under ``"provenance"``, one entry per run
its numbers come from, each with the fingerprint the run directory records (:func:`provenance`: the config and its
resolved hash, the ``selfid_jax`` version, source hash and git commit, the hash of the run's ``results.parquet``, the
date and the machine). The run's rows are kept in the repository (:func:`keep_rows`:
``docs/results/data/runs/RUN/results.parquet`` byte for byte, beside the resolved ``config.yaml``), so the numbers
can be recomputed from them by the same code (:func:`run_summary`: the experiment's own ``summarize``), which
``tests/test_results_pages.py`` does: an edited number, or edited rows, fail.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
#: Where the rows of the runs behind the results pages are kept, one folder per run.
ROWS = ROOT / "docs" / "results" / "data" / "runs"
RESULTS = "results.parquet"
CONFIG = "config.yaml"


def sha256_file(path: Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def provenance(run: Path, name: str, config: str) -> dict[str, Any]:
    """The fingerprint of run directory ``run`` as it records it: ``name`` (the run), ``config`` (the shipped
    config, a path from the repository root), the resolved config's SHA-256 and the package's version and source
    SHA-256 (from its parts' manifests, which every part shares), the git commit of the package and whether its
    files differed from it, the SHA-256 and row count of ``results.parquet``, the date the run was created (UTC)
    and the machine (JAX backend and devices, Python and JAX versions: what ``versions.json`` records)."""
    import pandas as pd

    run = Path(run)
    if not (run / RESULTS).is_file():
        raise SystemExit(f"{run}: no {RESULTS}; run: selfid-jax sweep {config} --out {run}")
    versions = json.loads((run / "versions.json").read_text())
    prints = {json.dumps(json.loads(m.read_text())["fingerprint"], sort_keys=True)
              for m in sorted(run.glob("parts/*/manifest.json"))}
    if len(prints) != 1:
        raise SystemExit(f"{run}: its parts record {len(prints)} different fingerprints; rerun it with --fresh")
    fp = json.loads(prints.pop())
    return {"run": name, "config": config, "config_sha256": fp["config_sha256"],
            "selfid_jax": fp["package"]["version"], "source_sha256": fp["package"]["source_sha256"],
            "git_revision": versions.get("git_revision"), "git_dirty": versions.get("git_dirty"),
            "results_sha256": sha256_file(run / RESULTS), "n_rows": len(pd.read_parquet(run / RESULTS, columns=[])),
            "created_utc": versions.get("created_utc"),
            "machine": f"{versions.get('jax_backend')} ({', '.join(versions.get('devices', []))}), python "
                       f"{versions.get('python')}, jax {versions.get('jax')}, mujoco {versions.get('mujoco')}"}


#: A column whose cells are arrays longer than this is a per-step trace: too big to keep, and no page's number reads
#: one (:func:`keep_rows` checks that the numbers recomputed without them are the same).
TRACE_LEN = 64


def keep_rows(run: Path, name: str, rows: Path = ROWS) -> dict[str, Any]:
    """Copy the run's rows to ``rows/name/``: its resolved ``config.yaml``, and its ``results.parquet`` without the
    per-step trace columns (cells longer than :data:`TRACE_LEN`; the whole file's hash stays in the provenance as
    ``results_sha256``). Returns the provenance of the copy: ``{"rows", "rows_sha256", "traces_dropped"}``."""
    import pandas as pd

    dest = Path(rows) / name
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(Path(run) / CONFIG, dest / CONFIG)
    table = pd.read_parquet(Path(run) / RESULTS)
    traces = [c for c in table.columns if table[c].dtype == object
              and table[c].map(lambda v: hasattr(v, "__len__") and not isinstance(v, str) and len(v) > TRACE_LEN).any()]
    table.drop(columns=traces).to_parquet(dest / RESULTS, index=False, compression="zstd")
    kept = dest / RESULTS
    where = kept.relative_to(ROOT) if kept.is_relative_to(ROOT) else kept
    return {"rows": where.as_posix(), "rows_sha256": sha256_file(kept), "traces_dropped": traces}


def run_summary(run: Path) -> dict:
    """The run's summary recomputed from its rows: the experiment's ``summarize`` on ``run/results.parquet`` and
    the resolved ``run/config.yaml``, as plain JSON data (what the runner writes to ``summary.json``), so a kept
    copy of the rows gives the numbers without the summary file."""
    import pandas as pd
    import yaml

    from selfid_jax.runner import registry
    from selfid_jax.runner.config import load_config
    from selfid_jax.strict_json import jsonable

    run = Path(run)
    exp = registry.get(yaml.safe_load((run / CONFIG).read_text())["experiment"])
    summary = exp.summarize(pd.read_parquet(run / RESULTS), load_config(run / CONFIG, model=exp.config))
    return json.loads(json.dumps(jsonable(summary), allow_nan=False))  # as the runner writes summary.json


def resolved_config_sha256(run: Path) -> str:
    """The fingerprint's hash of the resolved ``run/config.yaml`` (as the runner computes it)."""
    import yaml

    from selfid_jax.runner import registry
    from selfid_jax.runner.config import dump_config, load_config
    from selfid_jax.runner.fingerprint import config_sha256

    exp = registry.get(yaml.safe_load((Path(run) / CONFIG).read_text())["experiment"])
    return config_sha256(dump_config(load_config(Path(run) / CONFIG, model=exp.config)))


def differences(old: Any, new: Any, *, rtol: float = 1e-9, atol: float = 1e-12, path: str = "") -> list[str]:
    """Each leaf where ``new`` differs from ``old`` (nested dicts and lists): ``"PATH: OLD -> NEW"``. Numbers differ
    beyond ``max(rtol |old|, atol)``; None and NaN equal each other; anything else by ``!=``."""
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        out = [f"{path}/{k}: only in the old" for k in old if k not in new]
        out += [f"{path}/{k}: only in the new" for k in new if k not in old]
        for k in old:
            if k in new:
                out += differences(old[k], new[k], rtol=rtol, atol=atol, path=f"{path}/{k}")
        return out
    if isinstance(old, list) and isinstance(new, list):
        if len(old) != len(new):
            return [f"{path}: {len(old)} items -> {len(new)}"]
        return [d for i, (a, b) in enumerate(zip(old, new))
                for d in differences(a, b, rtol=rtol, atol=atol, path=f"{path}/{i}")]

    def missing(v: Any) -> bool:
        return v is None or (isinstance(v, float) and math.isnan(v))

    if missing(old) and missing(new):
        return []
    number = (int, float)
    if (isinstance(old, number) and isinstance(new, number) and not isinstance(old, bool)
            and not isinstance(new, bool)):
        return [] if abs(new - old) <= max(rtol * abs(old), atol) else [f"{path}: {old!r} -> {new!r}"]
    return [] if old == new else [f"{path}: {old!r} -> {new!r}"]


def provenance_block(entries: list[dict]) -> str:
    """The provenance of a page's numbers, Markdown: one row per run, hashes shortened to 12 digits (the data file
    holds them whole). No entries: a line saying no run is on record."""
    if not entries:
        return ("No run of these numbers is on record: they predate the provenance of issue 55, and their run's "
                "rows were not kept, so no test recomputes them. Rerun: `python scripts/rerun_results.py "
                "--page PAGE --keep`.")
    lines = ["| run (config) | resolved config sha256 | selfid_jax (source sha256, commit) | results.parquet sha256 "
             "(rows) | kept rows sha256 (traces dropped) | created (UTC) | machine |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for e in entries:
        commit = "no commit" if not e.get("git_revision") else (
            e["git_revision"][:12] + (", modified" if e.get("git_dirty") else ""))
        lines.append(f"| `{e['run']}` (`{e['config']}`) | {e['config_sha256'][:12]} | {e['selfid_jax']} "
                     f"({e['source_sha256'][:12]}, {commit}) | {e['results_sha256'][:12]} ({e['n_rows']:,}) | "
                     f"[{e['rows_sha256'][:12]}](data/runs/{e['run']}/{RESULTS}) "
                     f"({', '.join(e['traces_dropped']) or 'none'}) | {e['created_utc']} | {e['machine']} |")
    return "\n".join(lines)


def markers(prefix: str, name: str) -> tuple[str, str]:
    """The opening and closing comment of block ``name``."""
    return f"<!-- {prefix}:{name} -->", f"<!-- /{prefix}:{name} -->"


def read_block(text: str, prefix: str, name: str) -> str:
    """The body of block ``name`` in ``text`` (without the newlines next to its markers); ``KeyError`` if absent."""
    begin, end = markers(prefix, name)
    if begin not in text or end not in text:
        raise KeyError(f"no {begin} ... {end} block")
    return text[text.index(begin) + len(begin):text.index(end)].strip("\n")


def write_blocks(page: Path, prefix: str, blocks: dict[str, str]) -> None:
    """Replace the body of each block ``name`` of ``page`` by ``blocks[name]``; every block must be there."""
    text = page.read_text()
    for name, body in blocks.items():
        begin, end = markers(prefix, name)
        if begin not in text or end not in text:
            raise SystemExit(f"{page}: no {begin} ... {end} block")
        i, j = text.index(begin) + len(begin), text.index(end)
        text = text[:i] + "\n" + body + "\n" + text[j:]
    page.write_text(text)


def from_runs(extract: Callable[[Path], dict], runs: Callable[[Path], dict[str, tuple[Path, str]]], where: Path,
              *, keep: Callable[[], dict] | None = None) -> dict:
    """The numbers ``extract`` reads from the run(s) at ``where``, with their ``"provenance"`` (one
    :func:`provenance` per run of ``runs(where)``: ``{name: (run directory, config)}``). ``keep``: also copy each
    run's rows to :data:`ROWS` (:func:`keep_rows`) and check that ``keep()``, the numbers recomputed from the kept
    rows, are the same."""
    entries = []
    for name, (run, config) in runs(where).items():
        entries.append(provenance(run, name, config))
        if keep is not None:
            entries[-1].update(keep_rows(run, name))
    data = extract(where)
    if keep is not None:
        moved = differences(data, keep())
        if moved:
            raise SystemExit("the kept rows do not give the runs' numbers: " + "; ".join(moved[:5]))
    data["provenance"] = entries
    return data


def cli(doc: str, prefix: str, extract: Callable[[Path], dict], blocks: Callable[[dict], dict[str, str]], *,
        run_flag: str, run_default: str, runs: Callable[[Path], dict[str, tuple[Path, str]]],
        from_rows: Callable[[], dict]) -> None:
    """The command line of a page script: read the numbers from the run(s) at ``run_flag`` (``extract``, with
    their provenance, ``runs`` naming them) or from ``--from-json``, write them to ``--json`` (and, with
    ``--keep-rows``, the runs' rows to :data:`ROWS`), print the blocks and rewrite ``--page``'s blocks under
    ``prefix``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument(run_flag, dest="run", default=run_default, help="where the run directories are")
    ap.add_argument("--json", default=None, help="write the numbers here")
    ap.add_argument("--keep-rows", action="store_true", help=f"copy the runs' rows to {ROWS.relative_to(ROOT)}")
    ap.add_argument("--from-json", default=None, help="read the numbers from here, not from the runs")
    ap.add_argument("--page", default=None, help="rewrite this page's generated blocks")
    args = ap.parse_args()
    data = (json.loads(Path(args.from_json).read_text()) if args.from_json
            else from_runs(extract, runs, Path(args.run), keep=from_rows if args.keep_rows else None))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(data, indent=1) + "\n")
    rendered = blocks(data)
    for body in rendered.values():
        print(body + "\n")
    if args.page:
        write_blocks(Path(args.page), prefix, rendered)
        print(f"rewrote the generated blocks of {args.page}")
