"""What every package has: a licence in the wheel, type information, ``python -m``, shell
completion, a changelog for the version it carries."""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _setuptools_version() -> tuple[int, ...]:
    try:
        text = importlib.metadata.version("setuptools")
    except importlib.metadata.PackageNotFoundError:
        return (0,)
    return tuple(int(x) for x in re.findall(r"\d+", text)[:2])


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    """The wheel pip builds from this checkout, with the venv's setuptools (no download)."""
    if _setuptools_version() < (77,):
        pytest.skip("building the wheel needs setuptools >= 77 (pip install -e '.[dev]')")
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(out), str(ROOT)],
        check=True, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    (built,) = out.glob("usdforest-*.whl")
    return zipfile.ZipFile(built)


def test_the_wheel_carries_the_licence_type_information_and_its_data(wheel):
    names = set(wheel.namelist())
    version = importlib.metadata.version("usdforest")
    info = f"usdforest-{version}.dist-info"
    assert wheel.read(f"{info}/licenses/LICENSE") == (ROOT / "LICENSE").read_bytes()
    licence = (ROOT / "LICENSE").read_text()
    assert "Apache License" in licence and "Version 2.0, January 2004" in licence
    metadata = wheel.read(f"{info}/METADATA").decode()
    assert "License-Expression: Apache-2.0" in metadata and "License-File: LICENSE" in metadata
    assert {"usdforest/py.typed", "usdforest/__main__.py", "usdforest/entry.py"} <= names
    # the data a forest is built from: the default recipe and the templates' layers
    assert "usdforest/pipelines/default.toml" in names
    assert any(n.startswith("usdforest/templates/") and n.endswith(".usdc") for n in names)
    entry = wheel.read(f"{info}/entry_points.txt").decode()
    assert "usdforest = usdforest.entry:main" in entry


def test_python_dash_m_usdforest_is_the_command(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "usdforest", "--version"], capture_output=True, text=True,
        cwd=tmp_path, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1] == importlib.metadata.version("usdforest")
    r = subprocess.run(
        [sys.executable, "-m", "usdforest", "build", "--help"], capture_output=True, text=True,
        cwd=tmp_path, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0 and "Usage: python -m usdforest build" in r.stdout, r.stderr
    assert importlib.util.find_spec("usdforest.py") is None  # py.typed is data, not a module
    assert (Path(importlib.util.find_spec("usdforest").origin).parent / "py.typed").is_file()


def test_shell_completion_offers_commands_and_shipped_recipes(tmp_path):
    """Typer's completion protocol, as the script `usdforest --install-completion` installs
    calls it."""
    from usdforest.recipe import shipped_recipes

    script = Path(sys.executable).parent / "usdforest"
    if not script.exists():
        pytest.skip("no usdforest console script beside this Python (pip install the package)")

    def complete(words: str) -> list[str]:
        env = {**os.environ, "_USDFOREST_COMPLETE": "complete_bash", "COMP_WORDS": words,
               "COMP_CWORD": str(len(words.split()) - 1)}  # fmt: skip
        r = subprocess.run(
            [str(script)], env=env, capture_output=True, text=True, cwd=tmp_path, timeout=120,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr
        return r.stdout.split()

    assert complete("usdforest bui") == ["build"]
    assert complete("usdforest build --fo") == ["--force"]
    expected = sorted(n for n in shipped_recipes() if n.startswith("st"))
    assert len(expected) >= 2 and sorted(complete("usdforest build -p st")) == expected


def test_the_changelog_has_a_section_for_what_comes_next():
    """Keep a Changelog: an Unreleased section and the usual kinds of change."""
    text = (ROOT / "CHANGELOG.md").read_text()
    assert text.startswith("# Changelog")
    assert "https://keepachangelog.com/en/1.1.0/" in text
    sections = re.findall(r"^## \[([^\]]+)\]", text, re.MULTILINE)
    assert sections and sections[0] == "Unreleased"
    kinds = set(re.findall(r"^### (\w+)", text, re.MULTILINE))
    assert kinds <= {"Added", "Changed", "Deprecated", "Removed", "Fixed", "Security"}
    assert {"Added", "Fixed"} <= kinds
