"""Whole-tree decomposition: the shared CAD samples (skipped without ../shared) and models
authored here with known branch positions."""

from __future__ import annotations

import json
import math
import tomllib

import numpy as np
import pytest
import synthetic_trees as syn

from usdforest.cad.extract import extract_tree
from usdforest.cli import app
from usdforest.usd.validate import validate


def test_tree_2_broadleaf(cad_samples):
    ex = extract_tree(cad_samples / "Tree_2.obj")
    assert ex.units == "m" and ex.up_axis == "+Y" and ex.wood_by == "names"
    assert ex.height == pytest.approx(5.434, abs=0.01)
    # the limb fused into the trunk component is split off at the fork: the trunk ends there
    assert ex.trunk.measurements.length == pytest.approx(3.77, abs=0.1)
    assert 0.1 < ex.trunk.measurements.base_radius < 0.4
    orders = [b.order for b in ex.branches]
    assert orders.count(1) == 4 and orders.count(2) == 3
    for b in ex.branches:
        # no branch reads as pointing down: second-order ones grow from their limb
        assert b.angle_to_trunk < 90
        if b.order == 2:
            parent = ex.branches[b.parent]
            assert parent.order == 1
            d = np.array(parent.tip) - np.array(parent.base)
            u = (np.array(b.base) - np.array(parent.base)) @ d / (d @ d)
            assert 0.0 < u < 1.0  # its base lies along its parent
    heights = np.array([b.insertion_height for b in ex.branches])
    assert np.all((heights > 3.0) & (heights < ex.height))
    assert len(ex.clumps) == 28
    p = ex.profile()
    assert p["branches"]["count"] == 7 and p["foliage"]["clumps"] == 28
    assert 2.0 < p["tree"]["crown_base_height"] < 4.0
    assert p["tree"]["crown_diameter"] > 4.0


def test_pine_1_conifer(cad_samples):
    ex = extract_tree(cad_samples / "Pine_1.obj")
    assert ex.up_axis == "+Y"
    assert ex.height == pytest.approx(7.58, abs=0.01)
    assert len(ex.clumps) == 43 and len(ex.branches) == 0
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
    names = sorted(p.name for p in out.iterdir())
    assert names[:2] == ["branch.usdc", "clump_0.usdc"]
    assert names[-2:] == ["profile.toml", "trunk.usdc"]
    profile = tomllib.loads((out / "profile.toml").read_text())
    assert profile["branches"]["count"] == 7
    assert len(profile["branches"]["bases"]) == 7
    assert len(profile["foliage"]["clump_centres"]) == 28
    for layer in out.glob("*.usdc"):
        assert validate(layer) == []
    r = runner.invoke(app, ["template", "extract", str(cad_samples / "Tree_2.obj"), "-o", str(out)])
    assert r.exit_code == 2 and "--force" in r.stderr


def _match(ex, model):
    """Each true branch with the extracted one whose base is nearest (the tree's base is the
    origin in both: the synthetic trunk starts upright at (0, 0, 0))."""
    got = np.array([b.base for b in ex.branches])
    pairs = []
    for i, b in enumerate(model.branches):
        j = int(np.argmin(np.linalg.norm(got - b.base, axis=1)))
        pairs.append((i, j))
    assert len({j for _, j in pairs}) == len(model.branches), "two branches matched one"
    return pairs


@pytest.mark.parametrize("leaves", [True, False])
def test_extraction_recovers_known_branches(tmp_path, leaves):
    """A model authored here: every branch's base within 2 cm, direction within 2 degrees,
    length within 2 cm, and its parent right; clumps counted and grouped by shape."""
    model = syn.broadleaf(leaves=leaves)
    ex = extract_tree(syn.write_obj(model, tmp_path / "tree.obj"))
    assert ex.up_axis == "+Y" and ex.units == "m"
    assert len(ex.branches) == len(model.branches)
    pairs = dict(_match(ex, model))
    for i, b in enumerate(model.branches):
        e = ex.branches[pairs[i]]
        assert np.linalg.norm(np.array(e.base) - b.base) <= 0.02, (i, e.base, b.base)
        d = np.array(e.tip) - np.array(e.base)
        cos = float(d @ b.direction) / np.linalg.norm(d)
        assert math.degrees(math.acos(min(cos, 1.0))) <= 2.0, i
        assert e.length == pytest.approx(b.length, abs=0.02)
        assert e.angle_to_trunk == pytest.approx(math.degrees(math.acos(b.direction[2])), abs=2)
        want_parent = -1 if b.parent < 0 else pairs[b.parent]
        assert e.parent == want_parent and e.order == (1 if b.parent < 0 else 2)
    if leaves:
        assert len(ex.clumps) == len(model.clumps)
        assert len(ex.clump_templates) == 2  # round and flattened clumps
    else:
        assert ex.clumps == () and ex.clump_templates == ()
        assert ex.profile()["foliage"]["clumps"] == 0


def test_leafless_models_extract(tmp_path, runner):
    import trimesh

    trimesh.creation.cylinder(radius=0.2, height=5).export(tmp_path / "pole.stl")
    r = runner.invoke(
        app, ["template", "extract", str(tmp_path / "pole.stl"), "-o", str(tmp_path / "o")]
    )
    assert r.exit_code == 0, r.output
    assert "0 foliage clumps" in r.stdout
    profile = tomllib.loads((tmp_path / "o" / "profile.toml").read_text())
    assert profile["foliage"]["clumps"] == 0
    assert profile["trunk"]["length"] == pytest.approx(5.0, abs=0.01)
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["profile.toml", "trunk.usdc"]
