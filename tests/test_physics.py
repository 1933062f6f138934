"""Colliders: UsdPhysics schemas read back with pxr, and a real engine (newton, CPU) stopping
a ball at a trunk of a built forest and letting one pass between the trees."""

from __future__ import annotations

import csv
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdPhysics

from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.species import get_species
from usdforest.usd.forest import write_forest
from usdforest.usd.tree import write_tree

PIPELINES = default_recipe_path().parent
PROBE = Path(__file__).with_name("physics_probe.py")


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
    asked = read_recipe(PIPELINES / "paper-two-tree-stand.toml")
    data = dict(asked.data, forest={**asked.data.get("forest", {}), "physics_scene": True})
    from usdforest.recipe import parse_recipe

    with_scene = parse_recipe(data, asked.base, asked.source)
    write_forest(with_scene, tmp_path / "g.usda", thumbnail=False)
    s = Usd.Stage.Open(str(tmp_path / "g.usda"))
    assert [p.GetPath() for p in s.Traverse() if p.IsA(UsdPhysics.Scene)] == [
        "/Forest/PhysicsScene"
    ]


def _physics_python() -> str:
    py = os.environ.get("USDFOREST_PHYSICS_PYTHON", "")
    if not py or not Path(py).exists():
        pytest.skip("newton is not installed (make test installs it in .venv-physics)")
    probe = subprocess.run([py, "-c", "import newton"], capture_output=True, check=False)
    if probe.returncode:
        pytest.skip(f"newton does not import in {py}")
    return py


def test_newton_stops_a_ball_at_a_trunk_of_a_built_forest(tmp_path):
    py = _physics_python()
    out = tmp_path / "f.usda"
    write_forest(read_recipe(PIPELINES / "paper-two-tree-stand.toml"), out, thumbnail=False)
    with (tmp_path / "f_assets" / "trees.csv").open() as f:
        first = next(csv.DictReader(f))
    x0, y0 = float(first["x"]), float(first["y"])

    def roll(y: float) -> dict:
        r = subprocess.run(
            [py, str(PROBE), str(out), str(x0 - 2.0), str(y), "1.0", "3", "0", "0", "2"],
            capture_output=True,
            text=True,
            check=False,
            timeout=600,
        )
        assert r.returncode == 0, r.stderr[-2000:]
        return json.loads(r.stdout.strip().splitlines()[-1])

    hit = roll(y0)
    radius = 0.2 + 0.16  # ball + trunk capsule
    assert hit["position"][0] < x0 - radius + 0.05, hit  # stopped at the trunk
    free = roll(y0 - 2.0)  # 2 m to the side of it, clear of both trees
    assert free["position"][0] == pytest.approx(x0 - 2.0 + 3 * 2, abs=0.05), free
