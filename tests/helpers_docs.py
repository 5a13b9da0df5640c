"""The rule of the README's and the docs pages' Python blocks: each prints what its comments say.

Shared by tests/test_readme.py (the README's block, the tolerance rule) and tests/test_docs.py (the docs pages'
blocks).

Stated outputs. Every ``print(...)`` line of a README or docs Python block ends in a
comment that is exactly the line it prints (an explanation goes on a comment
line of its own). The block runs in a fresh interpreter, as a reader pasting
it would (default float32, no test config), and its k-th stdout line is
compared with the k-th print's comment:

* the text with every number taken out must be equal (words, ``True``,
  brackets and units);
* the numbers, in order, must agree by kind of number, as written in the README:

  - an integer (``8``, a shape ``(50, 3, 3)``): exactly; these are counts and
    shapes, which do not move with rounding;
  - a number in scientific notation (``1.8e-07``): the README's way of writing
    a rounding-level quantity, such as float32 noise; within an order of
    magnitude, ``0.1 <= printed / stated <= 10``;
  - any other decimal (``1.1``, ``1.00``): within 10% relative, plus half a
    unit of the last digit written (``1.1`` accepts 0.94-1.26, ``0.0`` only
    values that print as 0.0 to 0.05).
"""

import io
import math
import re
import subprocess
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"


def doc_pages() -> list[Path]:
    """The Markdown pages of the docs site written by hand or committed (not the build, not the API pages
    ``docs/conf.py`` generates at build time)."""
    return sorted(p for p in DOCS.rglob("*.md") if p.relative_to(DOCS).parts[0] not in {"_build", "api"})


def python_blocks(text: str) -> list[str]:
    """The bodies of the ```python fenced blocks of a Markdown ``text``, in order."""
    return re.findall(r"```python\n(.*?)```", text, re.DOTALL)


# A number not glued to a word or another number: 8, -3, 1.00, .5, 1.8e-07 (not the 32 of float32, the 3 of 3rd).
NUMBER = re.compile(r"(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?(?![\w.])")
TOLERANCE_RULE = "integers exactly; scientific notation within 10x; other decimals 10% + half a last digit"


def stated_outputs(block: str) -> list[str]:
    """The trailing comment of every line that starts a ``print(`` statement, in order."""
    comments = {}
    for tok in tokenize.generate_tokens(io.StringIO(block).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string[1:].strip()
    stated = []
    for lineno, line in enumerate(block.splitlines(), start=1):
        if line.lstrip().startswith("print("):
            assert lineno in comments, f"print without its stated output: {line.strip()!r}"
            stated.append(comments[lineno])
    return stated


def _decimals(token: str) -> int:
    return len(token.split(".")[1]) if "." in token else 0


def number_agrees(stated: str, printed: str) -> bool:
    """The tolerance rule of this module's docstring, for one stated and one printed number."""
    s, p = float(stated), float(printed)
    if not math.isfinite(p):
        return False
    if re.fullmatch(r"[-+]?\d+", stated):
        return p == s
    if "e" in stated.lower():
        return s != 0 and p / s > 0 and 0.1 <= p / s <= 10
    return abs(p - s) <= 0.1 * abs(s) + 0.5 * 10.0 ** -_decimals(stated)


def compare_line(stated: str, printed: str) -> list[str]:
    """What differs between a stated and a printed line (empty when they agree)."""
    problems = []
    if NUMBER.sub("#", stated).split() != NUMBER.sub("#", printed).split():
        problems.append(f"text differs: README says {stated!r}, the block prints {printed!r}")
        return problems
    for s, p in zip(NUMBER.findall(stated), NUMBER.findall(printed), strict=True):
        if not number_agrees(s, p):
            problems.append(f"README says {s}, the block prints {p} (in {printed!r}; rule: {TOLERANCE_RULE})")
    return problems


def check_block_prints_what_it_says(block: str, tmp_path: Path) -> None:
    """Run ``block`` in a fresh interpreter, as a reader pasting it would (default float32, no test config), and
    compare each printed line with its print's stated output."""
    script = tmp_path / "block.py"
    script.write_text(block)
    res = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    printed = res.stdout.splitlines()
    stated = stated_outputs(block)
    assert len(printed) == len(stated), (stated, printed)
    problems = [problem for s, p in zip(stated, printed, strict=True) for problem in compare_line(s, p)]
    assert not problems, "\n".join(problems)
