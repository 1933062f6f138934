"""Host stages of other units and up axes that reference a forest, for the sensor and
preview tests."""

from __future__ import annotations


def host_stage(path, forest, *, up: str = "Z", cm: bool = False, tilt: float = 0.0):
    """A host stage in its own units and up axis that references ``forest`` under the
    transform that corrects it (Z-up metres into Y-up: turned -90 degrees about X; into
    centimetres: scaled 100), turned ``tilt`` degrees more about X."""
    from pxr import Gf, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01 if cm else 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    plot = UsdGeom.Xform.Define(stage, "/World/Forest")
    if cm:
        plot.AddScaleOp().Set(Gf.Vec3f(100.0, 100.0, 100.0))
    if up == "Y" or tilt:
        plot.AddRotateXOp().Set((-90.0 if up == "Y" else 0.0) + tilt)
    plot.GetPrim().GetReferences().AddReference(str(forest))
    stage.SetDefaultPrim(world.GetPrim())
    stage.Save()
    return path
