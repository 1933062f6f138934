"""Implicit UsdGeom shapes in the sensor scene: a lidar scan of an analytic scene (plane,
sphere, cylinder, cube, cone, capsule with its axis turned) returns points on the analytic
surfaces, and what the scene cannot hold is named in a warning."""

from __future__ import annotations

import numpy as np
from pxr import Gf, Usd, UsdGeom

from usdforest.cli import app
from usdforest.sensors.lidar.scanners import SpinningLidar, scan
from usdforest.sensors.platforms.checks import unseen_warning
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene


def _stage(path):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    return stage


def _place(shape, x, y, z):
    UsdGeom.XformCommonAPI(shape).SetTranslate(Gf.Vec3d(x, y, z))


def test_lidar_points_lie_on_the_analytic_surfaces(tmp_path):
    stage = _stage(tmp_path / "shapes.usda")
    plane = UsdGeom.Plane.Define(stage, "/World/Ground")
    plane.CreateWidthAttr(60.0)
    plane.CreateLengthAttr(60.0)
    _place(plane, 0, 0, -1.5)
    sphere = UsdGeom.Sphere.Define(stage, "/World/Ball")
    sphere.CreateRadiusAttr(1.2)
    _place(sphere, 6, 0, 0)
    cyl = UsdGeom.Cylinder.Define(stage, "/World/Post")
    cyl.CreateRadiusAttr(0.4)
    cyl.CreateHeightAttr(4.0)
    _place(cyl, -5, 3, 0.5)
    lying = UsdGeom.Cylinder.Define(stage, "/World/Log")  # axis X: a log on the ground
    lying.CreateRadiusAttr(0.3)
    lying.CreateHeightAttr(3.0)
    lying.CreateAxisAttr("X")
    _place(lying, 0, -5, -1.2)
    cube = UsdGeom.Cube.Define(stage, "/World/Box")
    cube.CreateSizeAttr(1.0)
    _place(cube, 0, 6, -1.0)
    stage.Save()

    scene = extract_scene(tmp_path / "shapes.usda")
    assert scene.unseen == ()
    lidar = SpinningLidar(channels=64, vfov_min=-40, vfov_max=15, azimuth_step=0.5, max_range=40.0)
    r = scan(scene, lidar, Pose(0, 0, 0))
    paths = np.array(r.paths)[r.path]
    p = r.points
    checks = {
        "/World/Ground": np.abs(p[:, 2] + 1.5),
        "/World/Ball": np.abs(np.linalg.norm(p - [6, 0, 0], axis=1) - 1.2),
        # a cylinder's side or its caps
        "/World/Post": np.minimum(
            np.abs(np.hypot(p[:, 0] + 5, p[:, 1] - 3) - 0.4), np.abs(np.abs(p[:, 2] - 0.5) - 2.0)
        ),
        "/World/Log": np.minimum(
            np.abs(np.hypot(p[:, 1] + 5, p[:, 2] + 1.2) - 0.3), np.abs(np.abs(p[:, 0]) - 1.5)
        ),
        "/World/Box": np.abs(np.abs(p - [0, 6, -1.0]).max(axis=1) - 0.5),
    }
    for name, distance in checks.items():
        mine = paths == name
        assert mine.sum() > 20, name
        assert distance[mine].max() < 1e-3, (name, distance[mine].max())


def test_cone_capsule_and_the_warning_for_unseen_prims(tmp_path, runner):
    stage = _stage(tmp_path / "more.usda")
    cone = UsdGeom.Cone.Define(stage, "/World/Cone")
    cone.CreateRadiusAttr(1.0)
    cone.CreateHeightAttr(2.0)
    _place(cone, 5, 0, 0)
    cap = UsdGeom.Capsule.Define(stage, "/World/Capsule")
    cap.CreateRadiusAttr(0.5)
    cap.CreateHeightAttr(1.0)
    cap.CreateAxisAttr("Y")
    _place(cap, -5, 0, 0)
    curves = UsdGeom.BasisCurves.Define(stage, "/World/Wire")
    curves.CreatePointsAttr([(0, 0, 3), (1, 0, 3), (2, 0, 3), (3, 0, 3)])
    curves.CreateCurveVertexCountsAttr([4])
    points = UsdGeom.Points.Define(stage, "/World/Dust")
    points.CreatePointsAttr([(0, 2, 0)])
    stage.Save()
    scene = extract_scene(tmp_path / "more.usda")
    assert set(scene.unseen) == {"/World/Wire", "/World/Dust"}
    msg = unseen_warning(scene)
    assert "2 prim(s)" in msg and "/World/Wire" in msg and "/World/Dust" in msg
    lidar = SpinningLidar(channels=32, vfov_min=-30, vfov_max=30, azimuth_step=0.5, max_range=20)
    r = scan(scene, lidar, Pose(0, 0, 0))
    paths = np.array(r.paths)[r.path]
    p = r.points
    # the cone: apex at z = +1, base circle of radius 1 at z = -1, around (5, 0)
    c = p[paths == "/World/Cone"]
    assert len(c) > 20
    radial = np.hypot(c[:, 0] - 5, c[:, 1])
    side = np.abs(radial - (1 - c[:, 2]) / 2)
    base = np.abs(c[:, 2] + 1)
    assert np.minimum(side, base).max() < 1e-3
    # the capsule along Y: distance to its spine segment is its radius
    k = p[paths == "/World/Capsule"] - [-5, 0, 0]
    assert len(k) > 20
    t = np.clip(k[:, 1], -0.5, 0.5)
    d = np.linalg.norm(k - np.stack([np.zeros_like(t), t, np.zeros_like(t)], 1), axis=1)
    assert np.abs(d - 0.5).max() < 1e-3
    # the command line says it on one line
    result = runner.invoke(
        app,
        [
            "scan",
            str(tmp_path / "more.usda"),
            "--sensor",
            "lidar",
            "--pose",
            "0,0,0",
            "-o",
            str(tmp_path / "s.npz"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "cannot see" in result.output and "/World/Wire" in result.output
