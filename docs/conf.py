"""Sphinx configuration of the lanefree_sumo documentation (``make docs``; warnings are errors)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

project = "lanefree_sumo"
author = "the lanefree_sumo developers"
copyright = "2026, the lanefree_sumo developers"
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.viewcode", "sphinxarg.ext"]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
html_theme = "furo"
html_title = "lanefree_sumo"
html_static_path = ["_static"]
html_css_files = ["tables.css"]  # the wide result tables in a smaller font
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3
autodoc_member_order = "bysource"
autodoc_inherit_docstrings = False  # gymnasium's and SB3's own docstrings are theirs to format
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": False}
# the optional heavy imports stay optional for readers of the API: autodoc imports the modules
autodoc_mock_imports = ["libsumo", "traci", "sumolib"]
nitpicky = False
suppress_warnings = ["myst.header"]


def _generated_config_reference() -> None:
    """docs/_generated/config.md: every config key with its default, unit, range and meaning, from the
    code (``lanefree config``'s text), so the reference can never drift from the defaults."""
    from lanefree_sumo.config import LaneFreeConfig
    from lanefree_sumo.config.describe import describe_config

    out = Path(__file__).parent / "_generated"
    out.mkdir(exist_ok=True)
    text = describe_config(LaneFreeConfig())
    (out / "config.yaml").write_text(text)


_generated_config_reference()


def _escape_bars(app, what, name, obj, options, lines: list[str]) -> None:  # noqa: ANN001
    """The docstrings write absolute values as |x| (plain text), which reST reads as substitutions:
    escape every bar outside inline literals."""
    for k, line in enumerate(lines):
        pieces = line.split("``")
        lines[k] = "``".join(p if i % 2 else p.replace("|", "\\|") for i, p in enumerate(pieces))


def setup(app):  # noqa: ANN001, ANN201
    app.connect("autodoc-process-docstring", _escape_bars)
