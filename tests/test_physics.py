"""Colliders: UsdPhysics schemas read back with pxr, and a real engine (newton, CPU) stopping
a ball at a trunk of a built forest and letting one pass between the trees."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from optional import optional_tool
from physics_probe import roll as roll_ball
from pxr import Usd, UsdGeom, UsdPhysics

from usdforest.grow.species import get_species
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.tree import write_tree
from usdforest.usd.validate import validate

PIPELINES = default_recipe_path().parent


def _two_trees(**forest):
    """The paper's two-tree stand with ``[forest]`` settings added."""
    from usdforest.recipe import parse_recipe

    base = read_recipe(PIPELINES / "paper-two-tree-stand.toml")
    data = dict(base.data, forest={**base.data.get("forest", {}), **forest})
    return parse_recipe(data, base.base, base.source)


def _capsules(stage: Usd.Stage) -> list[Usd.Prim]:
    return [p for p in stage.Traverse() if p.IsA(UsdGeom.Capsule)]


@pytest.mark.parametrize(("mode", "at_least"), [("trunk", 1), ("wood", 2), ("none", 0)])
def test_tree_colliders_read_back(tmp_path, mode, at_least):
    out = tmp_path / "t.usda"
    b = write_tree(get_species("paper-rule-2"), out, seed=3, colliders=mode)
    stage = Usd.Stage.Open(str(out))
    caps = [
        p
        for p in Usd.PrimRange(stage.GetPrimAtPath("/Tree"), Usd.TraverseInstanceProxies())
        if p.IsA(UsdGeom.Capsule)
    ]
    if mode == "none":
        assert caps == [] and not stage.GetPrimAtPath("/Tree/Colliders")
        return
    assert len(caps) >= at_least
    trunk = stage.GetPrimAtPath("/Tree/Colliders/Trunk")
    for c in caps:
        assert c.HasAPI(UsdPhysics.CollisionAPI)
        assert UsdGeom.Imageable(c).ComputePurpose() == UsdGeom.Tokens.guide
    cap = UsdGeom.Capsule(trunk)
    r, h = cap.GetRadiusAttr().Get(), cap.GetHeightAttr().Get()
    m = np.asarray(UsdGeom.Xformable(trunk).ComputeLocalToWorldTransform(0))
    axis = m[2, :3] / np.linalg.norm(m[2, :3])
    bottom = m[3, :3] - axis * (h / 2 + r)
    top = m[3, :3] + axis * (h / 2 + r)
    # the capsule covers the trunk from the ground to its top, as thick as its base
    assert abs(bottom[2]) < 1e-3
    t = stage.GetPrimAtPath("/Tree/Trunk")
    assert r == pytest.approx(t.GetAttribute("usdforest:radius").Get(), rel=1e-6)
    tip = np.array(t.GetAttribute("usdforest:tip").Get())
    assert np.linalg.norm(top - tip) < 1e-3
    assert b.colliders is not None and len(b.colliders) == len(caps)


def test_forest_collision_layer_and_optional_physics_scene(tmp_path):
    recipe = read_recipe(PIPELINES / "paper-two-tree-stand.toml")
    out = tmp_path / "f.usda"
    write_forest(recipe, out, thumbnail=False)
    stage = Usd.Stage.Open(str(out))
    world = [p for p in _capsules(stage) if str(p.GetPath()).startswith("/Forest/Colliders/")]
    assert len(world) == 2  # one trunk capsule per tree, outside the instancer
    with (tmp_path / "f_assets" / "trees.csv").open() as f:
        rows = list(csv.DictReader(f))
    for p, row in zip(sorted(world, key=lambda p: p.GetName()), rows, strict=True):
        c = np.asarray(UsdGeom.Xformable(p).ComputeLocalToWorldTransform(0))[3, :3]
        assert np.hypot(c[0] - float(row["x"]), c[1] - float(row["y"])) < 0.05
    assert not [p for p in stage.Traverse() if p.IsA(UsdPhysics.Scene)]  # not imposed
    write_forest(_two_trees(physics_scene=True), tmp_path / "g.usda", thumbnail=False)
    s = Usd.Stage.Open(str(tmp_path / "g.usda"))
    assert [p.GetPath() for p in s.Traverse() if p.IsA(UsdPhysics.Scene)] == [
        "/Forest/PhysicsScene"
    ]


