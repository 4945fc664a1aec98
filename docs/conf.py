"""Sphinx configuration of the sb3-dipper documentation (``make docs`` builds it offline, warnings as errors)."""

import os
import sys

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
source_suffix = {".rst": "restructuredtext"}
exclude_patterns = ["_build", "benchmarks", "tasks", "research", "**/_*.rst", "Thumbs.db", ".DS_Store"]
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
