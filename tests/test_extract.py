"""Whole-tree decomposition on the two shared CAD samples (skipped without ../shared)."""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest

from usdforest.cli import app
from usdforest.extract import extract_tree
from usdforest.validate import validate


def test_tree_2_broadleaf(cad_samples):
    ex = extract_tree(cad_samples / "Tree_2.obj")
    assert ex.units == "m" and ex.up_axis == "+Y" and ex.wood_by == "names"
    assert ex.height == pytest.approx(5.434, abs=0.01)
    assert len(ex.branches) == 6
    assert len(ex.clumps) == 28
    # the trunk part stands upright: its length is its height (forks fused to it included)
    assert ex.trunk.measurements.length == pytest.approx(4.83, abs=0.02)
    assert 0.1 < ex.trunk.measurements.base_radius < 0.4
    heights = np.array([b.insertion_height for b in ex.branches])
    assert np.all((heights > 2.0) & (heights < ex.height))
    p = ex.profile()
    assert p["branches"]["count"] == 6 and p["foliage"]["clumps"] == 28
    assert 2.0 < p["tree"]["crown_base_height"] < 4.0
    assert p["tree"]["crown_diameter"] > 4.0


def test_pine_1_conifer(cad_samples):
    ex = extract_tree(cad_samples / "Pine_1.obj")
    assert ex.up_axis == "+Y"
    assert ex.height == pytest.approx(7.58, abs=0.01)
    assert len(ex.clumps) == 43
    assert ex.trunk.measurements.length == pytest.approx(7.58, abs=0.05)
    assert ex.profile()["tree"]["crown_base_height"] >= 0.0


def test_explicit_units_and_up(cad_samples):
    ex = extract_tree(cad_samples / "Pine_1.obj", units="cm", up="Y")
    assert ex.height == pytest.approx(0.0758, abs=1e-4)


def test_extract_cli_writes_templates_and_profile(cad_samples, tmp_path, runner):
    out = tmp_path / "tree2"
    r = runner.invoke(
        app, ["template", "extract", str(cad_samples / "Tree_2.obj"), "-o", str(out), "--json"]
    )
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["foliage"]["clumps"] == 28
    assert sorted(p.name for p in out.iterdir()) == [
        "branch.usdc",
        "clump.usdc",
        "profile.toml",
        "trunk.usdc",
    ]
    profile = tomllib.loads((out / "profile.toml").read_text())
    assert profile["branches"]["count"] == 6
    assert len(profile["branches"]["lengths"]) == 6
    for layer in out.glob("*.usdc"):
        assert validate(layer) == []
    r = runner.invoke(app, ["template", "extract", str(cad_samples / "Tree_2.obj"), "-o", str(out)])
    assert r.exit_code == 2 and "--force" in r.stderr


def test_extract_refuses_a_model_without_foliage(tmp_path, runner):
    import trimesh

    trimesh.creation.cylinder(radius=0.2, height=5).export(tmp_path / "pole.stl")
    r = runner.invoke(
        app, ["template", "extract", str(tmp_path / "pole.stl"), "-o", str(tmp_path / "o")]
    )
    assert r.exit_code == 2 and "no foliage" in r.stderr
    assert not (tmp_path / "o").exists()
