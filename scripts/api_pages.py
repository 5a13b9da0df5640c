"""Generate the API reference pages docs/api/*.md: one autodoc page per public module of selfid_jax, found by pkgutil.

Every module and package under ``selfid_jax`` whose dotted name has no
component starting with ``_`` gets a page ``docs/api/<dotted name>.md`` that
runs Sphinx's ``automodule`` on it; ``docs/api/index.md`` lists them, one
toctree per top-level subpackage, bottom layer first (the import-linter
layers contract of ``pyproject.toml``). ``docs/conf.py`` runs this script at
every build, so a module added to the package has its page without any edit;
the pages are build outputs (``docs/api/`` is ignored by git).

    python scripts/api_pages.py          # write docs/api/ (what docs/conf.py does)
    python scripts/api_pages.py --list   # print the documented module names, one per line

``tests/test_docs.py`` checks that the pages cover every module pkgutil finds.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import pkgutil
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "api"
PACKAGE = "selfid_jax"


def public_modules(package: str = PACKAGE) -> list[str]:
    """Dotted names of ``package`` and every module and subpackage under it with no ``_``-prefixed component."""
    pkg = importlib.import_module(package)
    names = [package]
    # selfid_jax.experiments is the top-level experiments/ (pyproject.toml's package-dir), not a folder of the
    # package's own path in a checkout: walked by its own path
    extra = [importlib.import_module(f"{package}.experiments")] if package == PACKAGE else []
    for mod in (pkg, *extra):
        if mod is not pkg:
            names.append(mod.__name__)
        for info in pkgutil.walk_packages(mod.__path__, prefix=f"{mod.__name__}."):
            if not any(part.startswith("_") for part in info.name.split(".")):
                names.append(info.name)
    return sorted(set(names))


def _layer_order() -> list[str]:
    """Subpackage names of ``selfid_jax``, bottom layer first, from the layers contract of ``pyproject.toml``."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    for contract in config.get("tool", {}).get("importlinter", {}).get("contracts", []):
        if contract.get("type") == "layers":
            return [name.strip().removeprefix("selfid_jax.") for layer in reversed(contract["layers"])
                    for name in layer.split("|")]
    return []


def _group(name: str) -> str:
    """The top-level subpackage a module belongs to (``""`` for ``selfid_jax`` and its direct modules)."""
    parts = name.split(".")
    if len(parts) < 2:
        return ""
    top = f"{PACKAGE}.{parts[1]}"
    return parts[1] if importlib.util.find_spec(top).submodule_search_locations else ""


def module_page(name: str) -> str:
    """The MyST source of one module's page: its name as title, then ``automodule`` with its members.

    A module documents the members it defines (its ``__all__`` may re-export others, documented where they are
    defined). A package's page shows what it re-exports (its ``__all__``: ``sj.init`` and the like) without
    indexing it again, so each object has one indexed description, on its defining module's page.
    """
    is_package = importlib.util.find_spec(name).submodule_search_locations is not None
    option = "   :no-index:\n" if is_package else "   :ignore-module-all:\n"
    return (
        f"# `{name}`\n\n"
        "```{eval-rst}\n"
        f".. automodule:: {name}\n"
        "   :members:\n"
        "   :show-inheritance:\n"
        f"{option}"
        "```\n"
    )


def index_page(names: list[str]) -> str:
    """The MyST source of ``docs/api/index.md``: one toctree per subpackage, bottom layer first."""
    groups: dict[str, list[str]] = {}
    for name in names:
        groups.setdefault(_group(name), []).append(name)
    order = [""] + _layer_order()
    keys = sorted(groups, key=lambda g: (order.index(g) if g in order else len(order), g))
    lines = [
        "# API reference",
        "",
        "Generated at every build by `scripts/api_pages.py` from the package itself: one page per public module",
        "of `selfid_jax` (every module `pkgutil` finds whose name has no `_`-prefixed part), each the module's",
        "docstring and its members' docstrings. Subpackages run bottom layer first, as in the",
        "[layout](../layout.md). The [functional API guide](../api_guide.md) shows how the pieces fit.",
        "",
    ]
    for key in keys:
        caption = f"{PACKAGE}.{key}" if key else PACKAGE
        lines += ["```{toctree}", f":caption: {caption}", ":maxdepth: 1", ""]
        lines += groups[key]
        lines += ["```", ""]
    return "\n".join(lines)


def write(out: Path = OUT) -> list[str]:
    """Write every page into ``out`` (removing pages of modules that no longer exist); returns the module names."""
    names = public_modules()
    out.mkdir(parents=True, exist_ok=True)
    wanted = {f"{name}.md": module_page(name) for name in names}
    wanted["index.md"] = index_page(names)
    for stale in out.glob("*.md"):
        if stale.name not in wanted:
            stale.unlink()
    for file, text in wanted.items():
        path = out / file
        if not path.exists() or path.read_text(encoding="utf-8") != text:  # unchanged pages keep their mtime
            path.write_text(text, encoding="utf-8")
    return names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="print the documented module names instead of writing")
    args = ap.parse_args(argv)
    if args.list:
        print("\n".join(public_modules()))
        return 0
    names = write()
    print(f"wrote {len(names) + 1} pages into {OUT.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
