"""NVIDIA's asset validator (usd-validation-nvidia, its CLI) reports 0 failures and 0 warnings
on what ``tree`` and ``build`` write. It lives in its own venv (``make test`` installs it in
``.venv-validate``); without it these tests skip and say so."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from optional import optional_tool

from usdforest.grow.species import get_species
from usdforest.recipe import default_recipe_path, parse_recipe, read_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.tree import write_tree


def _validator() -> str:
    return optional_tool("USDFOREST_NVIDIA_VALIDATE", "usd-validation-nvidia", ".venv-validate")


def _check(exe: str, stage: Path) -> None:
    r = subprocess.run([exe, str(stage)], capture_output=True, text=True, check=False, timeout=1200)
    text = r.stdout + r.stderr
    assert r.returncode == 0 and "No issues found" in text, text[-3000:]


@pytest.mark.parametrize("species", ["pine", "broadleaf", "paper-rule-2"])
def test_trees_pass_nvidias_validator(tmp_path, species):
    exe = _validator()
    out = tmp_path / "t.usda"
    write_tree(get_species(species), out, seed=2, colliders="wood")
    _check(exe, out)


def test_a_forest_with_ground_colliders_and_physics_scene_passes(tmp_path):
    exe = _validator()
    base = read_recipe(default_recipe_path().parent / "paper-two-tree-stand.toml")
    data = dict(
        base.data,
        ground={"kind": "plane", "margin": 2.0},
        forest={**base.data["forest"], "physics_scene": True, "lod": "medium"},
    )
    out = tmp_path / "f.usda"
    write_forest(parse_recipe(data, base.base, base.source), out)
    _check(exe, out)


def test_a_forest_on_a_raster_height_field_passes(tmp_path):
    """The height field's arrays go to their own crate layer (ground.usdc): no ASCII
    performance failure, and its collider and label pass the physics and semantics rules."""
    import numpy as np

    exe = _validator()
    x = np.linspace(-2.0, 12.0, 15)
    gx, gy = np.meshgrid(x, x[::-1])
    np.save(tmp_path / "dem.npy", 0.2 * gx + np.sin(gy))
    base = read_recipe(default_recipe_path().parent / "paper-two-tree-stand.toml")
    data = dict(base.data, ground={"kind": "raster", "file": "dem.npy", "margin": 2.0})
    out = tmp_path / "f.usda"
    write_forest(parse_recipe(data, tmp_path, str(tmp_path / "r.toml")), out)
    _check(exe, out)


@pytest.mark.parametrize("season", ["winter", "summer"])
def test_a_windy_forest_passes(tmp_path, season):
    """The wind layer's time samples (orientations and orientationsf over the instancer, the
    root's time codes) pass, over a winter stand's leafless broadleaves and over a summer's
    fluttering leaves (the flutter classes, their sibling leaf prototypes and each leaf's
    class)."""
    exe = _validator()
    base = read_recipe(default_recipe_path().parent / "paper-two-tree-stand.toml")
    wind = {"speed": 8.0, "duration": 1.0, "fps": 24.0}
    data = dict(base.data, season=season, wind=wind)
    out = tmp_path / "f.usda"
    write_forest(parse_recipe(data, base.base, base.source), out)
    _check(exe, out)
