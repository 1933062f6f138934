"""Small stages the sensor tests look at: written here with pxr, Z up, in metres."""

from __future__ import annotations

from pxr import Gf, Usd, UsdGeom


def new_stage(path) -> Usd.Stage:
    """An empty Z-up stage at ``path`` with a default prim ``/World``."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    return stage


def quad(stage: Usd.Stage, name: str, corners) -> UsdGeom.Mesh:
    """A one-face mesh ``/World/<name>`` through four ``corners`` in order."""
    mesh = UsdGeom.Mesh.Define(stage, f"/World/{name}")
    mesh.CreatePointsAttr([tuple(map(float, c)) for c in corners])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    return mesh


def ball_and_wall(path, centre=(6.0, 1.0, 0.5), radius=1.0, wall=20.0, half=100.0):
    """A sphere at ``centre`` and a wall across the +x view at x = ``wall`` (2 ``half`` wide
    and tall); returns ``path``."""
    stage = new_stage(path)
    ball = UsdGeom.Sphere.Define(stage, "/World/Ball")
    ball.CreateRadiusAttr(radius)
    UsdGeom.XformCommonAPI(ball).SetTranslate(Gf.Vec3d(*centre))
    s = half
    quad(stage, "Wall", [(wall, -s, -s), (wall, s, -s), (wall, s, s), (wall, -s, s)])
    stage.Save()
    return path
