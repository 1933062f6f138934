"""The documentation: the site builds without warnings, the getting-started page runs as
written, the recipe reference names every key the recipe reader accepts, and the README stays
short and its links lead somewhere."""

from __future__ import annotations

import ast
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _needs_sphinx() -> None:
    missing = [m for m in ("sphinx", "myst_parser", "furo") if importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"the docs need {', '.join(missing)}: pip install -e '.[docs]'")


def test_the_site_builds_without_a_warning(tmp_path):
    """What ``make docs`` runs: Sphinx with warnings as errors (broken links and anchors,
    docstrings that do not parse, pages outside the table of contents)."""
    _needs_sphinx()
    out = tmp_path / "html"
    r = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(DOCS),
         str(out), "-d", str(tmp_path / "doctrees")],
        capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-4000:]
    for page in ("index", "getting-started", "guide/sensors", "reference/cli", "reference/api",
                 "reference/recipe", "reference/modules", "changelog"):  # fmt: skip
        assert (out / f"{page}.html").is_file(), page
    api = (out / "reference" / "api.html").read_text(encoding="utf-8")
    assert 'id="usdforest.api.build_forest"' in api and 'id="usdforest.api.fly"' in api
    cli = re.sub(r"<[^>]+>", "", (out / "reference" / "cli.html").read_text(encoding="utf-8"))
    assert all(f"usdforest {c}" in cli for c in ("build", "scan", "fly", "wrap", "stats"))


def _blocks(page: Path, language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```", page.read_text(), re.MULTILINE | re.DOTALL)


def test_the_getting_started_examples_run_as_written(tmp_path):
    """Every Python block of the getting-started page, in order, in one fresh process in an
    empty folder."""
    blocks = _blocks(DOCS / "getting-started.md", "python")
    assert len(blocks) >= 5
    script = tmp_path / "getting_started.py"
    script.write_text("\n".join(blocks))
    r = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=900
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "quick.usda").is_file() and (tmp_path / "pine.usda").is_file()


def _recipe_keys() -> set[str]:
    """Every key the recipe reader checks: its *_KEYS sets and the literal sets it passes to
    check_keys (read from the source, so a key added there is a key this test asks for)."""
    source = (ROOT / "usdforest" / "recipe.py").read_text()
    keys: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id.endswith("_KEYS") for t in node.targets
        ):
            keys |= set(ast.literal_eval(node.value))
        if (
            isinstance(node, ast.Call)
            and getattr(node.func, "id", "") == "check_keys"
            and isinstance(node.args[1], ast.Set)
        ):
            keys |= set(ast.literal_eval(node.args[1]))
    # tables whose keys are their spec's fields
    from dataclasses import fields

    from usdforest.grow.groundcover import GroundCoverSpec
    from usdforest.grow.sway import WindSpec
    from usdforest.grow.understorey import RegenerationSpec, ShrubSpec

    for spec in (GroundCoverSpec, ShrubSpec, RegenerationSpec, WindSpec):
        keys |= {f.name for f in fields(spec)}
    return keys


def test_the_recipe_reference_names_every_key_the_reader_accepts():
    keys = _recipe_keys()
    assert {"region", "intensity", "forest", "lod", "layer", "hard_core", "sites"} <= keys
    text = (DOCS / "recipe-table.md").read_text() + (DOCS / "reference" / "recipe.md").read_text()
    code = re.findall(r"^```[a-z]*\n(.*?)^```", text, re.MULTILINE | re.DOTALL)
    code += re.findall(r"`([^`\n]+)`", text)
    named = {w for c in code for w in re.findall(r"[a-z_][a-z0-9_]*", c)}
    assert sorted(keys - named) == []


def test_the_readme_is_short_and_its_links_lead_somewhere():
    text = (ROOT / "README.md").read_text()
    assert len(text.split()) <= 1500
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [x for x in links if "://" not in x]
    assert len(local) >= 10
    assert [x for x in local if not (ROOT / x).exists()] == []
    assert not re.search(r"\bissue \d+", text, re.IGNORECASE)


def test_the_trees_guide_names_every_species_preset():
    from usdforest.grow.species import PRESETS

    text = (DOCS / "guide" / "trees.md").read_text()
    assert [n for n in PRESETS if f"`{n}`" not in text] == []
