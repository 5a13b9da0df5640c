"""Generated blocks of the results pages: the text between ``<!-- PREFIX:NAME -->`` and ``<!-- /PREFIX:NAME -->``,
written by the scripts that render tables from runs (``gap_study.py``, ``tracking_page.py``,
``valid_region_page.py``) and read back by ``tests/test_results_pages.py``."""

from __future__ import annotations

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
