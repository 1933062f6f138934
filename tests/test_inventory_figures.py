"""Stand figures of a hand-built stand (usdforest.usd.inventory): wood that native instances
hold, read once per prototype, against trimesh's own areas and a girth tape round the mesh."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from pxr import Gf, Sdf, Usd, UsdGeom

from usdforest.usd.inventory import stand_figures

R, H = 0.2, 4.0  # the trunk cylinder's radius and height
SECTIONS = 16


def _mesh(stage: Usd.Stage, path: str, m: trimesh.Trimesh) -> None:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([Gf.Vec3f(*map(float, v)) for v in m.vertices])
    mesh.CreateFaceVertexCountsAttr([3] * len(m.faces))
    mesh.CreateFaceVertexIndicesAttr([int(i) for i in m.faces.ravel()])
    mesh.CreateExtentAttr([Gf.Vec3f(*map(float, b)) for b in m.bounds])


def _instance(stage: Usd.Stage, path: str, cls: str, matrix: np.ndarray | None = None):
    prim = UsdGeom.Xform.Define(stage, path)
    if matrix is not None:
        prim.AddTransformOp().Set(Gf.Matrix4d(matrix.tolist()))
    prim.GetPrim().GetReferences().AddInternalReference(cls)
    prim.GetPrim().SetInstanceable(True)
    return prim


@pytest.fixture(scope="module")
def stand(tmp_path_factory):
    """One tree, instanced twice by the forest (the second at 1.5x). The tree holds native
    instances: its trunk (a cylinder class, base at z = 0); a branch of the same class,
    scaled, sheared and moved; a branch of a class that holds the cylinder 1 m up and 2x wide;
    a branch of a class that holds the cylinder and a leaf instancer (two unit squares at half
    scale: a prototype whose instances are walked proxy by proxy); a proxy-purpose hull (not
    the tree). Returns the stage's path, the trunk's area and the two changed branches' area
    (trimesh's)."""
    path = tmp_path_factory.mktemp("figures") / "stand.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    forest = UsdGeom.Xform.Define(stage, "/Forest").GetPrim()
    stage.SetDefaultPrim(forest)
    forest.SetCustomDataByKey("usdforest", {"regionArea": 400.0, "regionBounds": [0, 0, 20, 20]})
    cyl = trimesh.creation.cylinder(radius=R, height=H, sections=SECTIONS)
    cyl.apply_translation([0, 0, H / 2])
    stage.CreateClassPrim("/Cylinder")
    _mesh(stage, "/Cylinder/Mesh", cyl)
    stage.CreateClassPrim("/Raised")
    part = UsdGeom.Xform.Define(stage, "/Raised/Part")
    part.AddTranslateOp().Set(Gf.Vec3d(0, 0, 1))
    part.AddScaleOp().Set(Gf.Vec3f(2, 1, 1))
    _mesh(stage, "/Raised/Part/Mesh", cyl)
    stage.CreateClassPrim("/Tufted")
    _mesh(stage, "/Tufted/Mesh", cyl)
    leaves = UsdGeom.PointInstancer.Define(stage, "/Tufted/Leaves")  # walked proxy by proxy
    square = trimesh.Trimesh([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], [(0, 1, 2), (0, 2, 3)])
    _mesh(stage, "/Tufted/Leaves/Leaf", square)
    leaves.CreatePrototypesRel().SetTargets([Sdf.Path("/Tufted/Leaves/Leaf")])
    leaves.CreateProtoIndicesAttr([0, 0])
    leaves.CreatePositionsAttr([(0, 0, 2), (0, 0, 3)])
    leaves.CreateScalesAttr([(0.5, 0.5, 0.5)] * 2)
    trees = UsdGeom.PointInstancer.Define(stage, "/Forest/Trees")
    tree = "/Forest/Trees/Prototypes/T"
    UsdGeom.Xform.Define(stage, tree).GetPrim().SetCustomDataByKey("usdforest", {"species": "test"})
    _instance(stage, f"{tree}/Trunk", "/Cylinder")
    branch = np.diag([0.5, 0.5, 0.3, 1.0])
    branch[2, 0] = 0.4  # a shear: z moves x
    branch[3, :3] = (1.0, 0.0, 2.0)
    _instance(stage, f"{tree}/Branches/B_0001", "/Cylinder", branch)
    _instance(stage, f"{tree}/Branches/B_0002", "/Raised")
    _instance(stage, f"{tree}/Branches/B_0003", "/Tufted")
    hull = _instance(stage, f"{tree}/Proxy", "/Cylinder", np.diag([9.0, 9.0, 1.0, 1.0]))
    hull.CreatePurposeAttr("proxy")
    trees.CreatePrototypesRel().SetTargets([Sdf.Path(tree)])
    trees.CreateProtoIndicesAttr([0, 0])
    trees.CreatePositionsAttr([(5, 5, 0), (15, 12, 0)])
    trees.CreateScalesAttr([(1, 1, 1), (1.5, 1.5, 1.5)])
    stage.GetRootLayer().Save()
    sheared = cyl.copy()
    sheared.apply_transform(branch.T)  # USD's row vectors: trimesh's columns
    wide = cyl.copy()
    wide.apply_scale([2, 1, 1])
    return path, cyl.area, sheared.area + wide.area


def test_instanced_wood_is_measured_once_per_prototype_as_each_proxy_holds_it(stand):
    path, trunk_area, branch_area = stand
    t = stand_figures(path)["per_tree"]
    # one-sided: half the surface of each closed mesh (the trunk, the sheared branch, the
    # raised one widened 2x and the trunk's mesh in the tufted one); the proxy hull is not wood
    one = 0.5 * (2 * trunk_area + branch_area)
    scale = np.array([1.0, 1.5])
    np.testing.assert_allclose(t["wood_area"], one * scale**2, rtol=1e-6)  # float32 points
    np.testing.assert_allclose(t["leaf_area"], 2 * 0.5**2 * scale**2, rtol=1e-6)  # float32 points
    # a girth tape round the 16-sided trunk at 1.3 m: its perimeter over pi
    tape = SECTIONS * 2 * R * math.sin(math.pi / SECTIONS) / math.pi
    np.testing.assert_allclose(t["dbh"], tape * scale, rtol=1e-6)
    # the tallest wood: the raised cylinder, 1 m up (the hull's purpose is proxy)
    np.testing.assert_allclose(t["height"], (H + 1.0) * scale, rtol=1e-6)
