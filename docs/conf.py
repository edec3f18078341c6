"""Sphinx configuration of the lfstudy documentation.

Build (warnings are errors; the tutorial is executed)::

    pip install -e ".[docs]"
    sphinx-build -W --keep-going -b html docs docs/_build/html

``LFSTUDY_DOCS_EXECUTE=cache`` reuses the tutorial's outputs while its code is unchanged
(jupyter-cache under docs/_build/.jupyter_cache); ``off`` skips executing it. The default,
``force``, runs it on every build, as CI does.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS / "_ext"))

import lfstudy  # noqa: E402

project = "lfstudy"
author = "the lfstudy developers"
copyright = "the lfstudy developers"
release = lfstudy.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "myst_nb",
    "lfstudy_docs",
]

source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
root_doc = "index"
exclude_patterns = ["_build", "_ext", "Thumbs.db", ".DS_Store", "**.ipynb_checkpoints"]
templates_path: list[str] = []

# -- autodoc / napoleon (numpydoc-style docstrings) -------------------------------------
autosummary_generate = False  # the API pages are written by lfstudy_docs (one page per stage)
autodoc_member_order = "bysource"
autodoc_typehints = "none"  # the numpydoc sections carry the types
autodoc_default_options = {"show-inheritance": False}
autodoc_mock_imports: list[str] = []
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_ivar = True
napoleon_use_rtype = False
napoleon_preprocess_types = False
add_module_names = False

# -- MyST / MyST-NB ----------------------------------------------------------------------
myst_enable_extensions = ["colon_fence", "deflist", "dollarmath"]
myst_heading_anchors = 3
nb_execution_mode = os.environ.get("LFSTUDY_DOCS_EXECUTE", "force")
nb_execution_timeout = 1200  # the tutorial's study: a few minutes on 2 cores
nb_execution_raise_on_error = True  # a failing cell fails the build
nb_execution_show_tb = True
nb_execution_cache_path = str(DOCS / "_build" / ".jupyter_cache")
nb_merge_streams = True

# The tutorial copies its study's report here; published beside the pages as tutorial-report.html.
_EXTRA = DOCS / "_build" / "tutorial_site"
_EXTRA.mkdir(parents=True, exist_ok=True)
html_extra_path = [str(_EXTRA)]

# -- HTML ---------------------------------------------------------------------------------
html_theme = "furo"
html_title = f"lfstudy {release}"
html_static_path: list[str] = []
html_show_sourcelink = False
