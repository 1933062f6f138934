"""Sphinx configuration: the documentation site built from this repository (`make docs`).

Pages are MyST Markdown; the API reference comes from the docstrings (autodoc, numpy style
through napoleon); the CLI reference is generated from the typer app on every build.
"""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version as _version
from pathlib import Path

HERE = Path(__file__).resolve().parent

project = "usdforest"
author = "the usdforest maintainers"
copyright = "2026, the usdforest maintainers"
release = _version("usdforest")
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "sphinx_copybutton",
]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "notes", "recipe-table.md", "**/.ipynb_checkpoints"]
myst_heading_anchors = 3
myst_enable_extensions = ["colon_fence", "deflist"]
suppress_warnings = ["myst.header"]  # pages moved from one README start at level 2

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_format = "short"
autodoc_default_options = {"members": True, "show-inheritance": True}
napoleon_numpy_docstring = True
napoleon_google_docstring = False

html_theme = "furo"
html_title = f"usdforest {release}"
html_static_path: list[str] = []


def _cli_reference() -> None:
    """docs/reference/cli.md from the typer app itself, so it cannot drift from --help."""
    typer = Path(sys.executable).parent / "typer"
    command = [str(typer)] if typer.exists() else [sys.executable, "-m", "typer"]
    out = HERE / "reference" / "cli.md"
    subprocess.run(
        [*command, "usdforest.cli", "utils", "docs", "--name", "usdforest", "--title",
         "Command-line reference", "--output", str(out)],
        check=True, capture_output=True, text=True,
    )  # fmt: skip


_cli_reference()


def _literal_bars(app, what, name, obj, options, lines: list[str]) -> None:
    """Docstrings write formulas with |x| for a magnitude; to reStructuredText a bar opens a
    substitution. They are literal bars here (no docstring uses an RST table)."""
    lines[:] = [line.replace("|", r"\|") for line in lines]


def setup(app) -> None:
    app.connect("autodoc-process-docstring", _literal_bars)
