"""The project's own validation rules (usdforest.usd.validate), on stages with planted defects."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdValidation, Vt

from usdforest.usd.validate import project_findings, pxr_findings


def _broken_stage(path: Path) -> Usd.Stage:
    """A Z-up stage whose prototype ``/Proto`` (a Mesh with a NaN point and an extent that
    misses a point at x = 5, a PointInstancer with a repeated id and a quaternion of norm 2)
    is instanced by ``/A`` and ``/B``; ``/Loose`` is an uninstanced Mesh without an extent."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(root.GetPrim())
    proto = stage.CreateClassPrim("/Proto")  # abstract: traversed only through /A and /B
    mesh = UsdGeom.Mesh.Define(stage, "/Proto/M")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, float("nan"), 0), (5, 5, 5)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 3])
    mesh.CreateExtentAttr([(0, 0, 0), (1, 1, 1)])
    pi = UsdGeom.PointInstancer.Define(stage, "/Proto/P")
    pi.CreatePositionsAttr([(0, 0, 0), (1, 0, 0)])
    pi.CreateProtoIndicesAttr([0, 0])
    pi.CreateIdsAttr(Vt.Int64Array([3, 3]))
    pi.CreateOrientationsAttr([Gf.Quath(1, 0, 0, 0), Gf.Quath(2, 0, 0, 0)])
    pi.CreateExtentAttr([(0, 0, 0), (1, 1, 1)])
    pi.CreatePrototypesRel().AddTarget("/Proto/P/Missing")
    for name in ("A", "B"):
        inst = stage.DefinePrim(f"/World/{name}", "Xform")
        inst.GetReferences().AddInternalReference(proto.GetPath())
        inst.SetInstanceable(True)
    loose = UsdGeom.Mesh.Define(stage, "/World/Loose")
    loose.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    loose.CreateFaceVertexCountsAttr([3])
    loose.CreateFaceVertexIndicesAttr([0, 1, 2])
    stage.GetRootLayer().Save()
    return stage


def test_each_instance_proxy_reports_its_prototypes_defects(tmp_path):
    stage = _broken_stage(tmp_path / "s.usda")
    found = {(f.source, f.path, f.message) for f in project_findings(stage)}
    # expected, rule by rule, at both instances (a prototype checked once must still be
    # reported at every path a user would look at)
    expected = {("usdforest:extent", "/World/Loose", "Mesh has no extent")}
    for name in ("A", "B"):
        m, p = f"/World/{name}/M", f"/World/{name}/P"
        expected |= {
            ("usdforest:finite", m, "points contain NaN or infinity"),
            ("usdforest:extent", m, "extent does not contain the points"),  # x reaches 5
            ("usdforest:ids", p, "PointInstancer ids are not unique"),
            ("usdforest:quaternions", p, "orientations are not unit quaternions"),
            ("usdforest:prototypes", p, f"prototype {p}/Missing does not exist"),
        }
    assert found == expected
    # in the order of the stage's traversal, as a prim-by-prim check gives them
    ids = [f.path for f in project_findings(stage) if f.source == "usdforest:ids"]
    assert ids == ["/World/A/P", "/World/B/P"]


def test_an_extent_that_misses_its_points_is_named(tmp_path):
    layer = Sdf.Layer.CreateNew(str(tmp_path / "m.usda"))
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    mesh = UsdGeom.Mesh.Define(stage, "/M")
    stage.SetDefaultPrim(mesh.GetPrim())
    pts = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 2.0)])
    mesh.CreatePointsAttr(pts.tolist())
    mesh.CreateExtentAttr([(0, 0, 0), (1, 1, 1)])  # z reaches 2, the extent 1
    found = [(f.source, f.message) for f in project_findings(stage)]
    assert found == [("usdforest:extent", "extent does not contain the points")]
    mesh.GetExtentAttr().Set([(0, 0, 0), (1, 1, 2)])
    assert project_findings(stage) == []


def test_pxr_findings_are_those_of_a_prim_by_prim_traversal():
    # /Proto nests a Mesh in a Mesh (pxr's InvalidNestedGprims at every instance's inner
    # mesh); /World/G/C instances it under a Mesh, so there the outer mesh is nested too: an
    # ancestry only that instance has, which one instance checked for all would miss
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    proto = stage.CreateClassPrim("/Proto")
    UsdGeom.Mesh.Define(stage, "/Proto/M")
    UsdGeom.Mesh.Define(stage, "/Proto/M/Inner")
    UsdGeom.Mesh.Define(stage, "/World/G")
    for path in ("/World/A", "/World/B", "/World/G/C", "/World/AB"):
        inst = stage.DefinePrim(path, "Xform")
        inst.GetReferences().AddInternalReference(proto.GetPath())
        inst.SetInstanceable(True)
    everything = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    reference = []  # every prim, proxies included, one by one: what pxr's default gives
    for e in UsdValidation.ValidationContext(list(everything)).Validate(stage):
        reference.append((e.GetName(), str(e.GetSites()[0].GetPrim().GetPath()), e.GetMessage()))
    found = [(f.source, f.path, f.message) for f in pxr_findings(stage)]
    assert sorted(found) == sorted(reference)
    assert {p for _, p, _ in found} == {
        "/World/A/M/Inner",
        "/World/B/M/Inner",
        "/World/AB/M/Inner",
        "/World/G/C/M/Inner",
        "/World/G/C/M",
    }
    assert all(path in message for _, path, message in found)  # each message names its prim
