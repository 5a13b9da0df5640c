"""A Sphinx extension: furo's navigation tree resolved once per folder of pages instead of once per page.

furo draws the whole toctree, sections pruned (``titles_only``), on every page. To build it Sphinx copies every
page's full table of contents (each API page's object entries included): the larger part of this site's build.
Two pages of one folder get the same tree but for the marks of the page itself: its own link is relative to itself
and its branch carries the ``current`` class. So the tree is resolved once per folder, for a name no page has (its
links relative to that folder), and each page takes a copy with its own branch marked as Sphinx marks it
(``sphinx.environment.adapters.toctree._toctree_add_classes``). A call with ``collapse`` (the tree then depends on
the page beyond its marks) goes to Sphinx's own function. ``tests/test_docs.py`` builds a small site with and
without this extension and compares every page byte for byte.
"""

from __future__ import annotations

import posixpath

from docutils import nodes
from sphinx.environment.adapters.toctree import global_toctree_for_doc

_NAVIGATION: dict[tuple, nodes.Element | None] = {}


def _share_navigation(app, pagename, templatename, context, doctree):
    """Replace the page's ``toctree(**kwargs)`` in ``context`` with the shared one (the module's docstring)."""
    if "toctree" not in context:
        return
    builder, own = app.builder, context["toctree"]
    folder = posixpath.dirname(pagename)
    neutral = posixpath.join(folder, "\x00navigation")

    def shared(collapse=True, **kwargs):
        if collapse:
            return own(collapse=collapse, **kwargs)
        kwargs.setdefault("includehidden", False)  # as StandaloneHTMLBuilder._get_local_toctree
        if kwargs.get("maxdepth") == "":
            kwargs.pop("maxdepth")
        key = (folder, tuple(sorted(kwargs.items())))
        if key not in _NAVIGATION:
            _NAVIGATION[key] = global_toctree_for_doc(app.env, neutral, builder, tags=builder.tags, collapse=False,
                                                      **kwargs)
        tree = _NAVIGATION[key]
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

    context["toctree"] = shared


def setup(app):
    app.connect("html-page-context", _share_navigation, priority=400)  # before furo's handler (500)
    app.connect("builder-inited", lambda app: _NAVIGATION.clear())
    return {"parallel_read_safe": True, "parallel_write_safe": True}
