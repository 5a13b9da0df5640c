"""A Sphinx extension: furo's navigation tree built once per folder of pages instead of once per page.

furo draws the whole toctree, sections pruned (``titles_only``), on every page, and then rewrites it with
BeautifulSoup (a checkbox and a label for every entry with children). To build it Sphinx copies every page's full
table of contents (each API page's object entries included): with the rewrite, the larger part of this site's build.
Two pages of one folder get the same tree but for the marks of the page itself: its own link is relative to itself
and its branch carries the ``current`` class. So the tree is resolved, rendered and rewritten once per folder, for
a name no page has (its links relative to that folder), and each page's copy gets its own marks as Sphinx
(``sphinx.environment.adapters.toctree._toctree_add_classes``) and furo (``furo.navigation.get_navigation_tree``)
write them: ``current`` on the branch's ``<a>``, ``<li>`` and ``<ul>`` tags, ``href="#"`` on its own link,
``checked`` on the checkboxes of the branch and ``current-page`` on its deepest ``<li>``. A tree whose branch holds
any other tag is marked the way Sphinx and furo do it, on a copy of the resolved tree; a call with ``collapse``
(the tree then depends on the page beyond its marks) goes to Sphinx's own function. ``tests/test_docs.py`` builds a
small site with and without this extension and compares every page byte for byte.
"""

from __future__ import annotations

import html
import posixpath
import re
from dataclasses import dataclass, field

from docutils import nodes
from sphinx.environment.adapters.toctree import global_toctree_for_doc

