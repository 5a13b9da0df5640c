"""The documentation site's inputs are fresh and whole: API pages for every module, every config key, working links.

The Sphinx build itself (``sphinx-build -W``) runs in the README's second
command, not here (it takes minutes). What is checked here, each against a
computation independent of the generator under test:

* ``scripts/api_pages.py`` writes a page for every public module of
  ``selfid_jax``: the modules found by walking the package's folders on disk
  (``os.walk``, following the ``experiments`` link) are exactly those it
  documents, each page runs ``automodule`` on its module, the index lists them
  all, and ``docs/conf.py`` runs the script;
* ``docs/config_reference.md`` is what ``scripts/config_keys.py`` renders, and
  its table for each experiment names every field of that experiment's
  config schema and every field of each nested section;
* every relative link and image of the README and the docs pages resolves to
  a file, and a ``#fragment`` to a heading of that page; every toctree entry
  is a page and every page is in a toctree;
* the Python blocks that the README test used to run (now on the functional
  API page) still print what their comments say (slow tier);
* the build's own extension (``docs/_ext/shared_navigation.py``) leaves every
  page of a small site byte-identical to a build without it (slow tier).
"""

from __future__ import annotations

import importlib.util
import os
import re
import tomllib
import types
import typing
from pathlib import Path

import pytest
from helpers_docs import DOCS, README, ROOT, check_block_prints_what_it_says, doc_pages, python_blocks, stated_outputs
from pydantic import BaseModel

from selfid_jax import runner


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def modules_on_disk() -> set[str]:
    """Public module names of ``selfid_jax`` from its folders: a package is a folder with ``__init__.py``.

    The top-level experiments/ is selfid_jax.experiments (pyproject.toml's package-dir).
    """
    names = set()
    for top, prefix in ((ROOT / "selfid_jax", ("selfid_jax",)), (ROOT / "experiments", ("selfid_jax", "experiments"))):
        for folder, subfolders, files in os.walk(top):
            here = Path(folder)
            if not (here / "__init__.py").exists():
                subfolders[:] = []
                continue
            package = ".".join(prefix + here.relative_to(top).parts)
            if any(part.startswith("_") for part in package.split(".")):
                subfolders[:] = []
                continue
            names.add(package)
            names |= {f"{package}.{f[:-3]}" for f in files if f.endswith(".py") and not f.startswith("_")}
            subfolders[:] = [s for s in subfolders if not s.startswith(("_", "."))]
    return names


# ------------------------------------------------------------------------ API pages


def test_api_pages_cover_every_public_module(tmp_path):
    script = _script("api_pages")
    names = script.public_modules()
    on_disk = modules_on_disk()
    assert {"selfid_jax", "selfid_jax.identify.estimator", "selfid_jax.experiments.common.schema",
            "selfid_jax.runner.sweep"} <= on_disk
    assert set(names) == on_disk, (sorted(on_disk - set(names)), sorted(set(names) - on_disk))
    written = script.write(tmp_path)
    assert written == names
    assert {p.name for p in tmp_path.glob("*.md")} == {f"{n}.md" for n in names} | {"index.md"}
    index = (tmp_path / "index.md").read_text(encoding="utf-8")
    listed = set(re.findall(r"^(selfid_jax[\w.]*)$", index, re.MULTILINE))
    assert listed == set(names)
    for name in names:
        page = (tmp_path / f"{name}.md").read_text(encoding="utf-8")
        assert f".. automodule:: {name}\n" in page and ":members:" in page, name


def test_api_pages_drop_a_page_of_a_removed_module(tmp_path):
    script = _script("api_pages")
    (tmp_path / "selfid_jax.gone.md").write_text("# old\n")
    script.write(tmp_path)
    assert not (tmp_path / "selfid_jax.gone.md").exists()


def test_conf_generates_the_api_pages_and_uses_the_docs_extra():
    conf = (DOCS / "conf.py").read_text(encoding="utf-8")
    assert "api_pages.py" in conf and "module.write()" in conf
    assert '"myst_parser"' in conf and '"sphinx.ext.autodoc"' in conf and 'html_theme = "furo"' in conf
    extra = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["optional-dependencies"]
    assert {re.split(r"[<>=]", r)[0] for r in extra["docs"]} == {"sphinx", "myst-parser", "furo"}
    ignored = (ROOT / ".gitignore").read_text(encoding="utf-8").splitlines()
    assert "docs/_build/" in ignored and "docs/api/" in ignored


# ------------------------------------------------------------------ config reference


def _sections(text: str) -> dict[str, set[str]]:
    """``{section title: keys of its table}`` of docs/config_reference.md."""
    out = {}
    for block in re.split(r"^## ", text, flags=re.MULTILINE)[1:]:
        title, _, body = block.partition("\n")
        out[title.strip()] = set(re.findall(r"^\| `([^`]+)` \|", body, re.MULTILINE))
    return out


