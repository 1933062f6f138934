"""Measurements on composed stages, as a user would take them (pxr + trimesh + numpy).

Nothing here reads usdforest's internal arrays: wood meshes, transforms and leaf positions
come from the composed stage, distances from trimesh, silhouettes from a raster of the
projected triangles.
"""

from __future__ import annotations

import numpy as np
import trimesh
from matplotlib.path import Path as MplPath
from pxr import Usd, UsdGeom

T0 = Usd.TimeCode.Default()


def renders(prim: Usd.Prim) -> bool:
    """A renderer draws it: computed purpose default or render (not a proxy or guide)."""
    return UsdGeom.Imageable(prim).ComputePurpose() in ("default", "render")


def _world_points(prim: Usd.Prim) -> np.ndarray:
    mesh = UsdGeom.Mesh(prim)
    pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(T0))
    return pts @ m[:3, :3] + m[3, :3]


def _triangles(prim: Usd.Prim) -> np.ndarray:
    mesh = UsdGeom.Mesh(prim)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = [
        np.stack([idx[s] * np.ones(c - 2, int), idx[s + 1 : s + c - 1], idx[s + 2 : s + c]], 1)
        for s, c in zip(starts, counts, strict=True)
    ]
    return np.concatenate(tris) if tris else np.zeros((0, 3), int)


def world_mesh(prim: Usd.Prim) -> trimesh.Trimesh:
    """Every Mesh at or under ``prim`` (instance proxies included), in world space, as one."""
    parts = []
    for p in Usd.PrimRange(prim, Usd.TraverseInstanceProxies()):
        if p.IsA(UsdGeom.Mesh) and renders(p):
            parts.append(trimesh.Trimesh(_world_points(p), _triangles(p), process=False))
    return trimesh.util.concatenate(parts) if parts else trimesh.Trimesh()


def wood_prims(stage: Usd.Stage, root: str = "/Tree") -> dict[int, Usd.Prim]:
    """Wood prims by their index (``B_0007`` -> 7; the trunk under the index no branch has)."""
    out = {int(p.GetName()[2:]): p for p in wood_list(stage, root) if p.GetName() != "Trunk"}
    parents = {p.GetAttribute("usdforest:parent").Get() for p in out.values()}
    trunk_index = next(iter(parents - set(out) - {-1}), -1)
    out[trunk_index] = stage.GetPrimAtPath(f"{root}/Trunk")
    return out


def wood_list(stage: Usd.Stage, root: str = "/Tree") -> list[Usd.Prim]:
    """The trunk and every branch prim, on the tree or in its limbs' groups."""
    tree = stage.GetPrimAtPath(root)
    return [p for p in Usd.PrimRange(tree) if p.GetAttribute("usdforest:order").HasAuthoredValue()]


def leaf_instancers(stage: Usd.Stage, root: str = "/Tree") -> list[UsdGeom.PointInstancer]:
    """The tree's leaf instancers: its own and each limb's (``Leaves``)."""
    return [
        UsdGeom.PointInstancer(p)
        for p in Usd.PrimRange(stage.GetPrimAtPath(root))
        if p.IsA(UsdGeom.PointInstancer) and p.GetName() == "Leaves"
    ]


def leaf_positions(stage: Usd.Stage, root: str = "/Tree") -> np.ndarray:
    """Every leaf's position in the tree's space, instancer by instancer."""
    cache = UsdGeom.XformCache(T0)
    tree = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(stage.GetPrimAtPath(root))))
    out = []
    for pi in leaf_instancers(stage, root):
        m = np.asarray(cache.GetLocalToWorldTransform(pi.GetPrim()), dtype=float) @ tree
        pos = np.asarray(pi.GetPositionsAttr().Get() or [], dtype=float).reshape(-1, 3)
        out.append(pos @ m[:3, :3] + m[3, :3])
    return np.concatenate(out) if out else np.zeros((0, 3))


def base_point(prim: Usd.Prim) -> np.ndarray:
    """Where a wood prim's template origin (the base centre) lands in world space."""
    m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(T0))
    return m[3, :3].copy()


def outside_gap(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Distance from each point to the mesh surface when the point is outside it, else 0.

    Inside/outside from the closest triangle's outward normal (templates are closed tubes
    whose winding points outwards, but not always watertight).
    """
    points = np.atleast_2d(points)
    closest, dist, tri = trimesh.proximity.closest_point(mesh, points)
    outward = np.einsum("ij,ij->i", points - closest, mesh.face_normals[tri])
    return np.where(outward > 0, dist, 0.0)


def joint_gaps(stage: Usd.Stage, root: str = "/Tree") -> np.ndarray:
    """For every branch prim, the gap from its base to its parent's composed mesh (0 inside)."""
    prims = wood_prims(stage, root)
    meshes: dict[int, trimesh.Trimesh] = {}
    gaps = []
    for _, p in sorted(prims.items()):
        if p.GetPath().name == "Trunk":
            continue
        parent = p.GetAttribute("usdforest:parent").Get()
        if parent not in meshes:
            meshes[parent] = world_mesh(prims[parent])
        gaps.append(float(outside_gap(meshes[parent], base_point(p)[None])[0]))
    return np.array(gaps)


