"""Composed statistics of a stage: prims, meshes, branches, leaves, triangles after instancing."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom

from usdforest.progress import Progress
from usdforest.usd.layers import LOD_SET, class_labels, open_stage, rendered, time_range


@dataclass
class _Tally:
    meshes: int = 0
    triangles: int = 0
    leaves: int = 0
    trees: int = 0
    instances: int = 0
    labels: Counter = field(default_factory=Counter)

    def add(self, other: _Tally, times: int = 1) -> None:
        self.meshes += other.meshes * times
        self.triangles += other.triangles * times
        self.leaves += other.leaves * times
        self.trees += other.trees * times
        self.instances += other.instances * times


def _mesh_triangles(mesh: UsdGeom.Mesh) -> int:
    counts = mesh.GetFaceVertexCountsAttr().Get()
    if counts is None:
        return 0
    c = np.asarray(counts)
    return int(np.maximum(c - 2, 0).sum())


def _expand(prim: Usd.Prim, cache: dict) -> _Tally:
    """Tally of ``prim``'s subtree with every PointInstancer expanded (memoised per prim; an
    instance proxy's under its prototype's prim, which holds every opinion it has)."""
    key = prim.GetPrimInPrototype().GetPath() if prim.IsInstanceProxy() else prim.GetPath()
    if key in cache:
        return cache[key]
    t = _Tally()
    if not rendered(prim):  # the proxy beside the full tree, colliders
        cache[key] = t
        return t
    if prim.IsA(UsdGeom.Mesh):
        t.meshes = 1
        t.triangles = _mesh_triangles(UsdGeom.Mesh(prim))
    elif prim.IsA(UsdGeom.PointInstancer):
        pi = UsdGeom.PointInstancer(prim)
        idx = pi.GetProtoIndicesAttr().Get()
        counts = (
            np.bincount(np.asarray(idx, dtype=np.int64))
            if idx is not None and len(idx)
            else np.zeros(0, dtype=np.int64)
        )
        protos = pi.GetPrototypesRel().GetTargets()
        is_leafy = "leaf" in class_labels(prim)
        for k, path in enumerate(protos):
            n = int(counts[k]) if k < len(counts) else 0
            proto = prim.GetStage().GetPrimAtPath(path)
            if not proto or n == 0:
                continue
            sub = _expand(proto, cache)
            t.add(sub, n)
            t.instances += n
            if is_leafy:
                t.leaves += n
        cache[key] = t
        return t
    if "tree" in class_labels(prim):
        t.trees += 1
    if prim.IsInstance():  # what lies below is its prototype's, the same for every instance
        proto = prim.GetPrototype()
        below = cache.get(("below", proto.GetPath()))
        if below is None:
            below = cache["below", proto.GetPath()] = _Tally()
            for child in proto.GetFilteredChildren(Usd.TraverseInstanceProxies()):
                below.add(_expand(child, cache))
        t.add(below)
    else:
        for child in prim.GetFilteredChildren(Usd.TraverseInstanceProxies()):
            t.add(_expand(child, cache))
    cache[key] = t
    return t


@dataclass
class _Prims:
    """What :func:`_prims` counts in a subtree (``orders``: the wood prims' paths below its
    root, their order and axis)."""

    count: int = 0
    levels: Counter = field(default_factory=Counter)
    orders: list = field(default_factory=list)

    def visit(self, p: Usd.Prim, below: str) -> None:
        self.count += 1
        if p.IsPseudoRoot():  # an empty stage's root: no properties to ask for
            return
        if p.GetVariantSets().HasVariantSet(LOD_SET):
            self.levels[p.GetVariantSet(LOD_SET).GetVariantSelection()] += 1
        a = p.GetAttribute("usdforest:order")
        if a and a.HasValue():
            ax = p.GetAttribute("usdforest:axis")
            self.orders.append((below, int(a.Get()), int(ax.Get()) if ax else -1))


def _prims(root: Usd.Prim) -> tuple[int, Counter, Counter, dict[int, set]]:
    """Prims under ``root`` with instance proxies (each prototype's walked once), the level
    of detail each LOD variant set selects, wood prims by order, and the branches (tree and
    axis) of each order."""
    seen = _Prims()
    inside: dict[Sdf.Path, _Prims] = {}  # each prototype's prims below its root
    for p in Usd.PrimRange(root):
        at = str(p.GetPath())
        seen.visit(p, at)
        if not p.IsInstance():
            continue
        proto = p.GetPrototype()
        got = inside.get(proto.GetPath())
        if got is None:
            got = inside[proto.GetPath()] = _Prims()
            base = proto.GetPath()
            for q in list(Usd.PrimRange(proto, Usd.TraverseInstanceProxies()))[1:]:
                got.visit(q, str(q.GetPath().MakeRelativePath(base)))
        seen.count += got.count
        seen.levels.update(got.levels)
        seen.orders += [(f"{at}/{below}", order, axis) for below, order, axis in got.orders]
    by_order: Counter = Counter()
    axes: dict[int, set] = {}
    for path, order, axis in seen.orders:
        by_order[order] += 1
        tree = path.split("/Branches/")[0].replace("/Trunk", "")
        axes.setdefault(order, set()).add((tree, axis))
    return seen.count, seen.levels, by_order, axes


def stage_info(path: str | Path, *, full: bool = False, progress: Progress | None = None) -> dict:
    """Composed statistics for the stage at ``path``, at the levels of detail its layers
    select (what a client opens), or with every tree at ``full`` detail (what sensors see).

    Triangles and leaves count every instance: a forest of 1,000 trees of 500 leaves reports
    500,000 leaves. ``lod`` counts the tree prims by the level they show.
    ``progress(stage, done, total)`` as each of its three steps ends.
    """
    tick = progress or (lambda stage, done, total: None)
    tick("reading the stage", 0, 3)
    path = Path(path)
    stage = open_stage(path, sound=True, full=full)
    tick("reading the stage", 1, 3)
    root = stage.GetDefaultPrim() or stage.GetPseudoRoot()
    prims, levels, by_order, axes = _prims(root)
    tick("reading the stage", 2, 3)
    tally = _expand(root, {})
    bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"], True)
    box = bbox.ComputeWorldBound(root).ComputeAlignedRange()
    base = path.parent.resolve()
    layers = []
    for layer in stage.GetUsedLayers():
        if layer.anonymous:
            continue
        real = Path(layer.realPath) if layer.realPath else None
        try:
            layers.append(str(real.relative_to(base)) if real else layer.identifier)
        except ValueError:
            layers.append(str(real))
    tick("reading the stage", 3, 3)
    return {
        "stage": str(path),
        "default_prim": str(root.GetPath()),
        "prims": prims,
        "meshes": tally.meshes,
        "triangles": tally.triangles,
        "leaves": tally.leaves,
        "instances": tally.instances,
        "trees": tally.trees,
        "lod": dict(sorted(levels.items())),
        "wood_prims_by_order": {str(k): v for k, v in sorted(by_order.items())},
        "branches_by_order": {str(k): len(v) for k, v in sorted(axes.items())},
        "extent": [list(box.GetMin()), list(box.GetMax())] if not box.IsEmpty() else None,
        "animation": _animation(stage),
        "layers": sorted(layers),
    }


def _animation(stage: Usd.Stage) -> dict | None:
    """The stage's time range as its root layer gives it (a forest's wind: seconds, time
    codes, time codes a second, whether it loops); None for a stage without one."""
    start, end, tcps, loops = time_range(stage.GetRootLayer())
    if not end > start:
        return None
    return {
        "seconds": end - start,
        "time_codes": round((end - start) * tcps) + 1,
        "time_codes_per_second": tcps,
        "loops": loops,
    }