def _direct_sections(model: type[BaseModel]) -> dict[str, type[BaseModel]]:
    """Fields of ``model`` whose type is one pydantic model (optionally or null): the nested config sections."""
    out = {}
    for name, field in model.model_fields.items():
        tp = field.annotation
        args = [a for a in typing.get_args(tp) if a is not type(None)] if typing.get_origin(tp) in (
            typing.Union, types.UnionType) else [tp]
        if len(args) == 1 and isinstance(args[0], type) and issubclass(args[0], BaseModel):
            out[name] = args[0]
    return out


def test_config_reference_is_current():
    script = _script("config_keys")
    assert (DOCS / "config_reference.md").read_text(encoding="utf-8") == script.render(), (
        "docs/config_reference.md is out of date: run python scripts/config_keys.py")


def test_config_reference_names_every_field_of_every_experiment_schema():
    sections = _sections((DOCS / "config_reference.md").read_text(encoding="utf-8"))
    entry_points = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))[
        "project"]["entry-points"]["selfid_jax.experiments"]
    assert {"demo", "valid_region", "ablation", "tracking", "design", "articulated"} <= set(entry_points)
    for name in entry_points:
        model = runner.get(name).config
        keys = sections[name]
        top = {k for k in keys if not re.search(r"[.\[ ]", k)}
        assert top == set(model.model_fields), (name, set(model.model_fields) ^ top)
        for field, sub in _direct_sections(model).items():
            for subfield in sub.model_fields:
                assert f"{field}.{subfield}" in keys, (name, f"{field}.{subfield}")
        leaves = {k.rsplit(".", 1)[-1] for k in keys}
        for field, info in model.model_fields.items():
            for arg in getattr(info.annotation, "__args__", ()):
                inner = getattr(arg, "__args__", (arg,))
                for tp in inner:
                    if isinstance(tp, type) and issubclass(tp, BaseModel):
                        assert set(tp.model_fields) <= leaves, (name, field, set(tp.model_fields) - leaves)


def test_config_reference_covers_the_robot_commands():
    sections = _sections((DOCS / "config_reference.md").read_text(encoding="utf-8"))
    from selfid_jax.sessions.online_config import OnlineConfig
    from selfid_jax.sessions.online_sim import RobotSimConfig

    for title, model in (("selfid-jax online", OnlineConfig), ("selfid-jax robot-sim", RobotSimConfig)):
        top = {k for k in sections[title] if not re.search(r"[.\[ ]", k)}
        assert top == set(model.model_fields), title


# ------------------------------------------------------------------------ links


def slug(heading: str) -> str:
    """The anchor GitHub and MyST (``myst_heading_anchors``) give a heading: markup dropped, lower case,
    punctuation but ``-`` and ``_`` removed, spaces as ``-``."""
    text = re.sub(r"[`*]", "", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.DOTALL)
    return {slug(h) for h in re.findall(r"^#{1,6} (.+)$", text, re.MULTILINE)}


def links(path: Path) -> list[str]:
    """Targets of the Markdown links and images of a page, outside code blocks and inline code."""
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.DOTALL)
    text = re.sub(r"`[^`\n]*`", "", text)
    return re.findall(r"!?\[[^\]]*\]\(([^)\s]+)\)", text)


def test_slug_matches_the_documented_rule():
    assert slug("CPU XLA flags") == "cpu-xla-flags"
    assert slug("The real loop's non-idealities (`realism`)") == "the-real-loops-non-idealities-realism"
    assert slug("Refinement methods (Eq. 14)") == "refinement-methods-eq-14"


PAGES = [README] + doc_pages()


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    problems = []
    for target in links(page):
        if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
            continue
        file, _, fragment = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        if not dest.is_file():
            problems.append(f"{target}: no file {dest}")
        elif fragment and dest.suffix == ".md" and fragment not in anchors(dest):
            problems.append(f"{target}: no heading with anchor #{fragment} in {dest.name}")
    assert not problems, problems


def test_link_check_finds_a_broken_link(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# Top\n\n[ok](#top) [bad](missing.md) `[code](x.md)`\n\n```\n[block](y.md)\n```\n")
    assert links(page) == ["#top", "missing.md"]
    assert anchors(page) == {"top"}


def _toctree_entries(page: Path) -> list[str]:
    entries = []
    for block in re.findall(r"```\{toctree\}\n(.*?)```", page.read_text(encoding="utf-8"), re.DOTALL):
        entries += [s.strip() for s in block.splitlines() if s.strip() and not s.startswith(":")]
    return entries


def test_every_page_is_in_a_toctree_and_every_entry_is_a_page():
    included = set()
    for page in doc_pages():
        for entry in _toctree_entries(page):
            target = page.parent / f"{entry}.md"
            if entry == "api/index":  # generated at build time by scripts/api_pages.py (tested above)
                continue
            assert target.is_file(), (page.name, entry)
            included.add(target.resolve())
    pages = {p.resolve() for p in doc_pages()} - {(DOCS / "index.md").resolve()}
    assert pages <= included, sorted(str(p) for p in pages - included)


# -------------------------------------------------------------- moved Python blocks

API_PAGE = DOCS / "api_guide.md"
API_BLOCKS = python_blocks(API_PAGE.read_text(encoding="utf-8"))


def test_the_readme_blocks_moved_to_the_api_page():
    """The two blocks the README test ran (the estimator on a linear robot; self-ID and a star on the UR5e)."""
    assert len(API_BLOCKS) >= 2
    assert "sj.init(" in API_BLOCKS[0] and "sj.self_identify(" in API_BLOCKS[0]
    assert "sj.ur5e(" in API_BLOCKS[1] and "sj.follow(" in API_BLOCKS[1]
    for block in API_BLOCKS:
        assert stated_outputs(block)


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(API_BLOCKS)))
def test_api_page_python_block_prints_what_it_says(index, tmp_path):
    check_block_prints_what_it_says(API_BLOCKS[index], tmp_path)


