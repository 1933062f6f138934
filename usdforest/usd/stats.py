"""Composed statistics of a stage: prims, meshes, branches, leaves, triangles after instancing."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom

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
    """Tally of ``prim``'s subtree with every PointInstancer expanded (memoised per prim)."""
    key = prim.GetPath()
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
    for child in prim.GetFilteredChildren(Usd.TraverseInstanceProxies()):
        t.add(_expand(child, cache))
    cache[key] = t
    return t


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
    prims = 0
    by_order: Counter = Counter()
    axes: dict[int, set] = {}
    levels: Counter = Counter()
    for p in Usd.PrimRange(root, Usd.TraverseInstanceProxies()):
        prims += 1
        if p.IsPseudoRoot():  # an empty stage's root: no properties to ask for
            continue
        if p.GetVariantSets().HasVariantSet(LOD_SET):
            levels[p.GetVariantSet(LOD_SET).GetVariantSelection()] += 1
        a = p.GetAttribute("usdforest:order")
        if a and a.HasValue():
            order = int(a.Get())
            by_order[order] += 1
            ax = p.GetAttribute("usdforest:axis")
            tree = str(p.GetPath()).split("/Branches/")[0].replace("/Trunk", "")
            axes.setdefault(order, set()).add((tree, int(ax.Get()) if ax else -1))
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