def _physics_python() -> str:
    return optional_tool("USDFOREST_PHYSICS_PYTHON", "newton", ".venv-physics", "newton")


def test_newton_stops_a_ball_at_a_trunk_of_a_built_forest(tmp_path):
    py = _physics_python()
    out = tmp_path / "f.usda"
    write_forest(read_recipe(PIPELINES / "paper-two-tree-stand.toml"), out, thumbnail=False)
    with (tmp_path / "f_assets" / "trees.csv").open() as f:
        first = next(csv.DictReader(f))
    x0, y0 = float(first["x"]), float(first["y"])

    def roll(y: float, stage: Path = out) -> dict:
        return roll_ball(py, stage, (x0 - 2.0, y, 1.0), (3, 0, 0), 2)

    hit = roll(y0)
    radius = 0.2 + 0.16  # ball + trunk capsule
    assert hit["position"][0] < x0 - radius + 0.05, hit  # stopped at the trunk
    free = roll(y0 - 2.0)  # 2 m to the side of it, clear of both trees
    assert free["position"][0] == pytest.approx(x0 - 2.0 + 3 * 2, abs=0.05), free
    # the physics layer alone (colliders, no visual meshes): the same colliders, the same roll
    physics = tmp_path / "f_assets" / "physics.usda"
    assert validate(physics) == []
    alone = roll(y0, physics)  # newton made 150 shapes of the whole forest, visual meshes too
    assert (alone["position"], alone["velocity"]) == (hit["position"], hit["velocity"])
    assert hit["colliders"] > alone["colliders"]
    stage = Usd.Stage.Open(str(physics))
    assert not [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) or p.IsA(UsdGeom.PointInstancer)]
    forest = Usd.Stage.Open(str(out))
    placed = forest.GetPrimAtPath("/Forest/Colliders").GetChildren()
    assert len(_capsules(stage)) == len(placed) == alone["colliders"] >= 2


