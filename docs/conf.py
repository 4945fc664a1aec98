"""Sphinx configuration of the sb3-dipper documentation (``make docs`` builds it offline, warnings as errors)."""

import os
import sys
from pathlib import Path

from docutils import nodes
from sphinx import addnodes

# Headless MuJoCo for the executed examples; set before anything imports mujoco.
os.environ.setdefault("MUJOCO_GL", "egl")

sys.path.insert(0, os.path.abspath(".."))

# After sys.path: the checkout's package (it also registers the env ids the examples use).
import sb3_dipper

project = "sb3-dipper"
author = "sb3-dipper contributors"
copyright = "2026, sb3-dipper contributors"
version = release = sb3_dipper.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.doctest",
    "sphinx.ext.mathjax",
    # MathJax 3 from its PyPI package, copied into the site (_static/mathjax): math renders with no network.
    "sphinx-mathjax-offline",
    "sphinx.ext.viewcode",
    "myst_parser",
]

# Nothing is fetched, neither at build time (no intersphinx) nor when a page is viewed (MathJax is in the site).
# The pages are reST; the research log (research/*.md, dated entries written for GitHub) is published as MyST Markdown,
# its pages in the hidden toctree of benchmarks.rst.
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "benchmarks", "tasks", "**/_*.rst", "Thumbs.db", ".DS_Store"]
master_doc = "index"

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_description_target = "documented"
autodoc_class_signature = "mixed"
autodoc_inherit_docstrings = True
# The library is type-checked by mypy; forward references in annotations need not resolve for the docs.
autodoc_type_aliases: dict[str, str] = {}

# The executed examples: one thread (tiny networks), quiet, fixed seeds.
doctest_global_setup = """
import os
import warnings
# SB3's reminder when a replay buffer is loaded to resume (the guide's recipe truncates on purpose).
warnings.filterwarnings("ignore", message="The last trajectory in the replay buffer will be truncated")
os.environ.setdefault("MUJOCO_GL", "egl")
import torch as th
th.set_num_threads(1)
"""

html_theme = "sphinx_rtd_theme"
html_title = f"sb3-dipper {release}"
html_static_path: list[str] = []
html_show_sourcelink = False

myst_heading_anchors = 3
# Markdown written for GitHub does not always start at "#" or go down one level at a time: BENCHMARKS.md, included
# below its "# Benchmarks" title, starts at "##", as do two research-log entries, and one goes from "#" to "###". MyST
# nests them as they read on GitHub. This warning type is only about heading levels: a missing document, anchor or
# image still fails the build.
suppress_warnings = ["myst.header"]


# ---------------------------------------------------------------------------------------------------- repository Markdown
# benchmarks.rst includes the repository's BENCHMARKS.md (myst parser). Its links and images are relative to the
# repository root, as GitHub reads them, while MyST resolves them relative to the page that includes it. Below, the
# targets that MyST left unresolved in Markdown included from outside the page are read relative to that Markdown file:
# a site page becomes a link to it (with its anchor), another file a download copied into the site, a folder (the site
# lists none) its plain text; a target that does not exist stays unresolved and fails the build. Every MyST heading anchor
# (``myst_heading_anchors``) is also a label ``<docname>#<slug>`` for ``:ref:`` (e.g. ``benchmarks#speed``).


def _included_markdown(node: nodes.Element, page: Path) -> Path | None:
    """The Markdown file ``node`` was read from, if the page included it from elsewhere."""
    source = Path(os.path.abspath(node.source)) if node.source else None  # docutils keeps an include's path relative
    return source if source is not None and source.suffix == ".md" and source != page else None


def _local(target: str) -> bool:
    return bool(target) and not target.startswith(("#", "/")) and ":" not in target.partition("/")[0]


def _reroot_included_markdown(app, doctree: nodes.document) -> None:
    env = app.env
    docname = env.current_document.docname
    page = Path(env.doc2path(docname))
    for image in doctree.findall(nodes.image):
        source = _included_markdown(image, page)
        if source is not None and _local(image["uri"]):
            image["uri"] = Path(os.path.relpath(source.parent / image["uri"], page.parent)).as_posix()
    for xref in list(doctree.findall(addnodes.pending_xref)):
        source = _included_markdown(xref, page)
        if xref.get("reftype") != "myst" or xref.get("refdomain") is not None or source is None:
            continue
        path_text, _, anchor = xref["reftarget"].partition("#")
        if not _local(path_text):
            continue
        path = Path(os.path.normpath(source.parent / path_text))
        children = [child.deepcopy() for child in xref.children] if xref.astext() else [nodes.literal(path_text, path_text)]
        common = {"refdoc": docname, "reftype": "myst", "refexplicit": xref.get("refexplicit", False)}
        target_doc = env.path2doc(str(path)) if path.is_file() else None
        if target_doc in env.found_docs:
            link = addnodes.pending_xref(
                "", *children, refdomain="doc", reftarget=target_doc, reftargetid=anchor or None, **common
            )
        elif path.is_file():
            relative = Path(os.path.relpath(path, page.parent)).as_posix()
            link = addnodes.download_reference("", *children, refdomain=None, reftarget=relative, **common)
        elif path.is_dir():
            link = nodes.inline("", "", *children)
        else:
            continue
        link.source, link.line = xref.source, xref.line
        xref.replace_self(link)


def _label_heading_anchors(app, doctree: nodes.document) -> None:
    env = app.env
    docname = env.current_document.docname
    std = env.domains.standard_domain
    for slug, (_line, section_id, title) in env.metadata[docname].get("myst_slugs", {}).items():
        name = nodes.fully_normalize_name(f"{docname}#{slug}")
        std.anonlabels[name] = docname, section_id
        std.labels[name] = docname, section_id, title


def setup(app) -> None:
    # Before the image and download collectors (priority 500) read the targets.
    app.connect("doctree-read", _reroot_included_markdown, priority=400)
    app.connect("doctree-read", _label_heading_anchors)
