"""Sanity checks of a sensor pose against the scene: outside the stage, inside a trunk."""

from __future__ import annotations

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.sensors.cast.raycast import RayCaster
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.scenetypes import CLASS_ID, Scene

AXES = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])


def pose_warnings(scene: Scene, pose: Pose, max_range: float) -> list[str]:
    """Warnings (the scan still runs): the stage is out of range, or the pose is outside a
    forest's bounds or below its ground."""
    lo, hi = scene.bounds
    p = pose.position
    gap = float(np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0)))
    if gap > max_range:
        return [
            f"the stage's geometry is {gap:.1f} m away, beyond the sensor's range "
            f"({max_range:g} m): nothing will be seen"
        ]
    forest = np.unique(scene.tree[scene.tree >= 0]).size > 1
    if forest and (np.any(p[:2] < lo[:2]) or np.any(p[:2] > hi[:2])):
        return [
            f"pose ({p[0]:g}, {p[1]:g}, {p[2]:g}) is outside the forest's bounds "
            f"x {lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f}"
        ]
    if p[2] < lo[2]:
        return [f"pose z = {p[2]:g} is below the ground of the stage (z = {lo[2]:.2f})"]
    return []


def unseen_warning(scene: Scene, shown: int = 3) -> str | None:
    """One line naming the geometry prims the scene could not hold (None when there are
    none): a sensor never silently ignores what a user put in the stage."""
    if not scene.unseen:
        return None
    names = ", ".join(scene.unseen[:shown])
    more = f" and {len(scene.unseen) - shown} more" if len(scene.unseen) > shown else ""
    return (
        f"{len(scene.unseen)} prim(s) the sensor cannot see (only meshes, instancers and "
        f"Cube/Sphere/Cylinder/Capsule/Cone/Plane are cast): {names}{more}"
    )


def check_not_inside_wood(scene: Scene, pose: Pose) -> None:
    """Refuse a pose inside a trunk: (almost) every axis ray first meets a trunk from inside.

    Only the trunks that could hold the pose are cast into (the scene's own and those of the
    tree instances whose bounds contain it), so the check never builds the acceleration
    structure of a whole tree's leaves."""
    trunk = CLASS_ID["trunk"]
    parts = [scene.triangles[scene.cls == trunk]]
    inst = scene.instances
    centre, radius = scene.instance_spheres()
    for i in np.flatnonzero(np.linalg.norm(centre - pose.position, axis=1) <= radius):
        proto = scene.protos[inst.proto[i]]
        tri = proto.triangles[proto.cls == trunk].astype(np.float64)
        m = inst.matrix[i]
        parts.append((tri.reshape(-1, 3) @ m[:3, :3] + m[3, :3]).reshape(-1, 3, 3))
    tri = np.concatenate(parts).astype(np.float32)
    if len(tri) == 0:
        return
    _, prim = RayCaster(tri).first_hit(np.broadcast_to(pose.position, AXES.shape), AXES, 5.0)
    hit = prim >= 0
    normal = np.cross(tri[prim, 1] - tri[prim, 0], tri[prim, 2] - tri[prim, 0])
    inside = hit & (np.sum(normal * AXES, axis=1) > 0)
    if np.count_nonzero(inside) >= len(AXES) - 1:
        raise UsdForestError(
            f"pose ({pose.x:g}, {pose.y:g}, {pose.z:g}) is inside a trunk; move the sensor out"
        )


def time_warning(stage_path, seconds: float | None) -> str | None:
    """One line when a scan's ``seconds`` is not a time of the stage's animation as asked (the
    scan still runs): a stage without time codes is scanned as it stands, a looping stage
    (a forest's wind) at that time wrapped into its loop, another as at its nearest end."""
    from usdforest.sensors.scene.stageframe import looped, root_layer
    from usdforest.usd.layers import time_range

    layer = root_layer(stage_path) if seconds is not None else None
    if layer is None:
        return None
    start, end, _, loops = time_range(layer)
    if not end > start:
        from pxr import Usd

        from usdforest.sensors.scene.stageframe import animated

        if animated(Usd.Stage.Open(layer)):  # a host of one's own that gives no range
            return (
                "time: the stage gives no time range (startTimeCode, endTimeCode): scanned at "
                f"{seconds:g} s as its layers' time samples give it"
            )
        return "time: the stage has no animation (no time codes): scanned as it stands"
    if loops:
        t = looped(seconds, (start, end - start))
        if abs(t - seconds) > 1e-9:
            return (
                f"time: {seconds:g} s is outside the stage's loop of {end - start:g} s from "
                f"{start:g} s: scanned at {t:g} s"
            )
    elif not start <= seconds <= end:
        return (
            f"time: {seconds:g} s is outside the stage's animation ({start:g}-{end:g} s): "
            f"scanned as at {min(max(seconds, start), end):g} s"
        )
    return None
