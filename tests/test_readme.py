"""README.md and the docs pages tell the truth: Python blocks print what their comments say, the Layout page is the
tree, the names, paths and commands they mention exist.

The README's content moved into the documentation site (``docs/``, issue 26);
every check here reads the README and the docs pages it moved to. The
README's own Python block runs here; the blocks of the docs pages run in
``tests/test_docs.py`` with the same rule.

Stated outputs: every ``print(...)`` line of a README or docs Python block ends in a comment that is
exactly the line it prints; the rule that compares them is ``tests/helpers_docs.py``'s.

The README's block takes about 6 s, the functional API page's two about 30 s
and 45 s on the 2 shared CPU cores (most of it compiling and dispatching), so
running them is marked slow; parsing the blocks, the Layout check and the name
checks are in the fast tier.
"""

import importlib
import re
import sys

import pytest
from helpers_docs import (
    DOCS,
    README,
    ROOT,
    check_block_prints_what_it_says,
    compare_line,
    doc_pages,
    number_agrees,
    python_blocks,
    stated_outputs,
)

README_TEXT = README.read_text(encoding="utf-8")
# The README and every docs page, which hold what the README used to.
TEXT = "\n".join([README_TEXT] + [p.read_text(encoding="utf-8") for p in doc_pages()])
BLOCKS = python_blocks(README_TEXT)


def test_readme_has_python_blocks():
    assert len(BLOCKS) >= 1
    assert len(BLOCKS[0].strip().splitlines()) <= 12, "the README's API example is about ten lines"


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_block_states_its_outputs(index):
    """Every block prints something, and each print says what it prints."""
    assert stated_outputs(BLOCKS[index])


def test_tolerance_rule():
    assert number_agrees("8", "8") and not number_agrees("8", "9")
    assert number_agrees("1.8e-07", "1.7881393e-07") and not number_agrees("6e-06", "1.7881393e-07")
    assert number_agrees("1.8e-07", "1e-06") and not number_agrees("1.8e-07", "-1.8e-07")
    assert number_agrees("1.1", "1.2") and not number_agrees("1.1", "1.3")
    assert number_agrees("1.00", "1.00") and not number_agrees("1.00", "0.89")
    assert number_agrees("0.0", "0.04") and not number_agrees("0.0", "0.1")
    assert compare_line("(3, 3) (50, 3, 3) 5", "(3, 3) (50, 3, 3) 5") == []
    assert compare_line("True 1e-07", "False 1e-07") and compare_line("(3, 3)", "(3, 4)")


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_python_block_prints_what_it_says(index, tmp_path):
    check_block_prints_what_it_says(BLOCKS[index], tmp_path)


def test_readme_cli_subcommands_exist():
    from selfid_jax.cli import commands as package_commands
    from selfid_jax.runner.command_line import _parser

    commands = set(re.findall(r"^selfid-jax ([\w-]+)", TEXT, re.MULTILINE))
    known = set(_parser(package_commands())._subparsers._group_actions[0].choices)  # as selfid_jax.cli adds them
    assert commands and commands <= known, commands - known


@pytest.mark.slow
def test_readme_layout_is_the_tree():
    """docs/layout.md equals what scripts/readme_layout.py generates from the tree (every module, no stale path)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import readme_layout
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    page = (DOCS / "layout.md").read_text(encoding="utf-8")
    assert readme_layout.section(page) == readme_layout.render() and page == readme_layout.page(), (
        "docs/layout.md is out of date: run python scripts/readme_layout.py --write"
    )


def _resolve(dotted: str):
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for part in parts[i:]:
            obj = getattr(obj, part)
        return obj
    raise ImportError(dotted)


def test_readme_names_exist():
    """Every ``selfid_jax.x.y`` and ``sj.x`` the README and docs name resolves (no old module path survives a move)."""
    names = set(re.findall(r"\bselfid_jax(?:\.[A-Za-z_]\w*)+", TEXT))
    names |= {"selfid_jax" + name[2:] for name in re.findall(r"\bsj(?:\.[A-Za-z_]\w*)+", TEXT)}
    missing = []
    for name in sorted(names):
        try:
            _resolve(name)
        except (ImportError, AttributeError) as err:
            missing.append(f"{name}: {err}")
    assert not missing, missing


# Paths the README and docs name as things a command writes, not files of the repository.
WRITTEN = {"benchmarks/results.json", "docs/_build/html", "docs/_build/html/index.html", "docs/api/*.md"}


def test_readme_paths_exist():
    """Every repository path the README and docs name exists: ``(_full)`` names both configs, ``<name>`` any name."""
    tops = "|".join(["selfid_jax", "experiments", "scripts", "configs", "benchmarks", "docs", "tests", r"\.ci"])
    paths = set(re.findall(rf"(?<![\w/.])((?:{tops})/(?:[\w./*-]|\(_full\)|<\w+>)*[\w*>])", TEXT)) - WRITTEN
    assert len(paths) > 10, paths
    missing = []
    for path in sorted(paths):
        path = re.sub(r"<\w+>", "*", path)
        for variant in {path.replace("(_full)", ""), path.replace("(_full)", "_full")}:
            if not (list(ROOT.glob(variant)) if "*" in variant else (ROOT / variant).exists()):
                missing.append(variant)
    assert not missing, missing


def test_ci_runs_exactly_the_readme_commands():
    """The README's two Quick-start commands: the first installs and runs the demo; ``.ci/run`` runs the second,
    which builds the docs with warnings as errors; the getting-started page gives the same two."""
    quick = README_TEXT.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    commands = re.findall(r"```bash\n(.+?)\n```", quick)
    assert len(commands) == 2 and commands[0] == "pip install . && selfid-jax demo", commands
    assert "sphinx-build -W --keep-going -q -b html docs docs/_build/html" in commands[1]
    assert '".[test,docs]"' in commands[1]
    ci_lines = [s.strip() for s in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert commands[1] in ci_lines, commands[1]
    started = re.findall(r"```bash\n(.+?)\n```", (DOCS / "getting_started.md").read_text(encoding="utf-8"))
    assert started[:2] == commands, started


def test_readme_is_short_and_links_the_docs():
    """The README is an entry point: under 100 lines, linking every hand-written docs page."""
    assert len(README_TEXT.splitlines()) < 100
    linked = {ROOT / target for target in re.findall(r"\]\((docs/[^)#\s]+)", README_TEXT)}
    pages = {p for p in doc_pages()}
    unlinked = sorted(str(p.relative_to(ROOT)) for p in pages - linked - {DOCS / "index.md"})
    assert not unlinked, f"the README's Documentation list does not link {unlinked}: add them there"