_NAVIGATION: dict[tuple, nodes.Element | None] = {}
_FURO: dict[tuple, _Marked | None] = {}
_FURO_OPTIONS = {"titles_only": True, "maxdepth": -1, "includehidden": True}  # furo's own call, with collapse=False
_TAG = re.compile(r"<(/?)([A-Za-z][A-Za-z0-9]*)((?:[^>\"']|\"[^\"]*\"|'[^']*')*)>")
_VOID = frozenset({"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "wbr"})


@dataclass
class _Tag:
    name: str
    start: int  # offset of "<" in the tree's HTML
    end: int  # offset after ">"
    parent: int  # index of the enclosing tag in _Marked.tags, -1 at the top
    children: list[int] = field(default_factory=list)


@dataclass
class _Marked:
    """furo's rewrite of one folder's unmarked tree, its tags indexed for marking a page's branch."""

    html: str
    tags: list[_Tag]
    links: dict[str, list[int]]  # href (as written) -> indices of the <a> tags with it

    @classmethod
    def parse(cls, text: str) -> _Marked | None:
        tags: list[_Tag] = []
        stack: list[int] = []
        links: dict[str, list[int]] = {}
        for m in _TAG.finditer(text):
            closing, name, attrs = m.group(1), m.group(2).lower(), m.group(3)
            if closing:
                if not stack or tags[stack[-1]].name != name:
                    return None  # not the well-formed markup furo writes
                stack.pop()
                continue
            tags.append(_Tag(name, m.start(), m.end(), stack[-1] if stack else -1))
            index = len(tags) - 1
            if stack:
                tags[stack[-1]].children.append(index)
            if name == "a":
                href = re.search(r'\shref="([^"]*)"', attrs)
                if href:
                    links.setdefault(href.group(1), []).append(index)
            if name not in _VOID and not attrs.endswith("/"):
                stack.append(index)
        return cls(text, tags, links) if not stack else None

    def for_page(self, link: str) -> str | None:
        """The tree as furo draws it on the page whose own link (relative to the folder) is ``link``; None where the
        branch holds a tag this marking does not know."""
        found = self.links.get(html.escape(link, quote=True), [])
        if not found:
            return self.html
        edits: dict[int, str | None] = {}  # tag index -> its new opening tag (None: a tag this marking does not know)
        current_li: list[int] = []
        for a in found:
            edits[a] = _own_link(self._open(a))
            index = self.tags[a].parent
            while index != -1:
                tag = self.tags[index]
                if index not in edits:
                    if tag.name == "li":
                        edits[index] = _with_class(self._open(index), "current", before="has-children")
                        current_li.append(index)
                        box = [c for c in tag.children if self.tags[c].name == "input"]
                        if box:
                            edits[box[0]] = _checked(self._open(box[0]))
                    elif tag.name == "ul":
                        edits[index] = _with_class(self._open(index), "current")
                    else:
                        return None
                index = tag.parent
        if any(text is None for text in edits.values()):
            return None
        deepest = max(current_li, key=lambda i: self.tags[i].start, default=None)
        if deepest is not None:
            edits[deepest] = _with_class(edits[deepest], "current-page")
        out, at = [], 0
        for index in sorted(edits, key=lambda i: self.tags[i].start):
            tag = self.tags[index]
            out += [self.html[at:tag.start], edits[index]]
            at = tag.end
        out.append(self.html[at:])
        return "".join(out)

    def _open(self, index: int) -> str:
        return self.html[self.tags[index].start:self.tags[index].end]


def _with_class(tag: str, name: str, before: str | None = None) -> str | None:
    """``tag`` (an opening tag) with ``name`` added to its class list: at the end, or before ``before`` where that is
    the list's last class (furo appends ``has-children`` after Sphinx's classes); a tag without attributes gets the
    attribute. None for a tag with other attributes but no class."""
    m = re.search(r'\sclass="([^"]*)"', tag)
    if m is None:
        bare = re.fullmatch(r"<([a-z]+)>", tag)
        return f'<{bare.group(1)} class="{name}">' if bare else None
    classes = m.group(1).split()
    if before is not None and classes and classes[-1] == before:
        classes.insert(len(classes) - 1, name)
    else:
        classes.append(name)
    return f'{tag[:m.start(1)]}{" ".join(classes)}{tag[m.end(1):]}'


def _own_link(tag: str) -> str | None:
    """The page's own ``<a>``: ``current`` before its classes (docutils writes the node's classes first) and
    ``href="#"`` (Sphinx's link of a page to itself)."""
    m = re.search(r'\sclass="([^"]*)"', tag)
    if m is None:
        return None
    tag = f'{tag[:m.start(1)]}current {m.group(1)}{tag[m.end(1):]}'
    return re.sub(r'(\shref=")[^"]*(")', r"\1#\2", tag, count=1)


def _checked(tag: str) -> str | None:
    """furo's checkbox of a current entry: ``checked=""`` where BeautifulSoup sorts it (after ``aria-label``)."""
    m = re.match(r'<input aria-label="[^"]*"(?= class=")', tag)
    return f'{m.group(0)} checked=""{tag[m.end():]}' if m else None


def _share_navigation(app, pagename, templatename, context, doctree):
    """Replace the page's ``toctree(**kwargs)`` in ``context`` with the shared one (the module's docstring)."""
    if "toctree" not in context:
        return
    builder, own = app.builder, context["toctree"]
    folder = posixpath.dirname(pagename)
    neutral = posixpath.join(folder, "\x00navigation")

    def resolved(kwargs):
        key = (folder, tuple(sorted(kwargs.items())))
        if key not in _NAVIGATION:
            _NAVIGATION[key] = global_toctree_for_doc(app.env, neutral, builder, tags=builder.tags, collapse=False,
                                                      **kwargs)
        return key, _NAVIGATION[key]

    def options(kwargs):
        kwargs.setdefault("includehidden", False)  # as StandaloneHTMLBuilder._get_local_toctree
        if kwargs.get("maxdepth") == "":
            kwargs.pop("maxdepth")
        return kwargs

    def shared(collapse=True, **kwargs):
        if collapse:
            return own(collapse=collapse, **kwargs)
        _, tree = resolved(options(kwargs))
        if tree is None:
            return builder.render_partial(None)["fragment"]
        tree = tree.deepcopy()
        link = builder.get_relative_uri(neutral, pagename)
        for ref in list(tree.findall(nodes.reference)):
            if ref.get("refuri") != link or ref.get("anchorname"):
                continue
            branch = ref
            while branch is not None and branch is not tree:
                branch["classes"].append("current")
                branch = branch.parent
            ref["refuri"] = builder.get_relative_uri(pagename, pagename)
        return builder.render_partial(tree)["fragment"]

    def furo_tree():
        """furo's navigation tree of this page from the folder's rewritten tree; None where it cannot be marked."""
        from furo.navigation import get_navigation_tree

        key, tree = resolved(options(dict(_FURO_OPTIONS)))
        if key not in _FURO:
            _FURO[key] = _Marked.parse(get_navigation_tree(builder.render_partial(tree)["fragment"]))
        marked = _FURO[key]
        return None if marked is None else marked.for_page(builder.get_relative_uri(neutral, pagename))

    shared.furo_tree = furo_tree
    context["toctree"] = shared


def _furo_navigation(original):
    """furo's ``_compute_navigation_tree(context)``, drawn from the folder's rewritten tree where the page's
    ``toctree`` is this extension's."""

    def compute(context):
        fast = getattr(context.get("toctree"), "furo_tree", None)
        drawn = fast() if fast is not None else None
        return original(context) if drawn is None else drawn

    compute.original = original
    return compute


def setup(app):
    import furo
    import furo.navigation

    compute = getattr(furo, "_compute_navigation_tree", None)
    rewrite = getattr(furo.navigation, "get_navigation_tree", None)
    if callable(compute) and callable(rewrite) and not hasattr(compute, "original"):  # else furo's own path, shared
        furo._compute_navigation_tree = _furo_navigation(compute)
    app.connect("html-page-context", _share_navigation, priority=400)  # before furo's handler (500)
    app.connect("builder-inited", lambda app: (_NAVIGATION.clear(), _FURO.clear()))
    return {"parallel_read_safe": True, "parallel_write_safe": True}
