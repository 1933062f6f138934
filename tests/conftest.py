"""Shared fixtures: the CLI runner and the optional ../shared folder."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
CAD_SAMPLES = SHARED / "cad-samples"


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
    for path in found:
        try:
            read_recipe(path)
        except (UsdForestError, OSError) as exc:
            bad.append(f"{path}: {exc}")
    assert not bad, "written recipes that do not load back:\n" + "\n".join(bad)


@pytest.fixture(scope="session")
def shipped(tmp_path_factory):
    """``shipped(name)``: the shipped recipe ``name`` built once a session (with its
    thumbnail), as ``(forest.usda, ForestBuild)``. Several test files read the default forest
    and the 1 ha stand; each build takes a minute or more. Tests only read it."""
    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.usd.forest import write_forest

    built = {}

    def build(name: str):
        if name not in built:
            out = tmp_path_factory.mktemp(f"shipped-{name}") / "forest.usda"
            recipe = read_recipe(default_recipe_path().parent / f"{name}.toml")
            built[name] = (out, write_forest(recipe, out))
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
