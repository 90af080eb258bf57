"""Sphinx configuration of magkf's documentation: the Markdown pages of docs/ and the API reference.

Build (no network needed): ``.venv/bin/python -m sphinx -W --keep-going -b html docs docs/_build/html``.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import magkf  # noqa: E402

project = "magkf"
author = "magkf contributors"
copyright = "magkf contributors"
version = release = magkf.__version__

extensions = ["sphinx.ext.autodoc", "numpydoc", "myst_parser"]
# No intersphinx: the documentation is built without network access.

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
# docs/examples/ holds files the pages link to (a column map, an effect file), not pages.
exclude_patterns = ["_build", "examples", "Thumbs.db", ".DS_Store"]

html_theme = "alabaster"
html_title = f"magkf {release}"
# wide enough for the code (lines of up to 120 characters) and the tables of interfaces and options
html_theme_options = {"page_width": "1320px", "body_max_width": "none", "sidebar_width": "240px"}

# ---------------------------------------------------------------- Markdown pages (MyST)
# The pages link to each other's sections (``data-contract.md#turntable-run-sine-fit``): anchors for
# headings down to level 3, slugged as GitHub does, so the same links work on GitHub and here.
myst_heading_anchors = 3

# ---------------------------------------------------------------- API reference (autodoc, numpydoc)
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_preserve_defaults = True
# Classes list their methods through autodoc's ``:members:``, not numpydoc's summary tables.
numpydoc_show_class_members = False
numpydoc_attributes_as_param_list = True
numpydoc_xref_param_type = False
# numpydoc's validation is off in the build: the plug-in interfaces' docstrings (filters, measurement models,
# effects, readers; ``MeasurementModel``'s methods among them) do not all have Parameters and Returns sections
# yet. The rest of the public API passes
# ``python -m numpydoc validate magkf.<module>.<name>`` for GL08, PR01, PR02 and RT01, but for two false
# positives: the signature of an enum (``Status``) and a function whose parameter is named ``cls``
# (``register_measurement``), which numpydoc drops from the signature.

# ---------------------------------------------------------------- warnings
# docs/data-contract.md sketches the JSON files' layout with placeholders (``[A, C_deg, D]``, ``{...}``) in
# ``json`` blocks: not valid JSON, so Pygments highlights them in its relaxed mode and says so. That
# message only, not other warnings.
suppress_warnings = ["misc.highlighting_failure"]
