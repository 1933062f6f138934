"""Stand figures measured on a composed forest: what a forest inventory would report.

Read with pxr from the composed stage, not from the build's arrays: every tree instance of the
forest's PointInstancers (tiles included, once loaded), its prototype's composed geometry and
the instance's transform. Per tree: height (its composed extent), DBH (a girth tape round
the composed trunk mesh 1.3 m up its stem, perpendicular to it: the perimeter of the
cross-section's hull over pi), one-sided leaf area (every leaf instance's template area -
half the surface of a closed needle mesh - times its scale squared) and wood area (half the
surface of its trunk and branch meshes, the same one-sided convention). Per stand:
stems/ha, basal area, quadratic mean DBH, DBH and height distributions, leaf and wood area
indices (over the region's area) and the crown footprint cover (the share of 0.25 m cells
of the region under any leaf or wood point: crowns' outlines, not what a sensor sees through
them; canopy cover and gap fractions by rays are :mod:`usdforest.sensors.optics.gaps`').
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom

from usdforest.cad.parts import one_sided_area, triangle_areas
from usdforest.errors import UsdForestError
from usdforest.grow.stems import hull_perimeter
from usdforest.progress import Progress
from usdforest.usd.debris import dead_wood_figures, is_dead_wood
from usdforest.usd.floor import ground_vegetation_figures, is_ground_vegetation
from usdforest.usd.layers import open_stage, rendered
from usdforest.usd.undergrowth import is_understorey, understorey_figures

CELL = 0.25  # m, the cover raster
BREAST = 1.3


def mesh_world(prim: Usd.Prim, cache: UsdGeom.XformCache, to_local: np.ndarray):
    """A Mesh's points in the space ``to_local`` maps the world to (row vectors), and its
    triangles (``None`` unless every face is one)."""
    m = np.asarray(cache.GetLocalToWorldTransform(prim), dtype=float) @ to_local
    return _points(prim) @ m[:3, :3] + m[3, :3], _triangles(prim)


def _points(prim: Usd.Prim) -> np.ndarray:
    return np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get() or [], dtype=float).reshape(-1, 3)


def _triangles(prim: Usd.Prim) -> np.ndarray | None:
    mesh = UsdGeom.Mesh(prim)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    return idx.reshape(-1, 3) if len(counts) and np.all(counts == 3) else None


def girth_dbh(
    points: np.ndarray,
    tri: np.ndarray,
    z: np.ndarray,
    origin: np.ndarray | None = None,
    axis: np.ndarray | None = None,
) -> np.ndarray:
    """Girth-tape diameters of the mesh at distances ``z`` along its stem's ``axis`` from
    ``origin`` (default: heights above z = 0): the hull perimeter of the section
    perpendicular to the axis, over pi."""
    import trimesh

    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=float)
    n = np.array([0.0, 0.0, 1.0]) if axis is None else np.asarray(axis, dtype=float)
    n = n / np.linalg.norm(n)
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    mesh = trimesh.Trimesh(points, tri, process=False)
    out = np.full(len(z), np.nan)
    for i, h in enumerate(z):
        seg = trimesh.intersections.mesh_plane(mesh, n, o + h * n).reshape(-1, 3) - o
        girth = hull_perimeter(np.column_stack([seg @ u, seg @ v]))
        if girth > 0:  # (0: no section, or a degenerate one)
            out[i] = girth / math.pi
    return out


def _leaf_unit_area(proto: Usd.Prim) -> float:
    """One-sided area of a leaf prototype (:func:`usdforest.cad.parts.one_sided_area` of each of
    its meshes), in its own space."""
    cache = UsdGeom.XformCache()
    inv = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(proto), dtype=float))
    total = 0.0
    for p in Usd.PrimRange(proto, Usd.TraverseInstanceProxies()):
        if p.IsA(UsdGeom.Mesh):
            v, tri = mesh_world(p, cache, inv)
            if tri is not None and len(tri):
                total += one_sided_area(v, tri)
    return total


def _footprints(instancer: Usd.Prim) -> dict[str, float]:
    """Each prototype's crown footprint (m²: the hull of every point of its rendered wood and
    leaf meshes, leaves placed by their instancers, on the ground, in its own space), by
    prototype path."""
    from scipy.spatial import ConvexHull

    out = {}
    stage = instancer.GetStage()
    cache = UsdGeom.XformCache()
    for target in UsdGeom.PointInstancer(instancer).GetPrototypesRel().GetTargets():
        proto = stage.GetPrimAtPath(target)
        inv = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(proto), dtype=float))
        xy = []
        it = iter(Usd.PrimRange(proto, Usd.TraverseInstanceProxies()))
        for p in it:
            if not rendered(p):
                it.PruneChildren()
            elif p.IsA(UsdGeom.Mesh):
                xy.append(mesh_world(p, cache, inv)[0][:, :2])
            elif p.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()
                pi = UsdGeom.PointInstancer(p)
                mats = np.asarray(
                    pi.ComputeInstanceTransformsAtTime(
                        Usd.TimeCode.Default(), Usd.TimeCode.Default()
                    )
                )
                idx = np.asarray(pi.GetProtoIndicesAttr().Get() or [], dtype=np.int64)
                to = np.asarray(cache.GetLocalToWorldTransform(p), dtype=float) @ inv
                for k, leaf in enumerate(pi.GetPrototypesRel().GetTargets()):
                    lp = stage.GetPrimAtPath(leaf)
                    own = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(lp), float))
                    pts = np.concatenate(
                        [
                            mesh_world(m, cache, own)[0]
                            for m in Usd.PrimRange(lp)
                            if m.IsA(UsdGeom.Mesh)
                        ]
                    )
                    m = mats[idx == k] @ to
                    placed = np.einsum("pj,njk->npk", pts, m[:, :3, :3]) + m[:, None, 3, :3]
                    xy.append(placed[..., :2].reshape(-1, 2))
        pts = np.concatenate(xy) if xy else np.zeros((0, 2))
        out[str(target)] = float(ConvexHull(pts).volume) if len(pts) >= 3 else 0.0
    return out


AREA_BATCH = 200_000  # wood triangles summed at once (72 bytes of corners each)


def _one_sided_area(corners: list[np.ndarray]) -> float:
    """Half the surface of the triangles ``corners`` (arrays of (k, 3, 3)): many small
    meshes in one pass (a pass a mesh cost the default forest's 47,000 meshes 4 s)."""
    if not corners:
        return 0.0
    return 0.5 * float(triangle_areas(np.concatenate(corners)).sum())


@dataclass(frozen=True)
class _Shape:
    """A native prototype's rendered meshes in the space of its root: (the path below the
    root, points, triangles or None) each. ``flat`` is False where the prototype holds a
    PointInstancer or resets the transform stack: its instances are then walked proxy by
    proxy."""

    meshes: tuple[tuple[str, np.ndarray, np.ndarray | None], ...]
    flat: bool


def _shape(proto: Usd.Prim) -> _Shape:
    cache = UsdGeom.XformCache()
    meshes = []
    it = iter(Usd.PrimRange(proto, Usd.TraverseInstanceProxies()))
    for p in it:
        if not rendered(p):
            it.PruneChildren()
        elif p.IsA(UsdGeom.PointInstancer):
            return _Shape((), False)
        elif p.IsA(UsdGeom.Mesh):
            rel, resets = cache.ComputeRelativeTransform(p, proto)
            if resets:
                return _Shape((), False)
            m = np.asarray(rel, dtype=float)
            below = str(p.GetPath().MakeRelativePath(proto.GetPath()))
            meshes.append((below, _points(p) @ m[:3, :3] + m[3, :3], _triangles(p)))
    return _Shape(tuple(meshes), True)


class _Tree:
    """What :func:`_tree_figures` gathers from one tree's meshes and leaf instancers."""

    def __init__(self, tree: Usd.Prim, cache: UsdGeom.XformCache, inv: np.ndarray):
        self.tree, self.cache, self.inv = tree, cache, inv
        self.wood_xy: list[np.ndarray] = []
        self.leaf_xy: list[np.ndarray] = []
        self.leaf_area = self.wood_area = 0.0
        self.wood_tri: list[np.ndarray] = []  # corners not yet summed, an array a mesh
        self.pending = 0
        # the trunk's points and triangles, and where its stem starts and its axis
        self.trunk: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def wood(self, v: np.ndarray, tri: np.ndarray | None) -> None:
        """A wood mesh: its points ``v`` in the tree's space and its triangles ``tri``
        (``v`` may hold many instances' copies, (n, k, 3), of one mesh)."""
        self.wood_xy.append(v[..., :2].reshape(-1, 2))
        if tri is not None and len(tri):
            corners = v[..., tri, :].reshape(-1, 3, 3)
            self.wood_tri.append(corners)
            self.pending += len(corners)
            if self.pending > AREA_BATCH:
                self.wood_area += _one_sided_area(self.wood_tri)
                self.wood_tri, self.pending = [], 0

    def prim(self, p: Usd.Prim) -> None:
        """A mesh or leaf instancer met prim by prim (an instance proxy or not)."""
        if p.IsA(UsdGeom.Mesh):
            path = str(p.GetPath())
            if "/Leaves" in path:
                return
            v, tri = mesh_world(p, self.cache, self.inv)
            self.wood(v, tri)
            if "/Trunk" in path and tri is not None and self.trunk is None:
                holder = p
                while holder.GetName() != "Trunk" and holder.GetParent():
                    holder = holder.GetParent()
                m = np.asarray(self.cache.GetLocalToWorldTransform(holder), dtype=float) @ self.inv
                self.trunk = (v, tri, m[3, :3], m[2, :3])
        elif p.IsA(UsdGeom.PointInstancer):
            pi = UsdGeom.PointInstancer(p)
            mats = np.asarray(
                pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
            )
            if not len(mats):
                return
            m = np.asarray(self.cache.GetLocalToWorldTransform(p), dtype=float) @ self.inv
            pos = mats[:, 3, :3] @ m[:3, :3] + m[3, :3]
            self.leaf_xy.append(pos[:, :2])
            idx = np.asarray(pi.GetProtoIndicesAttr().Get(), dtype=np.int64)
            s2 = np.abs(np.linalg.det(mats[:, :3, :3])) ** (2.0 / 3.0)
            stage = self.tree.GetStage()
            units = [
                _leaf_unit_area(stage.GetPrimAtPath(t)) for t in pi.GetPrototypesRel().GetTargets()
            ]
            grow2 = abs(np.linalg.det(m[:3, :3])) ** (2.0 / 3.0)
            self.leaf_area += float(np.sum(s2 * np.asarray(units)[idx])) * grow2


PROBES = 40  # breast heights cut on a prototype's trunk; more are interpolated
INSTANCE_POINTS = 1_000_000  # instance copies of a prototype's points placed at once


def _tree_figures(tree: Usd.Prim, breast: np.ndarray, shapes: dict | None = None) -> dict:
    """One tree prototype (its own space, base at z = 0): height, DBH at each of ``breast``
    heights, leaf area, and the xy of its leaf and wood points.

    The meshes under native instances (a tree's trunk and branches reference their templates
    instanceable) are read once per prototype (``shapes``, shared between trees) and placed
    by every instance's transform at once: what the instance proxies hold, without a walk of
    the stand-1ha forest's 738,000 proxies (17 s)."""
    shapes = {} if shapes is None else shapes
    cache = UsdGeom.XformCache()
    inv = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(tree), dtype=float))
    got = _Tree(tree, cache, inv)
    placed: dict[tuple, list[np.ndarray]] = {}  # (prototype, mesh): instance transforms
    it = iter(Usd.PrimRange(tree))
    for p in it:
        if not rendered(p):  # the proxy hull and guides are not the tree
            it.PruneChildren()
            continue
        got.prim(p)
        if not p.IsInstance():
            continue
        key = p.GetPrototype().GetPath()
        shape = shapes.get(key)
        if shape is None:
            shape = shapes[key] = _shape(p.GetPrototype())
        if not shape.flat:
            inner = iter(Usd.PrimRange(p, Usd.TraverseInstanceProxies()))
            next(inner)  # the instance itself, met above
            for q in inner:
                if not rendered(q):
                    inner.PruneChildren()
                else:
                    got.prim(q)
            continue
        m = np.asarray(cache.GetLocalToWorldTransform(p), dtype=float) @ inv
        at = str(p.GetPath())
        for j, (below, pts, tri) in enumerate(shape.meshes):
            path = f"{at}/{below}"
            if "/Leaves" in path:
                continue
            placed.setdefault((key, j), []).append(m)
            if "/Trunk" in path and tri is not None and got.trunk is None:
                got.trunk = (pts @ m[:3, :3] + m[3, :3], tri, m[3, :3], m[2, :3])
    for (key, j), mats in placed.items():
        _, pts, tri = shapes[key].meshes[j]
        ms = np.stack(mats)
        step = max(1, INSTANCE_POINTS // max(len(pts), 1))
        for a in range(0, len(ms), step):
            m = ms[a : a + step]
            v = np.einsum("pj,njk->npk", pts, m[:, :3, :3]) + m[:, None, 3, :3]
            got.wood(v, tri)
    got.wood_area += _one_sided_area(got.wood_tri)
    bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"], True)
    r = bbox.ComputeWorldBound(tree).ComputeAlignedRange()
    ext = np.array([list(r.GetMin()), list(r.GetMax())]) @ inv[:3, :3] + inv[3, :3]
    trunk = got.trunk
    dbh = (
        girth_dbh(trunk[0], trunk[1], breast, trunk[2], trunk[3])
        if trunk is not None
        else np.full(len(breast), np.nan)
    )
    xy = [*got.wood_xy, *got.leaf_xy]
    return {
        "height": float(ext[:, 2].max() - min(ext[:, 2].min(), 0.0)),
        "dbh": dbh,
        "leaf_area": got.leaf_area,
        "wood_area": got.wood_area,
        "xy": np.concatenate(xy) if xy else np.zeros((0, 2)),
    }


def _cells(xy: np.ndarray, size: float) -> np.ndarray:
    """The distinct cells of side ``size`` holding the points ``xy`` (their lower corners,
    sorted by x then y: ``np.unique(..., axis=0)`` of the floored points, without its
    row sort)."""
    q = np.floor(xy / size).astype(np.int64)
    if not len(q):
        return np.zeros((0, 2))
    low = q.min(axis=0)
    q -= low
    span = int(q[:, 1].max()) + 1
    u = np.unique(q[:, 0] * span + q[:, 1])
    return (np.stack([u // span, u % span], axis=1) + low) * size


def _cover(grid: tuple[np.ndarray, np.ndarray], pts: np.ndarray, mats: np.ndarray) -> None:
    """Mark the cells of ``grid`` (region bounds, boolean raster) under the prototype points
    ``pts`` (k, 2) of every instance transform ``mats`` (n, 4, 4), a batch at a time."""
    b, g = grid
    batch = max(1, 2_000_000 // max(len(pts), 1))
    for a in range(0, len(mats), batch):
        m = mats[a : a + batch]
        w = (pts @ m[:, :2, :2] + m[:, None, 3, :2]).reshape(-1, 2)
        cx = np.floor((w[:, 0] - b[0]) / CELL).astype(np.int64)
        cy = np.floor((w[:, 1] - b[1]) / CELL).astype(np.int64)
        ok = (cx >= 0) & (cy >= 0) & (cx < g.shape[1]) & (cy < g.shape[0])
        g[cy[ok], cx[ok]] = True


@contextmanager
def _step(tick: Progress, name: str) -> Iterator[None]:
    """The block, reported through ``tick`` as the one-part step ``name``."""
    tick(name, 0, 1)
    yield
    tick(name, 1, 1)


def open_forest(path: str | Path, progress: Progress | None = None) -> Usd.Stage:
    """The forest at ``path`` opened as the figures measure it: every tree at full detail,
    its geometry checked."""
    tick = progress or (lambda stage, done, total: None)
    tick("opening the stage", 0, 1)
    stage = open_stage(Path(path), sound=True, full=True)
    tick("opening the stage", 1, 1)
    return stage


def stand_figures(
    path: str | Path, progress: Progress | None = None, *, stage: Usd.Stage | None = None
) -> dict:
    """Stand figures of the forest at ``path`` (see the module docstring);
    ``progress(stage, done, total)`` as the stage opens and each tree prototype is measured.
    ``stage``: the forest already opened as :func:`open_forest` opens it (not opened again)."""
    tick = progress or (lambda stage, done, total: None)
    if stage is None:
        stage = open_forest(path, tick)
    measured = [0]
    root = stage.GetDefaultPrim()
    if not root:
        raise UsdForestError(f"{path}: no default prim")
    data = root.GetCustomDataByKey("usdforest") or {}
    area = float(data.get("regionArea", 0.0))
    bounds = data.get("regionBounds")
    if not area and bounds is not None:
        b = list(bounds)
        area = (b[2] - b[0]) * (b[3] - b[1])
    if not area:
        raise UsdForestError(f"{path}: not a usdforest forest (no regionArea in /Forest)")
    heights, dbhs, leaf, wood, species, where = [], [], [], [], [], []
    dead = dead_wood_figures(None, area)
    green = ground_vegetation_figures(None, area)
    under = understorey_figures(None, area, {})
    grid = None
    shapes: dict = {}  # native prototypes' meshes, read once for every tree
    if bounds is not None:
        b = np.asarray(list(bounds), dtype=float)
        nx = max(math.ceil((b[2] - b[0]) / CELL), 1)
        ny = max(math.ceil((b[3] - b[1]) / CELL), 1)
        grid = (b, np.zeros((ny, nx), dtype=bool))
    for p in Usd.PrimRange(root):
        if not p.IsA(UsdGeom.PointInstancer) or p.GetName() == "Leaves":
            continue
        if is_dead_wood(p):
            with _step(tick, "measuring dead wood"):
                dead = dead_wood_figures(p, area)
            continue
        if is_ground_vegetation(p):
            with _step(tick, "measuring ground vegetation"):
                green = ground_vegetation_figures(p, area)
            continue
        if is_understorey(p):
            with _step(tick, "measuring the understorey"):
                under = understorey_figures(p, area, _footprints(p))
            continue
        pi = UsdGeom.PointInstancer(p)
        idx = np.asarray(pi.GetProtoIndicesAttr().Get() or [], dtype=np.int64)
        if not len(idx):
            continue
        mats = np.asarray(
            pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
        )
        world = np.asarray(UsdGeom.XformCache().GetLocalToWorldTransform(p), dtype=float)
        scale = np.abs(np.linalg.det(mats[:, :3, :3])) ** (1.0 / 3.0)
        targets = pi.GetPrototypesRel().GetTargets()
        for k, target in enumerate(targets):
            sel = np.flatnonzero(idx == k)
            measured[0] += 1
            tick("measuring trees", measured[0], len(targets))
            if not len(sel):
                continue
            proto = stage.GetPrimAtPath(target)
            s = scale[sel]
            # DBH at each tree's breast height (1.3 m / its scale on the prototype, along its
            # stem), cut at each (to a millimetre), or at 40 heights and interpolated beyond
            zs = np.unique(np.round(BREAST / s, 3))
            probe = np.linspace(zs.min(), zs.max(), PROBES) if len(zs) > PROBES else zs
            f = _tree_figures(proto, probe, shapes)
            # a sapling's breast height is above its trunk (no DBH); the others' from the
            # probes that meet the trunk
            ok = np.isfinite(f["dbh"])
            d = (np.interp(BREAST / s, probe[ok], f["dbh"][ok]) if ok.any() else np.nan) * s
            d = np.where(f["height"] * s < BREAST, np.nan, d)
            heights.append(f["height"] * s)
            dbhs.append(d)
            leaf.append(f["leaf_area"] * s**2)
            wood.append(f["wood_area"] * s**2)
            label = proto.GetCustomDataByKey("usdforest") or {}
            species.append(np.full(len(sel), str(label.get("species", target.name))))
            where.append((mats[sel] @ world)[:, 3, :2])
            if grid is not None and len(f["xy"]):
                _cover(grid, _cells(f["xy"], CELL / 2), mats[sel] @ world)
    h = np.concatenate(heights) if heights else np.zeros(0)
    d = np.concatenate(dbhs) if dbhs else np.zeros(0)
    la = np.concatenate(leaf) if leaf else np.zeros(0)
    wa = np.concatenate(wood) if wood else np.zeros(0)
    sp = np.concatenate(species) if species else np.zeros(0, dtype=str)
    ha = area / 1e4
    known = np.isfinite(d)
    dk = d[known]

    def dist(x: np.ndarray) -> dict:
        if not len(x):
            return {}
        return {
            "mean": float(x.mean()),
            "sd": float(x.std(ddof=1)) if len(x) > 1 else 0.0,
            "cv": float(x.std(ddof=1) / x.mean()) if len(x) > 1 and x.mean() else 0.0,
            "p10": float(np.percentile(x, 10)),
            "median": float(np.median(x)),
            "p90": float(np.percentile(x, 90)),
        }

    return {
        "stage": str(path),
        "area_ha": ha,
        "trees": len(h),
        "stems_per_ha": len(h) / ha,
        "basal_area_m2_per_ha": float(np.sum(math.pi * (dk / 2) ** 2) / ha),
        "quadratic_mean_dbh_m": float(np.sqrt(np.mean(dk**2))) if len(dk) else None,
        "dbh_m": dist(dk),
        "height_m": dist(h),
        "slenderness": dist(h[known] / dk) if len(dk) else {},
        "leaf_area_index": float(la.sum() / area),
        "wood_area_index": float(wa.sum() / area),
        "wood_to_leaf_area": float(wa.sum() / la.sum()) if la.sum() else None,
        "crown_footprint_cover": float(grid[1].mean()) if grid is not None else None,
        **dead,
        **green,
        **under,
        "region_bounds": [float(v) for v in bounds] if bounds is not None else None,
        "species": {
            str(n): int(c) for n, c in zip(*np.unique(sp, return_counts=True), strict=True)
        },
        "per_tree": {
            "species": sp,
            "height": h,
            "dbh": d,
            "leaf_area": la,
            "wood_area": wa,
            "xy": np.concatenate(where) if where else np.zeros((0, 2)),
        },
    }