def test_default_forest_stands_on_a_labelled_ground_collider(shipped):
    recipe = read_recipe(default_recipe_path())
    g = recipe.ground
    assert (g["kind"], g["margin"], g["color"]) == ("plane", 5.0, (0.36, 0.3, 0.22))
    out, _ = shipped("default")
    stage = Usd.Stage.Open(str(out))
    mesh = stage.GetPrimAtPath("/Forest/Ground/Mesh")
    assert mesh.IsA(UsdGeom.Mesh) and mesh.HasAPI(UsdPhysics.CollisionAPI)
    # the default's ground vegetation lies on leaf litter
    assert list(mesh.GetAttribute("semantics:labels:class").Get()) == ["ground", "litter"]
    pts = np.asarray(UsdGeom.Mesh(mesh).GetPointsAttr().Get(), dtype=float)
    # the plane covers the plot (100 m x 100 m) with its 5 m margin
    assert pts[:, :2].min(axis=0) == pytest.approx([-5, -5]) and pts[:, 2].max() == 0
    assert pts[:, :2].max(axis=0) == pytest.approx([105, 105])
    # every tree stands on it: a ray down from above each trunk meets the ground at the
    # tree's own z
    import trimesh

    faces = np.asarray(UsdGeom.Mesh(mesh).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    assert len(faces) == 2
    tri = trimesh.Trimesh(pts, faces)
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    pos = np.asarray(pi.GetPositionsAttr().Get(), dtype=float)
    origins = pos + np.array([0.0, 0.0, 50.0])
    hits, rays, _ = tri.ray.intersects_location(origins, np.tile([0, 0, -1.0], (len(pos), 1)))
    assert len(np.unique(rays)) == len(pos)
    assert np.allclose(hits[np.argsort(rays)][:, 2], pos[:, 2], atol=1e-6)


def test_ground_settings_are_checked(tmp_path):
    from usdforest.errors import RecipeError
    from usdforest.recipe import parse_recipe

    base = read_recipe(PIPELINES / "paper-two-tree-stand.toml")
    for ground, fragment in (
        ({"kind": "hill"}, "ground.kind"),
        ({"color": [2, 0, 0]}, "ground.color"),
        ({"margin": -1}, "ground.margin"),
        ({"height": 1}, "height"),
    ):
        with pytest.raises(RecipeError, match=fragment):
            parse_recipe(dict(base.data, ground=ground), base.base, base.source)


def test_centred_origin_and_asset_info(tmp_path):

    write_forest(_two_trees(origin="centre"), tmp_path / "f.usda", thumbnail=False)
    stage = Usd.Stage.Open(str(tmp_path / "f.usda"))
    root = stage.GetPrimAtPath("/Forest")
    assert Usd.ModelAPI(root).GetAssetName() == "f"
    cache = UsdGeom.XformCache()
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    world = (
        np.asarray(pi.GetPositionsAttr().Get(), dtype=float)
        + np.asarray(cache.GetLocalToWorldTransform(pi.GetPrim()))[3, :3]
    )
    # the 10 m x 10 m plot's centre is the stage origin: trees at (3, 5) and (7.5, 5.5)
    assert world[:, :2] == pytest.approx(np.array([[-2.0, 0.0], [2.5, 0.5]]), abs=1e-6)


def test_a_tree_written_as_usda_keeps_its_data_in_a_crate_file(tmp_path):
    import shutil

    from usdforest.usd.validate import validate

    out = tmp_path / "a" / "t.usda"
    write_tree(get_species("broadleaf"), out, seed=1)
    assert out.stat().st_size < 2000  # a thin interface
    data = tmp_path / "a" / "t_assets" / "tree.usdc"
    assert data.read_bytes()[:8] == b"PXR-USDC"
    # self-contained: the folder moves and still validates and composes every leaf
    shutil.move(str(tmp_path / "a"), str(tmp_path / "b"))
    moved = tmp_path / "b" / "t.usda"
    assert validate(moved) == []
    stage = Usd.Stage.Open(str(moved))
    # the tree's own leaves and each limb's
    leaves = sum(
        len(UsdGeom.PointInstancer(p).GetPositionsAttr().Get())
        for p in stage.Traverse()
        if p.IsA(UsdGeom.PointInstancer) and p.GetName() == "Leaves"
    )
    assert leaves > 1000


def _composed_counts(stage: Usd.Stage, purposes=("default", "render")) -> tuple[int, int]:
    """(triangles of every Mesh of ``purposes`` once, leaf instances) on the composed stage."""
    tris = leaves = 0
    for p in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies()):
        if p.IsA(UsdGeom.Mesh) and UsdGeom.Imageable(p).ComputePurpose() in purposes:
            counts = UsdGeom.Mesh(p).GetFaceVertexCountsAttr().Get()
            tris += int(np.sum(np.asarray(counts) - 2)) if counts is not None else 0
        elif p.IsA(UsdGeom.PointInstancer) and p.GetName() in ("Leaves", "LeafClusters"):
            leaves += len(UsdGeom.PointInstancer(p).GetProtoIndicesAttr().Get() or [])
    return tris, leaves


