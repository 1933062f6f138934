"""Shared fixtures: the CLI runner and the optional ../shared folder."""

from __future__ import annotations

import json
from pathlib import Path

import forestcache
import pytest
from durations import HEAVY_SECONDS
from durations import OUT as DURATIONS
from typer.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
CAD_SAMPLES = SHARED / "cad-samples"


def pytest_collection_modifyitems(config, items):
    """Mark ``heavy`` the tests that read a shipped forest or took at least
    ``durations.HEAVY_SECONDS`` when last measured (``tests/durations.json``), and put the
    files that took longest first: pytest-xdist hands whole files out in this order, so the
    longest start at once and the short ones fill in at the end. Every worker collects the
    same order; a file's tests keep theirs."""
    measured = json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}
    tests, files = measured.get("tests", {}), measured.get("files", {})
    for item in items:
        if "shipped" in item.fixturenames or tests.get(item.nodeid, 0.0) >= HEAVY_SECONDS:
            item.add_marker(pytest.mark.heavy)
    items.sort(key=lambda item: -files.get(item.nodeid.split("::")[0], 0.0))


@pytest.fixture(scope="session", autouse=True)
def scene_cache(tmp_path_factory) -> Path:
    """The scene cache of every test (and of the commands they run) in a folder of the
    session's own, not the user's ~/.cache."""
    import os

    folder = tmp_path_factory.mktemp("scene-cache")
    saved = os.environ.get("USDFOREST_CACHE")
    os.environ["USDFOREST_CACHE"] = str(folder)
    yield folder
    if saved is None:
        os.environ.pop("USDFOREST_CACHE", None)
    else:
        os.environ["USDFOREST_CACHE"] = saved


@pytest.fixture(scope="session", autouse=True)
def every_written_recipe_loads_back(tmp_path_factory):
    """After the whole session: every ``pipeline.toml`` a test's build wrote (the record a
    forest keeps of its resolved recipe) loads back as a recipe, so any forest can be built
    again from its own record."""
    yield
    from usdforest.errors import UsdForestError
    from usdforest.recipe import read_recipe

    base = tmp_path_factory.getbasetemp()
    bad = []
    found = sorted(base.rglob("*_assets/pipeline.toml"))
    shared = forestcache.run_folder(base)
    if shared.is_dir():  # the forests the run's processes share, those whose build finished
        for done in shared.glob(f"*/{forestcache.DONE}"):
            found += sorted(done.parent.glob("out/*_assets/pipeline.toml"))
    for path in found:
        try:
            read_recipe(path)
        except (UsdForestError, OSError) as exc:
            bad.append(f"{path}: {exc}")
    assert not bad, "written recipes that do not load back:\n" + "\n".join(bad)


@pytest.fixture(scope="session")
def forest_folder(tmp_path_factory) -> Path:
    """The folder of the forests this run's pytest processes share (:mod:`forestcache`)."""
    return forestcache.run_folder(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="session")
def shipped(forest_folder):
    """``shipped(name)``: the shipped recipe ``name`` built once a run by whichever pytest
    process asks first, as ``(forest.usda, ForestBuild)``: the default with its thumbnail,
    as ``make forest`` builds it, the others without (18 s of the 1 ha stand's 81 s build,
    and no test looks at their thumbnails). Several test files read the default forest and
    the 1 ha stand; each build takes a minute or more. Tests only read it."""
    built = {}

    def build(name: str):
        if name not in built:
            thumbnail = name == "default"
            built[name] = forestcache.shipped_forest(forest_folder, name, thumbnail=thumbnail)
        return built[name]

    return build


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


@pytest.fixture
def cad_samples() -> Path:
    if not (CAD_SAMPLES / "Tree_2.obj").is_file():
        pytest.skip("../shared/cad-samples is not available on this machine")
    return CAD_SAMPLES
