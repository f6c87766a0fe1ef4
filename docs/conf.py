"""Sphinx configuration of the documentation site: the Markdown pages of docs/ (myst-parser) and the API
reference generated from the docstrings of the front doors (``calib.__all__``, ``optimize.__all__``) and
the application modules of ``iptm``.

    make docs     # sphinx-build -W --keep-going -b html docs docs/_build/html
"""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the packages from the checkout, also without an editable install

import calib  # noqa: E402

project = "iptm"
author = "iptm contributors"
release = calib.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",  # the docstrings' "Parameters" / "Returns" sections
    "sphinx.ext.mathjax",
    "sphinxarg.ext",  # the CLI reference, generated from iptm.cli.build_parser
]
source_suffix = {".md": "markdown"}
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

# GitHub-style heading anchors, so that "page.md#a-heading" links resolve as on GitHub
myst_heading_anchors = 3
myst_enable_extensions = ["colon_fence", "dollarmath"]

autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autosummary_generate = False  # the API pages list their members themselves: no generated stubs in the tree
napoleon_numpy_docstring = True
napoleon_google_docstring = True

try:
    import pydata_sphinx_theme  # noqa: F401

    html_theme = "pydata_sphinx_theme"
    html_theme_options = {"navigation_depth": 2, "show_toc_level": 2}
except ImportError:  # the default theme: the site still builds, only plainer
    html_theme = "alabaster"
html_title = f"iptm {release}"
