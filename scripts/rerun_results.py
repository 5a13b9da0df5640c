"""Rerun every configuration behind a results page and report each number that moved beyond its tolerance.

For each page (all four, or those named), every run its data file was made from (the page script's ``runs``) is
run again with ``selfid-jax sweep CONFIG --out SCRATCH/RUN`` into a scratch directory; the page's numbers are read
back from the new runs by the same code that wrote the data file (the script's ``extract``) and compared leaf by
leaf with ``docs/results/data/NAME.json`` (:func:`page_blocks.differences`). A number moved when it differs by more
than ``--rtol`` of its size (default 0.1 %; reruns of unchanged code on the same CPU differ by float round-off, far
below that) and ``--atol`` (default 1e-6) absolute; counts, flags and text must be equal.

    python scripts/rerun_results.py [--page gap|tracking|valid_region|articulated ...] [--scratch /tmp/rerun]
                                    [--reuse] [--keep] [--rtol 1e-3] [--atol 1e-6]

``--reuse``: a scratch run directory that already holds ``results.parquet`` is read, not rerun (the sweep resumes
an interrupted one anyway). ``--keep``: write the new numbers, their provenance and rows into the repository
(``docs/results/data/NAME.json``, ``docs/results/data/runs/RUN/``) and rewrite the page's generated blocks; then
check the sentences that quote a moved number (``tests/test_claims.py``). Exit status 0 when nothing moved, 1 when
something did (each printed), 2 for a usage error or a failed sweep. Run times on 2 shared cores are in
``docs/results/index.md``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the page scripts, run as python scripts/NAME.py

import articulated_page
import gap_study
import tracking_page
import valid_region_page
from page_blocks import ROOT, differences, from_runs, write_blocks


class Page(NamedTuple):
    """A results page and the code that makes its data file."""

    prefix: str  # the page's block prefix
    page: Path  # the Markdown page
    data: Path  # its data file
    runs: Callable[[Path], dict[str, tuple[Path, str]]]  # where -> {run: (run directory, config)}
    extract: Callable[[Path], dict]  # where -> the numbers
    blocks: Callable[[dict], dict[str, str]]  # data -> the page's generated blocks
    from_rows: Callable[[], dict]  # the numbers recomputed from the kept rows


RESULTS = ROOT / "docs" / "results"
PAGES = {
    "gap": Page("gap_study", RESULTS / "gap.md", RESULTS / "data" / "gap_study.json", gap_study.runs,
                lambda where: gap_study.to_json(gap_study.load(where)), gap_study.page_blocks_of,
                gap_study.from_rows),
    "tracking": Page("tracking", RESULTS / "tracking.md", RESULTS / "data" / "tracking.json", tracking_page.runs,
                     tracking_page.extract, tracking_page.blocks, tracking_page.from_rows),
    "valid_region": Page("valid_region", RESULTS / "valid_region.md", RESULTS / "data" / "valid_region.json",
                         valid_region_page.runs, valid_region_page.extract, valid_region_page.blocks,
                         valid_region_page.from_rows),
    "articulated": Page("articulated", RESULTS / "articulated.md", RESULTS / "data" / "articulated.json",
                        articulated_page.runs, articulated_page.extract, articulated_page.blocks,
                        articulated_page.from_rows),
}


def where_of(name: str, scratch: Path) -> Path:
    """The folder the page's ``runs`` and ``extract`` take: the scratch folder for pages of several runs, the run
    directory itself for pages of one."""
    return scratch if name in ("gap", "tracking") else scratch / next(iter(PAGES[name].runs(Path("."))))


def sweep(run: Path, config: str, *, reuse: bool) -> float:
    """Run ``selfid-jax sweep config --out run`` (nothing when ``reuse`` and it is finished); its wall time [s]."""
    if reuse and (run / "results.parquet").is_file():
        return 0.0
    start = time.monotonic()
    command = [str(Path(sys.executable).parent / "selfid-jax"), "sweep", str(ROOT / config), "--out", str(run),
               "--no-progress"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-5:])
        raise SystemExit(f"selfid-jax sweep {config} --out {run} failed (exit {done.returncode}):\n{tail}")
    return time.monotonic() - start


def rerun(name: str, scratch: Path, *, reuse: bool, keep: bool, rtol: float, atol: float) -> list[str]:
    """Rerun page ``name``'s runs into ``scratch`` and return each number that moved, ``"PATH: OLD -> NEW"``."""
    page = PAGES[name]
    where = where_of(name, scratch)
    for run, (directory, config) in page.runs(where).items():
        seconds = sweep(directory, config, reuse=reuse)
        print(f"{name}: {run} ({config}): " + ("reused" if not seconds else f"{seconds:.0f} s"), flush=True)
    old = json.loads(page.data.read_text())
    new = from_runs(page.extract, page.runs, where, keep=page.from_rows if keep else None)
    moved = differences({k: v for k, v in old.items() if k != "provenance"},
                        {k: v for k, v in new.items() if k != "provenance"}, rtol=rtol, atol=atol)
    if keep:
        page.data.write_text(json.dumps(new, indent=1) + "\n")
        write_blocks(page.page, page.prefix, page.blocks(new))
        print(f"{name}: wrote {page.data.relative_to(ROOT)}, its rows and {page.page.relative_to(ROOT)}")
    return moved


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--page", action="append", choices=sorted(PAGES), help="a page to rerun (repeatable; "
                    "default: all)")
    ap.add_argument("--scratch", default="/tmp/rerun_results", help="where the new run directories go")
    ap.add_argument("--reuse", action="store_true", help="read finished scratch runs instead of rerunning them")
    ap.add_argument("--keep", action="store_true", help="write the new data, rows and page into the repository")
    ap.add_argument("--rtol", type=float, default=1e-3, help="relative tolerance of a number (default 1e-3)")
    ap.add_argument("--atol", type=float, default=1e-6, help="absolute tolerance of a number (default 1e-6)")
    args = ap.parse_args(argv)
    if not (args.rtol >= 0 and args.atol >= 0):
        print("--rtol and --atol: expected numbers >= 0", file=sys.stderr)
        return 2
    moved_any = False
    for name in args.page or list(PAGES):
        start = time.monotonic()
        moved = rerun(name, Path(args.scratch), reuse=args.reuse, keep=args.keep, rtol=args.rtol, atol=args.atol)
        print(f"{name}: {len(moved)} number(s) moved beyond rtol {args.rtol:g} / atol {args.atol:g} "
              f"({time.monotonic() - start:.0f} s)")
        for line in moved:
            print(f"  {line}")
        moved_any |= bool(moved)
    return 1 if moved_any else 0


if __name__ == "__main__":
    raise SystemExit(main())
