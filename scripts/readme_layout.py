"""Generate docs/layout.md from the source tree: one line per module or folder, its one job.

Each line is a module's (or a package folder's ``__init__.py``'s) first
docstring line, read with ``ast`` (nothing is imported). The subpackages of
``selfid_jax/`` come bottom layer first, in the order of the import-linter
layers contract in ``pyproject.toml``; inside a folder, modules come first
(alphabetical), then subfolders. Folders without an ``__init__.py`` take their
line from ``FOLDERS`` below; a new one is an error until it is described there.

    python scripts/readme_layout.py          # print the page
    python scripts/readme_layout.py --write  # write docs/layout.md
    python scripts/readme_layout.py --check  # exit 1 if docs/layout.md differs

``tests/test_readme.py`` checks that docs/layout.md equals this script's
output. (The name is historical: the Layout section was README.md's.)
"""

from __future__ import annotations

import argparse
import ast
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "layout.md"
HEADING = "# Layout"

# Folders that are not Python packages: their one job, stated here.
FOLDERS = {
    "selfid_jax/systems/assets": "the shipped MJCF models ({files}), every dimension in each file's header",
    "selfid_jax/math/_native": "C++ sources of selfid_jax.math.native's kernels ({files}; the XLA FFI headers in "
    "xla/ffi/api/), built by setup.py",
    "selfid_jax/robot/data": "the shipped example log ({files}) of selfid-jax fit --example, made by "
    "scripts/make_example_log.py",
    "scripts": "studies and maintenance scripts run from a checkout (not installed)",
    "configs": "sweep configs by experiment, configs/<experiment>/ (small defaults; *_full.yaml at paper scale or "
    "larger), robot/ for selfid-jax online and robot-sim, studies/gap/ for scripts/gap_study.py; installed as "
    "selfid_jax.configs",
    "benchmarks": "scripts that print ratios against a baseline run in the same process",
    "docs": "the documentation site (Sphinx, MyST, furo: conf.py, the pages and their figures); api/ is generated at "
    "build time by scripts/api_pages.py; _ext/ holds the build's own Sphinx extension (shared_navigation)",
    "tests": 'pytest (float64, strict rank promotion); -m "not slow" is the fast tier',
}
# Folders listed with their own modules; the others are one line each.
EXPANDED = ("selfid_jax", "experiments", "scripts")
SKIP = {"__pycache__"}


def first_line(path: Path) -> str:
    """The first docstring line (its summary paragraph) of a module, with reST markup reduced to plain text."""
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
    if not doc:
        raise SystemExit(f"{path.relative_to(ROOT)} has no module docstring: its first line states its one job")
    lines = doc.strip().split("\n\n", 1)[0].splitlines()  # the summary, which a wrapped docstring spreads over lines
    line = " ".join(s.strip() for s in lines)
    # reST roles as Sphinx shows them: :func:`a.b.c` -> a.b.c, :func:`~a.b.c` -> c
    line = re.sub(r":\w+:`(~?)([\w.]+)`", lambda m: m[2].rsplit(".", 1)[-1] if m[1] else m[2], line)
    return line.replace("``", "")


def _layer_order() -> list[str]:
    """Subpackage names of ``selfid_jax`` bottom layer first, from the layers contract."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    for contract in config.get("tool", {}).get("importlinter", {}).get("contracts", []):
        if contract.get("type") == "layers":
            names = []
            for layer in reversed(contract["layers"]):
                names += [name.strip().removeprefix("selfid_jax.") for name in layer.split("|")]
            return names
    return []


def _folder_job(rel: str, folder: Path) -> str:
    if rel in FOLDERS:  # a data folder (configs/ is a data package: its __init__.py only names it)
        files = ", ".join(sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix != ".py"))
        return FOLDERS[rel].format(files=files)
    if (folder / "__init__.py").exists():
        return first_line(folder / "__init__.py")
    raise SystemExit(f"{rel}/ is neither a package nor described in FOLDERS of scripts/readme_layout.py")


def _walk(folder: Path, depth: int, rows: list[tuple[str, str]]) -> None:
    rel = folder.relative_to(ROOT).as_posix()
    indent = "  " * depth
    rows.append((f"{indent}{folder.name}/", _folder_job(rel, folder)))
    if rel not in EXPANDED and (rel in FOLDERS or not (folder / "__init__.py").exists()):
        return
    for module in sorted(folder.glob("*.py")):
        if module.name != "__init__.py":
            rows.append((f"{indent}  {module.name}", first_line(module)))
    subfolders = [p for p in folder.iterdir() if p.is_dir() and p.name not in SKIP and not p.name.startswith(".")]
    order = _layer_order() if rel == "selfid_jax" else []
    subfolders.sort(key=lambda p: (order.index(p.name) if p.name in order else len(order), p.name))
    for sub in subfolders:
        _walk(sub, depth + 1, rows)


def layout_rows() -> list[tuple[str, str]]:
    """(indented name, one job) per module and folder, in page order."""
    rows: list[tuple[str, str]] = []
    for name in EXPANDED:
        _walk(ROOT / name, 0, rows)
    for name in FOLDERS:
        if "/" not in name and name not in EXPANDED:
            _walk(ROOT / name, 0, rows)
    return rows


def render() -> str:
    """The page's body: a short note, then one fenced block with one line per module or folder."""
    rows = layout_rows()
    width = max(len(name) for name, _ in rows) + 2
    lines = [f"{name:<{width}}{job}".rstrip() for name, job in rows]
    intro = (
        "One line per module or folder, saying its one job: each module's first docstring line, generated by\n"
        "`python scripts/readme_layout.py --write` (`tests/test_readme.py` checks that this page is current).\n"
        "Subpackages run bottom layer first (the import-linter layers in `pyproject.toml`); each module's\n"
        "functions are in the API reference.\n\n"
    )
    return intro + "```text\n" + "\n".join(lines) + "\n```\n"


def page() -> str:
    """The whole of docs/layout.md: its heading, then :func:`render`'s body."""
    return f"{HEADING}\n\n" + render()


def section(text: str) -> str:
    """The body of a page's Layout section (after its heading, up to the next heading of that level or the end)."""
    level = HEADING.split()[0]
    match = re.search(rf"^{re.escape(HEADING)}\n\n(.*?)(?=^{level} |\Z)", text, re.DOTALL | re.MULTILINE)
    if match is None:
        raise SystemExit(f"{OUT.relative_to(ROOT)} has no {HEADING!r} section")
    return match.group(1).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--write", action="store_true", help="write docs/layout.md")
    mode.add_argument("--check", action="store_true", help="exit 1 if docs/layout.md is out of date")
    args = parser.parse_args(argv)
    text = page()
    if not (args.write or args.check):
        sys.stdout.write(text)
        return 0
    if args.check:
        if not OUT.exists() or OUT.read_text(encoding="utf-8") != text:
            print("docs/layout.md is out of date: run python scripts/readme_layout.py --write", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
