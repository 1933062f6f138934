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
    """``(t, 3)`` vertex indices: each face fanned from its first vertex."""
    mesh = UsdGeom.Mesh(prim)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    fans = np.maximum(counts - 2, 0)
    face = np.repeat(np.arange(len(counts)), fans)
    # k-th triangle of its face: vertices 0, k + 1, k + 2 of the face
    k = np.arange(int(fans.sum())) - np.repeat(np.cumsum(fans) - fans, fans)
    s = starts[face]
    return np.stack([idx[s], idx[s + k + 1], idx[s + k + 2]], axis=1)


def placed(local: np.ndarray, mats: np.ndarray) -> np.ndarray:
    """``(n, p, 3)``: the points ``local`` ``(p, 3)`` moved by each of the row-vector
    transforms ``mats`` ``(n, 4, 4)`` (one matrix product, not a loop)."""
    turned = np.tensordot(local, mats[:, :3, :3], axes=([1], [1]))  # (p, n, 3)
    return turned.transpose(1, 0, 2) + mats[:, None, 3, :3]


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


def _composed_pieces(stage: Usd.Stage, chunk: int | None = None, corners: bool = False):
    """World-space triangles ``(m, 3, 3)`` of every Mesh in the stage, piece by piece:
    PointInstancers expanded through ``ComputeInstanceTransformsAtTime``, ``chunk``
    instances at a time (all at once with None; ``corners``: see
    :func:`instanced_triangles`)."""
    it = iter(Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies()))
    for p in it:
        if p.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            here = np.asarray(UsdGeom.Xformable(p).ComputeLocalToWorldTransform(T0))
            yield from instanced_triangles(UsdGeom.PointInstancer(p), here, chunk, corners)
        elif p.IsA(UsdGeom.Mesh) and renders(p):
            yield _world_points(p)[_triangles(p)]


def instanced_triangles(
    pi: UsdGeom.PointInstancer,
    here: np.ndarray,
    chunk: int | None = None,
    corners: bool = False,
):
    """The triangles ``(m, 3, 3)`` of the instancer's instances, placed by their transforms
    times ``here`` (the instancer's own to world: the identity for its own space), ``chunk``
    instances at a time (all of a prototype's at once with None); with ``corners``, only
    their distinct corners ``(n, c, 3)`` (what a bounding box needs)."""
    protos = pi.GetPrototypesRel().GetTargets()
    idx = np.asarray(pi.GetProtoIndicesAttr().Get())
    mats = np.asarray(pi.ComputeInstanceTransformsAtTime(T0, T0))
    for k, path in enumerate(protos):
        local = triangles_under(pi.GetPrim().GetStage().GetPrimAtPath(path)).reshape(-1, 3)
        if corners:
            local = np.unique(local, axis=0)
        full = mats[idx == k] @ here  # (n, 4, 4) row-vector transforms
        step = chunk or max(len(full), 1)
        for a in range(0, len(full), step):
            moved = placed(local, full[a : a + step])
            yield moved if corners else moved.reshape(-1, 3, 3)


def composed_triangles(stage: Usd.Stage) -> np.ndarray:
    """``(n, 3, 3)`` world-space triangles of every Mesh in the stage, PointInstancers
    expanded through ``ComputeInstanceTransformsAtTime``."""
    out = list(_composed_pieces(stage))
    return np.concatenate(out) if out else np.zeros((0, 3, 3))


def composed_bounds(stage: Usd.Stage) -> np.ndarray:
    """``(2, 3)`` the box of :func:`composed_triangles`, without holding them all."""
    return bounds_of(_composed_pieces(stage, chunk=256, corners=True))


def bounds_of(pieces) -> np.ndarray:
    """``(2, 3)`` the box of the points of every array in ``pieces`` (each ``(..., 3)``)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for x in pieces:
        if x.size:
            axes = tuple(range(x.ndim - 1))
            lo, hi = np.minimum(lo, x.min(axis=axes)), np.maximum(hi, x.max(axis=axes))
    return np.stack([lo, hi])


def triangles_under(proto: Usd.Prim) -> np.ndarray:
    """Triangles of the Meshes under a prototype, in the prototype's own space."""
    inv = np.linalg.inv(np.asarray(UsdGeom.Xformable(proto).ComputeLocalToWorldTransform(T0)))
    tris = []
    for p in Usd.PrimRange(proto, Usd.TraverseInstanceProxies()):
        if p.IsA(UsdGeom.Mesh) and renders(p):
            pts = _world_points(p) @ inv[:3, :3] + inv[3, :3]
            tris.append(pts[_triangles(p)])
    return np.concatenate(tris) if tris else np.zeros((0, 3, 3))
