"""Native instances in a sensor scene: a prototype's meshes read once, placed by each of its
instances (what every instance proxy holds, without walking the proxies).

A tree's trunk and branches reference their templates instanceable; the default forest has
47,000 such instances of 130 prototypes, and reading each proxy's mesh cost its scene 10 s.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

import numpy as np
from pxr import Usd, UsdGeom

from usdforest.sensors.scene.implicit import IMPLICIT
from usdforest.usd.layers import class_labels, mesh_triangles, rendered

PLACED_TRIANGLES = 250_000  # triangles of one prototype mesh's instances placed at once

# (path below the prototype's root, float64 triangles (m, 3, 3) in its root's space, class)
Mesh = tuple[str, np.ndarray, int | None]


def class_inside(prim: Usd.Prim, root: Usd.Prim, classes: Mapping[str, int]) -> int | None:
    """The class the labels of ``prim`` and the prims above it, below ``root``, give
    (``classes``: label to class); None where none does (the instance and what is above it
    decide)."""
    p = prim
    while p and p != root:
        for label in class_labels(p):
            if label in classes:
                return classes[label]
        p = p.GetParent()
    return None


def prototype_meshes(
    proto: Usd.Prim, cache: UsdGeom.XformCache, classes: Mapping[str, int]
) -> tuple[Mesh, ...] | None:
    """A native prototype's rendered, visible meshes in the space of its root; None where it
    holds anything else (an instancer, another gprim, a reset transform stack), whose
    instances are then walked proxy by proxy."""
    meshes = []
    inside = iter(Usd.PrimRange(proto, Usd.TraverseInstanceProxies()))
    next(inside)  # the root: its instance's own prim stands for it
    for q in inside:
        if not rendered(q) or (
            q.IsA(UsdGeom.Imageable) and UsdGeom.Imageable(q).ComputeVisibility() == "invisible"
        ):
            inside.PruneChildren()
        elif q.IsA(UsdGeom.Mesh):
            rel, resets = cache.ComputeRelativeTransform(q, proto)
            if resets:
                return None
            below = str(q.GetPath().MakeRelativePath(proto.GetPath()))
            m = np.array(rel, dtype=float).reshape(4, 4)
            meshes.append((below, mesh_triangles(q, m), class_inside(q, proto, classes)))
        elif q.IsA(UsdGeom.Gprim) or q.IsA(UsdGeom.PointInstancer) or q.GetTypeName() in IMPLICIT:
            return None
    return tuple(meshes)


def placed(tri: np.ndarray, mats: np.ndarray) -> Iterator[np.ndarray]:
    """``tri`` (m, 3, 3) placed by each row-vector transform of ``mats`` (n, 4, 4), as float32,
    one instance at a time (computed a batch of instances at a time)."""
    step = max(1, PLACED_TRIANGLES // max(len(tri), 1))
    for a in range(0, len(mats), step):
        m = mats[a : a + step]
        yield from (np.einsum("tvj,njk->ntvk", tri, m[:, :3, :3]) + m[:, None, None, 3, :3]).astype(
            np.float32
        )


class NativeMeshes:
    """Each native prototype's meshes (:func:`prototype_meshes`), read once, and the placing
    of those a walk met: ``rows[(prototype path, mesh)]`` lists ``(slot, to_root, path id,
    class)`` per instance."""

    def __init__(self, cache: UsdGeom.XformCache, classes: Mapping[str, int]):
        self._cache, self._classes, self._of = cache, classes, {}

    def of(self, proto: Usd.Prim) -> tuple[Mesh, ...] | None:
        key = proto.GetPath()
        if key not in self._of:
            self._of[key] = prototype_meshes(proto, self._cache, self._classes)
        return self._of[key]

    def place(self, rows: dict) -> Iterator[tuple[int, int, int, np.ndarray]]:
        """``(slot, path id, class, float32 triangles)`` of every instance mesh in ``rows``."""
        for (proto, j), found in rows.items():
            tri = self._of[proto][j][1]
            mats = np.stack([r[1] for r in found])
            for (slot, _, path_id, cls), t in zip(found, placed(tri, mats), strict=True):
                yield slot, path_id, cls, t
