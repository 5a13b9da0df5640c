"""Generated blocks of the results pages: the text between ``<!-- PREFIX:NAME -->`` and ``<!-- /PREFIX:NAME -->``,
written by the scripts that render tables from runs (``gap_study.py``, ``tracking_page.py``,
``valid_region_page.py``, ``articulated_page.py``) and read back by ``tests/test_results_pages.py``."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path


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


def cli(doc: str, prefix: str, extract: Callable[[Path], dict], blocks: Callable[[dict], dict[str, str]], *,
        run_flag: str, run_default: str) -> None:
    """The command line of a page script: read the numbers from the run(s) at ``run_flag`` (``extract``) or from
    ``--from-json``, write them to ``--json``, print the blocks and rewrite ``--page``'s blocks under ``prefix``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument(run_flag, dest="run", default=run_default, help="where the run directories are")
    ap.add_argument("--json", default=None, help="write the numbers here")
    ap.add_argument("--from-json", default=None, help="read the numbers from here, not from the runs")
    ap.add_argument("--page", default=None, help="rewrite this page's generated blocks")
    args = ap.parse_args()
    data = json.loads(Path(args.from_json).read_text()) if args.from_json else extract(Path(args.run))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(data, indent=1) + "\n")
    rendered = blocks(data)
    for body in rendered.values():
        print(body + "\n")
    if args.page:
        write_blocks(Path(args.page), prefix, rendered)
        print(f"rewrote the generated blocks of {args.page}")