def tip_errors(stage: Usd.Stage, root: str = "/Tree") -> np.ndarray:
    """Distance from each wood prim's mesh tip (the centre of its far end cap) to the end of
    its skeleton axis (``usdforest:tip``)."""
    errors = []
    for p in wood_prims(stage, root).values():
        m = world_mesh(p)
        tip = np.array(p.GetAttribute("usdforest:tip").Get(), dtype=np.float64)
        base = base_point(p)
        axis = (tip - base) / np.linalg.norm(tip - base)
        t = (m.vertices - base) @ axis
        cap = m.vertices[t >= t.max() - 0.02 * np.ptp(t)]
        # the cap's middle across the axis, at the mesh's far end along it (a pointed trunk's
        # apex; a cut end's cap)
        mid = 0.5 * (cap.min(0) + cap.max(0))
        end = mid + axis * (t.max() - (mid - base) @ axis)
        errors.append(float(np.linalg.norm(end - tip)))
    return np.array(errors)


def silhouette_area(tris: np.ndarray, axes: tuple[int, int], cell: float = 0.05) -> float:
    """Area (m²) of the union of the triangles projected on the plane of ``axes``, on a
    ``cell``-metre raster: a cell counts when its centre is inside a projected triangle, or
    when a triangle smaller than a cell has its centroid in it."""
    p = tris[:, :, list(axes)]
    lo = np.floor(p.min(axis=1) / cell).astype(np.int64)
    hi = np.floor(p.max(axis=1) / cell).astype(np.int64)
    small = np.all(hi - lo <= 1, axis=1)
    keys = [np.floor(p[small].mean(axis=1) / cell).astype(np.int64)]
    for tri, a, b in zip(p[~small], lo[~small], hi[~small], strict=True):
        gx, gy = np.meshgrid(np.arange(a[0], b[0] + 1), np.arange(a[1], b[1] + 1))
        grid = np.stack([gx.ravel(), gy.ravel()], 1)
        inside = MplPath(tri).contains_points((grid + 0.5) * cell, radius=1e-9)
        keys.append(grid[inside])
    cells = np.unique(np.concatenate(keys), axis=0)
    return float(len(cells) * cell * cell)


def composed_triangles(stage: Usd.Stage) -> np.ndarray:
    """``(n, 3, 3)`` world-space triangles of every Mesh in the stage, PointInstancers (nested
    ones included) expanded through ``ComputeInstanceTransformsAtTime``."""
    out: list[np.ndarray] = []

    def visit(prim: Usd.Prim, xf: np.ndarray) -> None:
        it = iter(Usd.PrimRange(prim, Usd.TraverseInstanceProxies()))
        for p in it:
            if p.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()
                pi = UsdGeom.PointInstancer(p)
                protos = pi.GetPrototypesRel().GetTargets()
                idx = np.asarray(pi.GetProtoIndicesAttr().Get())
                mats = np.asarray(pi.ComputeInstanceTransformsAtTime(T0, T0))
                here = np.asarray(UsdGeom.Xformable(p).ComputeLocalToWorldTransform(T0)) @ xf
                for k, path in enumerate(protos):
                    local = triangles_under(p.GetStage().GetPrimAtPath(path))
                    full = mats[idx == k] @ here  # (n, 4, 4) row-vector transforms
                    tris = np.einsum("tvj,njk->ntvk", local, full[:, :3, :3])
                    out.append((tris + full[:, None, None, 3, :3]).reshape(-1, 3, 3))
            elif p.IsA(UsdGeom.Mesh) and renders(p):
                pts = _world_points(p) @ xf[:3, :3] + xf[3, :3]
                out.append(pts[_triangles(p)])

    visit(stage.GetPseudoRoot(), np.eye(4))
    return np.concatenate(out) if out else np.zeros((0, 3, 3))


def triangles_under(proto: Usd.Prim) -> np.ndarray:
    """Triangles of the Meshes under a prototype, in the prototype's own space."""
    inv = np.linalg.inv(np.asarray(UsdGeom.Xformable(proto).ComputeLocalToWorldTransform(T0)))
    tris = []
    for p in Usd.PrimRange(proto, Usd.TraverseInstanceProxies()):
        if p.IsA(UsdGeom.Mesh) and renders(p):
            pts = _world_points(p) @ inv[:3, :3] + inv[3, :3]
            tris.append(pts[_triangles(p)])
    return np.concatenate(tris) if tris else np.zeros((0, 3, 3))