DRIVER_BLOCKS = python_blocks((DOCS / "drivers.md").read_text(encoding="utf-8"))


@pytest.mark.slow
def test_the_example_driver_self_identifies_and_follows(tmp_path):
    """The driver page's example runs as a reader would paste it: converged, the star completed, the estimate exact."""
    assert len(DRIVER_BLOCKS) == 1 and stated_outputs(DRIVER_BLOCKS[0])
    check_block_prints_what_it_says(DRIVER_BLOCKS[0], tmp_path)


# ------------------------------------------------------------------------ the build's shared navigation tree

_SITE = {
    "index.md": "# Home\n\n```{toctree}\n:caption: Guides\n\nguide\na/index\n```\n\n"
                "```{toctree}\n:caption: Reference\n:titlesonly:\n\nb/ref\n```\n\n"
                "```{toctree}\n:hidden:\n\nb/hidden\n```\n",
    "guide.md": "# Guide\n\n## A section\n\ntext\n\n### A subsection\n\ntext\n",
    "a/index.md": "# Part A\n\n```{toctree}\n\nx\ny\n```\n",
    "a/x.md": "# X\n\n## X's section\n\n```{py:function} f(x)\n\nA function: an object entry in the ToC.\n```\n",
    "a/y.md": "# Y\n\ntext\n",
    "b/ref.md": "# Ref\n\n## Ref's section\n\n```{py:class} C\n```\n",
    "b/hidden.md": "# Hidden\n\ntext\n",
    "b/orphan.md": "---\norphan: true\n---\n\n# Orphan\n\nin no toctree\n",
}


@pytest.mark.slow
def test_shared_navigation_leaves_every_page_byte_identical(tmp_path, monkeypatch):
    """docs/_ext/shared_navigation.py (furo's navigation tree resolved once per folder): a small site with three
    toctrees in its index (captions, titlesonly, hidden), pages in the top folder and two subfolders, a nested
    toctree, sections, object entries and an orphan page builds to the same bytes in every HTML page with the
    extension as without it; the shared trees were used (one per folder) and mark each page's own branch, and furo's
    navigation of every page came from the folder's rewritten tree (marked for the pages in a toctree, as it is for
    the others), never from the fallback."""
    from sphinx.application import Sphinx
    from sphinx.util.docutils import docutils_namespace

    monkeypatch.syspath_prepend(str(ROOT / "docs" / "_ext"))
    import shared_navigation

    drawn = []
    for_page = shared_navigation._Marked.for_page
    monkeypatch.setattr(shared_navigation._Marked, "for_page",
                        lambda self, link: drawn.append((link, result := for_page(self, link), self.html)) or result)
    src = tmp_path / "src"
    for name, text in _SITE.items():
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        (src / name).write_text(text, encoding="utf-8")
    (src / "conf.py").write_text("", encoding="utf-8")
    pages = {}
    for ext in ([], ["shared_navigation"]):
        out = tmp_path / ("shared" if ext else "own")
        conf = {"extensions": ["myst_parser", *ext], "html_theme": "furo", "root_doc": "index"}
        with docutils_namespace():
            app = Sphinx(str(src), str(src), str(out / "html"), str(out / "doctrees"), "html", confoverrides=conf,
                         status=None, warningiserror=True, freshenv=True)
            app.build()
        pages[bool(ext)] = {p.relative_to(out / "html").as_posix(): p.read_bytes()
                            for p in (out / "html").rglob("*.html")}
    assert set(pages[True]) == set(pages[False]) >= {"index.html", "a/x.html", "b/ref.html", "b/orphan.html"}
    differ = [name for name in pages[False] if pages[True][name] != pages[False][name]]
    assert not differ, differ
    assert {key[0] for key in shared_navigation._NAVIGATION} == {"", "a", "b"}
    assert {key[0] for key in shared_navigation._FURO} == {"", "a", "b"}
    assert all(result is not None for _, result, _ in drawn), drawn
    marked = {link for link, result, unmarked in drawn if result != unmarked}
    assert len(drawn) == len(pages[True]), drawn
    assert {"guide.html", "x.html", "y.html", "ref.html", "hidden.html"} <= marked, marked
    x = pages[True]["a/x.html"].decode()
    assert re.search(r'<li class="toctree-l2 current[^"]*"><a class="current reference internal" href="#">X</a>', x), x
