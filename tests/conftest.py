"""Shared fixtures: the CLI runner and the optional ../shared folder."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
CAD_SAMPLES = SHARED / "cad-samples"


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


@pytest.fixture
def cad_samples() -> Path:
    if not (CAD_SAMPLES / "Tree_2.obj").is_file():
        pytest.skip("../shared/cad-samples is not available on this machine")
    return CAD_SAMPLES
