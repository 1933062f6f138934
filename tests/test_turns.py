"""Prims' own transforms in time as the sensors read them (usdforest.sensors.scene.turns), against
USD's own XformCache, and the boxes that hold a turning shape between time samples."""

from __future__ import annotations

import numpy as np
from pxr import Gf, Usd, UsdGeom

from usdforest.sensors.scene.turns import Turns, swept_boxes


def _stage() -> tuple[Usd.Stage, list[Usd.Prim]]:
    """Prims turned as a forest's wind turns them: a limb (pivot, frame, sway, inverses), two
    leaves inheriting one flutter class, one with two ops in time, one that never moves."""
    stage = Usd.Stage.CreateInMemory()
    rng = np.random.default_rng(3)
    cls = stage.CreateClassPrim("/_class_Turn")
    op = UsdGeom.Xformable(cls).AddOrientOp(UsdGeom.XformOp.PrecisionFloat, "flutter")
    for f in range(25):
        axis = rng.normal(size=3)
        q = Gf.Rotation(Gf.Vec3d(*axis), float(rng.uniform(-25, 25))).GetQuat()
        op.Set(Gf.Quatf(q), float(f))
    prims = []
    for name in ("LeafA", "LeafB"):
        leaf = UsdGeom.Xform.Define(stage, f"/{name}")
        leaf.GetPrim().GetInherits().AddInherit("/_class_Turn")
        leaf.AddScaleOp().Set(Gf.Vec3f(0.3, 0.3, 0.3))
        leaf.GetXformOpOrderAttr().Set(["xformOp:scale", "xformOp:orient:flutter"])
        prims.append(leaf.GetPrim())
    limb = UsdGeom.Xform.Define(stage, "/Limb")
    pivot = limb.AddTranslateOp(opSuffix="pivot")
    pivot.Set(Gf.Vec3d(1.0, -2.0, 3.0))
    limb.AddOrientOp(opSuffix="frame").Set(Gf.Quatf(0.8, 0.6, 0.0, 0.0))
    sway = limb.AddRotateXYZOp(opSuffix="sway")
    for f in range(25):
        sway.Set(Gf.Vec3f(*rng.uniform(-8, 8, 3)), float(f))
    limb.AddOrientOp(opSuffix="frame", isInverseOp=True)
    limb.AddTranslateOp(opSuffix="pivot", isInverseOp=True)
    prims.append(limb.GetPrim())
    both = UsdGeom.Xform.Define(stage, "/Both")
    move = both.AddTranslateOp()
    spin = both.AddRotateZOp()
    for f in range(0, 25, 3):
        move.Set(Gf.Vec3d(*rng.normal(size=3)), float(f))
        spin.Set(float(rng.uniform(-90, 90)), float(f))
    prims.append(both.GetPrim())
    still = UsdGeom.Xform.Define(stage, "/Still")
    still.AddTranslateOp().Set(Gf.Vec3d(4.0, 5.0, 6.0))
    prims.append(still.GetPrim())
    return stage, prims


def test_turns_are_usds_own_transforms_at_any_time_each_shared_op_read_once():
    _held, prims = _stage()  # the stage lives as long as its prims are read
    turns = Turns(prims)
    assert list(turns.moving) == [True, True, True, True, False]
    # the two leaves share their class's samples: one op read for both
    assert turns.which[0] == turns.which[1] and len({*turns.which[:4]}) == 3
    for code in [*np.random.default_rng(0).uniform(-2.0, 27.0, 40), 0.0, 24.0]:
        cache = UsdGeom.XformCache(Usd.TimeCode(code))
        want = np.array([np.asarray(cache.GetLocalTransformation(p)[0]) for p in prims])
        np.testing.assert_allclose(turns.at(Usd.TimeCode(code)), want, atol=1e-12)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    want = np.array([np.asarray(cache.GetLocalTransformation(p)[0]) for p in prims])
    np.testing.assert_allclose(turns.at(Usd.TimeCode.Default()), want, atol=1e-12)


def test_a_shapes_swept_box_holds_it_between_the_samples_where_usd_slerps():
    """The box of a leaf shape over its turns, in its space at time 0, holds the shape as
    USD turns it at 4,000 times between the samples (a slerp leaves the chord), and is no
    larger than its samples' box by more than the arc's sagitta."""
    _held, prims = _stage()  # the stage lives as long as its prims are read
    turns = Turns(prims)
    pts = np.random.default_rng(1).normal(size=(60, 3)) * [0.05, 0.02, 0.001] + [0.05, 0, 0]
    own = turns.at(Usd.TimeCode(0.0))[0]
    box = swept_boxes([pts], own, turns.series(0))[0]
    back = np.linalg.inv(own)
    dense = np.array([turns.at(Usd.TimeCode(c))[0] for c in np.linspace(0, 24, 4000)]) @ back
    moved = np.einsum("pj,njk->npk", pts, dense[:, :3, :3]) + dense[:, None, 3, :3]
    assert (moved.min(axis=(0, 1)) >= box[0]).all() and (moved.max(axis=(0, 1)) <= box[1]).all()
    at_samples = turns.series(0) @ back
    sampled = np.einsum("pj,njk->npk", pts, at_samples[:, :3, :3]) + at_samples[:, None, 3, :3]
    slack = np.concatenate([sampled.min(axis=(0, 1)) - box[0], box[1] - sampled.max(axis=(0, 1))])
    # the farthest an arc of a turn theta between two samples leaves its chord c: the
    # sagitta r (1 - cos(theta / 2)) = (c / 2) tan(theta / 4), over points and samples
    from scipy.spatial.transform import Rotation

    lin = at_samples[:, :3, :3] / 0.3
    theta = (Rotation.from_matrix(lin[:-1]).inv() * Rotation.from_matrix(lin[1:])).magnitude()
    chord = np.linalg.norm(sampled[1:] - sampled[:-1], axis=2).max(axis=1)
    sagitta = float((chord / 2 * np.tan(theta / 4)).max())
    assert (slack >= 0).all() and slack.max() <= sagitta + 1e-12
    assert sagitta < 0.1 * float((box[1] - box[0]).max())
