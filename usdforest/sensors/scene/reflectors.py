"""Leaves as the sonar's disk reflectors: a prototype's leaves placed by an instance, and the
blades of a ground-vegetation patch (which are meshes, not leaf instances) made reflectors."""

from __future__ import annotations

import numpy as np

from usdforest.sensors.scene.scenetypes import Leaves, Prototype


def placed_leaves(
    proto: Prototype, m: np.ndarray, tree: int, centre: np.ndarray | None, radius: float | None
) -> Leaves:
    """A prototype's leaves placed by ``m`` (row-vector 4x4), those within reach only: a
    tree's scaled by s² (its uniform scale), a ground-vegetation blade's area vector moved
    by the cofactor of ``m`` (a patch is stretched more across than up)."""
    lv = proto.leaves
    rot = m[:3, :3]
    c = lv.centre @ rot + m[3, :3]
    keep = np.ones(len(c), dtype=bool)
    if centre is not None and radius is not None:
        keep = np.linalg.norm(c - centre, axis=1) <= radius + 2 * np.sqrt(lv.area) + 1e-6
    normal = lv.normal[keep]
    n = normal @ np.linalg.inv(rot).T
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n /= np.maximum(length, 1e-12)
    det = abs(np.linalg.det(rot))
    # a tree is turned and scaled uniformly: s² (its half-float turn is not quite a rotation,
    # so s² is taken from the determinant, as the copied scene does)
    area = lv.area[keep] * det ** (2 / 3)
    blade = lv.blade[keep] if lv.blade is not None else None
    if blade is not None and blade.any():
        # a patch is stretched: |det M| |M^-T n| / |n|
        stretch = length[blade, 0] / np.maximum(np.linalg.norm(normal[blade], axis=1), 1e-12)
        area[blade] = lv.area[keep][blade] * det * stretch
    shape = lv.shape[keep] if lv.shape is not None else None
    frame = lv.frame[keep] @ m if lv.frame is not None else None
    return Leaves(c[keep], n, area, np.full(int(keep.sum()), tree, np.int64), blade, shape, frame)


def blade_reflectors(tri: np.ndarray) -> Leaves:
    """Each connected blade, leaf or frond of ``tri (m, 3, 3)`` (a ground-vegetation patch's)
    as a leaf reflector: its area-weighted centre, its area-weighted mean normal (turned up)
    and its one-sided area."""
    from usdforest.meshes import triangle_components

    if not len(tri):
        return Leaves.concat([])
    t = np.asarray(tri, dtype=float)
    label = triangle_components(t)
    cross = 0.5 * np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    area = np.linalg.norm(cross, axis=1)
    n = int(label.max()) + 1
    total = np.bincount(label, area, n)
    centre = (
        np.stack([np.bincount(label, area * t[:, :, k].mean(axis=1), n) for k in range(3)], axis=1)
        / np.maximum(total, 1e-30)[:, None]
    )
    # a triangle's normal turned up before summing: a curved blade's two faces do not cancel
    up = np.where(cross[:, 2:3] < 0, -cross, cross)
    vec = np.stack([np.bincount(label, up[:, k], n) for k in range(3)], axis=1)
    length = np.linalg.norm(vec, axis=1, keepdims=True)
    normal = np.where(length > 1e-30, vec / np.maximum(length, 1e-30), [0.0, 0.0, 1.0])
    keep = total > 0
    m = int(keep.sum())
    return Leaves(
        centre[keep], normal[keep], total[keep], np.full(m, -1, np.int64), np.ones(m, bool)
    )