def test_lod_variants_switch_without_rebuilding(tmp_path):
    out = tmp_path / "t.usda"
    b = write_tree(get_species("broadleaf"), out, seed=1)
    counts = {}
    for level in ("full", "medium", "proxy"):
        stage = Usd.Stage.Open(str(out))
        tree = stage.GetPrimAtPath("/Tree")
        assert tree.GetVariantSets().GetNames() == ["lod"]
        assert tree.GetVariantSet("lod").GetVariantSelection() == "full"
        stage.SetEditTarget(stage.GetSessionLayer())  # a viewer's switch, file untouched
        tree.GetVariantSet("lod").SetVariantSelection(level)
        assert not stage.GetCompositionErrors()
        counts[level] = _composed_counts(stage)
    assert counts["full"][1] == b.placement.n_leaves
    assert counts["medium"][1] == (b.placement.n_leaves + 7) // 8  # clusters of 8
    assert counts["proxy"][1] == 0
    assert counts["proxy"][0] <= 1000  # the proxy's triangle budget: stem + crown hull
    assert counts["full"][0] > counts["proxy"][0]
    # beside the full tree, the same proxy with purpose proxy: a viewer showing proxies
    # draws it, a renderer draws the render-purpose tree
    stage = Usd.Stage.Open(str(out))
    assert _composed_counts(stage, ("proxy",))[0] == counts["proxy"][0]
    for name, purpose in [("Trunk", "render"), ("Branches", "render"), ("Leaves", "render")]:
        assert UsdGeom.Imageable(stage.GetPrimAtPath(f"/Tree/{name}")).ComputePurpose() == purpose
    assert UsdGeom.Imageable(stage.GetPrimAtPath("/Tree/Proxy/Crown")).ComputePurpose() == "proxy"
    # extentsHint per purpose (default, render, proxy, guide) as pxr computes it
    purposes = ["default", "render", "proxy", "guide"]
    for level in ("full", "medium", "proxy"):
        cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), purposes)
        stage.SetEditTarget(stage.GetSessionLayer())
        tree = stage.GetPrimAtPath("/Tree")
        tree.GetVariantSet("lod").SetVariantSelection(level)
        authored = np.array(tree.GetAttribute("extentsHint").Get(), dtype=float)
        computed = np.array(UsdGeom.ModelAPI(tree).ComputeExtentsHint(cache), dtype=float)
        assert authored.shape[0] >= 2 and authored.shape == computed.shape, level
        big = np.abs(computed) > 1e30  # an empty purpose
        assert np.array_equal(big, np.abs(authored) > 1e30), level
        # pxr bounds instancers and capsules by rotated boxes: ours are exact, so inside
        lo, hi = authored[0::2][~big[0::2]], authored[1::2][~big[1::2]]
        assert np.all(lo >= computed[0::2][~big[0::2]] - 1e-4), level
        assert np.all(hi <= computed[1::2][~big[1::2]] + 1e-4), level
    stage = Usd.Stage.Open(str(out))
    stage.SetEditTarget(stage.GetSessionLayer())
    stage.GetPrimAtPath("/Tree").GetVariantSet("lod").SetVariantSelection("proxy")
    crown = UsdGeom.Mesh(stage.GetPrimAtPath("/Tree/Proxy/Crown"))
    hull = np.asarray(crown.GetPointsAttr().Get(), dtype=float)
    leaves = b.placement.leaf_position
    # the crown hull wraps the leaves: their attachment points lie inside it
    import trimesh

    tri = np.asarray(crown.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    mesh = trimesh.Trimesh(hull, tri)
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.contains(leaves[:: max(1, len(leaves) // 300)]).mean() >= 0.99


def test_a_forest_selects_its_level_per_prototype(tmp_path):

    write_forest(_two_trees(lod="proxy"), tmp_path / "f.usda", thumbnail=False)
    stage = Usd.Stage.Open(str(tmp_path / "f.usda"))
    protos = stage.GetPrimAtPath("/Forest/Trees/Prototypes").GetChildren()
    assert protos and all(p.GetVariantSet("lod").GetVariantSelection() == "proxy" for p in protos)
    tris, leaves = _composed_counts(stage)
    assert leaves == 0 and tris <= 2 * 1000 + 2
