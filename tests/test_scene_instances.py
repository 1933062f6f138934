"""Native instances in the sensors' scene (usdforest.sensors.scene.extraction): each prototype's
meshes read once and placed by every instance, the same triangles, classes and paths as a walk of
every instance proxy."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdSemantics

from usdforest.sensors.scene.extraction import extract_scene
from usdforest.sensors.scene.scenetypes import CLASS_ID
from usdforest.usd.layers import class_labels

QUAD = [(0, 0, 0), (1, 0, 0), (1, 1, 0.5), (0, 1, 0)]


def _label(prim: Usd.Prim, label: str) -> None:
    UsdSemantics.LabelsAPI.Apply(prim, "class").CreateLabelsAttr([label])


def _quad(stage: Usd.Stage, path: str, label: str | None = None) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(QUAD)
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateExtentAttr([(0, 0, 0), (1, 1, 0.5)])
    if label:
        _label(mesh.GetPrim(), label)
    return mesh


def _instance(stage, path: str, cls: str, matrix=None, label: str | None = None):
    x = UsdGeom.Xform.Define(stage, path)
    if matrix is not None:
        x.AddTransformOp().Set(Gf.Matrix4d(np.asarray(matrix, float).tolist()))
    x.GetPrim().GetReferences().AddInternalReference(cls)
    x.GetPrim().SetInstanceable(True)
    if label:
        _label(x.GetPrim(), label)


@pytest.fixture(scope="module")
def stage_path(tmp_path_factory):
    """/Twig: a labelled branch quad, an unlabelled quad 1 m up and 2x long (its class is its
    instance's), an invisible quad and a guide; /Reset: a quad under a prim that resets the
    transform stack (walked proxy by proxy). Instanced as a trunk, a sheared branch, a
    turned one and a reset one."""
    path = tmp_path_factory.mktemp("instances") / "s.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    stage.CreateClassPrim("/Twig")
    _quad(stage, "/Twig/Wood", "branch")
    up = UsdGeom.Xform.Define(stage, "/Twig/Up")
    up.AddTranslateOp().Set(Gf.Vec3d(0, 0, 1))
    up.AddScaleOp().Set(Gf.Vec3f(2, 1, 1))
    _quad(stage, "/Twig/Up/Bare")
    _quad(stage, "/Twig/Hidden").CreateVisibilityAttr("invisible")
    _quad(stage, "/Twig/Guide").CreatePurposeAttr("guide")
    stage.CreateClassPrim("/Reset")
    reset = UsdGeom.Xform.Define(stage, "/Reset/Alone")
    reset.SetResetXformStack(True)
    reset.AddTranslateOp().Set(Gf.Vec3d(0, 0, 7))
    _quad(stage, "/Reset/Alone/Mesh", "dead_wood")
    tree = UsdGeom.Xform.Define(stage, "/World/Tree")
    tree.AddTranslateOp().Set(Gf.Vec3d(3, 4, 0))
    _instance(stage, "/World/Tree/Trunk", "/Twig", label="trunk")
    shear = np.diag([0.5, 0.5, 0.3, 1.0])
    shear[2, 0], shear[3, :3] = 0.4, (1.0, 0.0, 2.0)
    _instance(stage, "/World/Tree/B_0001", "/Twig", shear, label="branch")
    turn = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(0, 0, 1), 30)) * Gf.Matrix4d().SetScale(1.5)
    _instance(stage, "/World/Tree/B_0002", "/Twig", np.asarray(turn), label="branch")
    _instance(stage, "/World/Tree/B_0003", "/Reset", label="branch")
    stage.GetRootLayer().Save()
    return path


def _proxy_by_proxy(path) -> tuple[list, list, list]:
    """Each rendered, visible mesh through the instance proxies: world triangles (the quad
    fanned 0-1-2, 0-2-3), class (the nearest label, from the mesh up) and path."""
    stage = Usd.Stage.Open(str(path))
    cache = UsdGeom.XformCache()
    tri, cls, where = [], [], []
    it = iter(Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies()))
    for p in it:
        img = UsdGeom.Imageable(p)
        if img and (
            img.ComputeVisibility() == "invisible" or img.GetPurposeAttr().Get() == "guide"
        ):
            it.PruneChildren()
            continue
        if not p.IsA(UsdGeom.Mesh):
            continue
        m = np.asarray(cache.GetLocalToWorldTransform(p))
        v = np.asarray(QUAD, float) @ m[:3, :3] + m[3, :3]
        q, label = p, None
        while q and label is None:
            label = next((x for x in class_labels(q) if x in CLASS_ID), None)
            q = q.GetParent()
        for face in ((0, 1, 2), (0, 2, 3)):
            tri.append(v[list(face)])
            cls.append(CLASS_ID[label] if label else 0)
            where.append(str(p.GetPath()))
    return tri, cls, where


def test_instanced_meshes_are_placed_as_their_proxies_hold_them(stage_path):
    scene = extract_scene(stage_path, cache=False)
    tri, cls, where = _proxy_by_proxy(stage_path)
    assert len(scene.triangles) == len(tri) == 2 * 3 * 2 + 2  # 3 instances of 2 quads, 1 reset
    np.testing.assert_allclose(scene.triangles, np.asarray(tri), atol=1e-5)
    assert scene.cls.tolist() == cls
    assert [scene.paths[i] for i in scene.path] == where
    # the unlabelled quad takes each instance's class; the reset one stands 7 m up
    assert cls.count(CLASS_ID["trunk"]) == 2 and cls.count(CLASS_ID["dead_wood"]) == 2
    assert np.all(scene.triangles[-2:, :, 2] >= 7.0)
