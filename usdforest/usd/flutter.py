"""Leaf flutter in the wind layer: every tree's leaves twisting and flapping in time, as a few
shared rotations.

The flutter's classes (:func:`usdforest.grow.sway.flutter`) are root ``class`` prims of the
wind layer, ``/_class_Flutter_<k>``, each holding ``xformOp:orient:flutter``: the class's
rotation in a leaf's own frame at every time code (at rest by default). Each leaf instancer
of each tree prototype gets, as overs in the same layer:

* its leaf prototypes (leaves, not conifer shoots: :func:`flutters`) inheriting class 0,
  with the flutter op last in their ``xformOpOrder`` (so it turns the leaf in its own
  frame, about its petiole);
* for every other class, a sibling prototype that references the leaf prototype and
  inherits that class (``<name>_flutter<k>``);
* ``prototypes`` listing them all and ``protoIndices`` putting each leaf in one class
  (drawn from the recipe's seed), its shape unchanged;
* its ``extent``, grown by the largest leaf (a leaf turns about its petiole).

So the layer stores ``classes x time codes`` rotations, not one per leaf and time code, and
a leaf instancer's leaves are the same leaves, in the same places, when nothing turns them
(the default time, or the layer muted).
"""

from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from usdforest.grow.sway import WindSpec, flutter, flutter_amplitude, template_flutters
from usdforest.usd.layers import T, attr, class_labels, extents, full_detail, ints, prim

FLUTTER_OP = "xformOp:orient:flutter"


def class_path(k: int) -> Sdf.Path:
    """The root class prim of flutter class ``k``."""
    return Sdf.Path(f"/_class_Flutter_{k}")


def leaf_instancers(stage: Usd.Stage, trees: str = "/Forest/Trees") -> list[Usd.Prim]:
    """The leaf instancers (``semantics:labels:class`` leaf) of every prototype of the tree
    instancer at ``trees``, in the order of its prototypes."""
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath(trees))
    out = []
    for target in pi.GetPrototypesRel().GetTargets() if pi else ():
        it = iter(Usd.PrimRange(stage.GetPrimAtPath(target)))
        for p in it:
            if p.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()
                if "leaf" in class_labels(p):
                    out.append(p)
    return out


def flutters(leaf: Usd.Prim) -> bool:
    """Whether a leaf prototype flutters, by its template's name
    (:func:`usdforest.grow.sway.template_flutters`)."""
    name = leaf.GetCustomDataByKey("usdforest:name")
    return not isinstance(name, str) or template_flutters(name)


def _leaf_reach(pi: UsdGeom.PointInstancer) -> float:
    """The farthest any of the instancer's leaves reaches from its petiole (m, its space)."""
    bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"], True)
    size = 0.0
    stage = pi.GetPrim().GetStage()
    for t in pi.GetPrototypesRel().GetTargets():
        box = bbox.ComputeUntransformedBound(stage.GetPrimAtPath(t)).ComputeAlignedRange()
        if not box.IsEmpty():
            corner = np.abs(np.array([box.GetMin(), box.GetMax()]))
            size = max(size, float(np.linalg.norm(corner.max(axis=0))))
    rows = np.asarray(
        pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default()) or [],
        dtype=float,
    ).reshape(-1, 4, 4)
    scale = float(np.linalg.norm(rows[:, :3, :3], axis=2).max()) if len(rows) else 0.0
    return size * scale


def author_flutter(
    layer: Sdf.Layer, stage: Usd.Stage, spec: WindSpec, seed: int
) -> tuple[int, float]:
    """Author the flutter of the trees composed on ``stage`` into ``layer`` (the wind layer);
    returns how many leaves flutter (none in still air or with ``flutter_angle = 0``) and the
    farthest a leaf reaches from its petiole, in its tree prototype's space (m).

    Both levels of detail flutter: the leaf instancers the forest's own selection shows
    (what clients draw: a tree at ``medium`` has its leaves merged into clusters) and those of
    every tree at ``full`` detail (what the sensors read: :func:`usdforest.usd.layers.
    open_stage` ``full``), each once."""
    if flutter_amplitude(spec) <= 0:
        return 0, 0.0
    k_all = spec.flutter_classes
    done: set[Sdf.Path] = set()
    leaves, farthest = 0, 0.0

    def author(instancers: list[Usd.Prim]) -> None:
        nonlocal leaves, farthest
        with Sdf.ChangeBlock():
            for p in instancers:
                if p.GetPath() in done:
                    continue
                # numbered in the order met, the forest's own selection first
                n, reach = _author_instancer(layer, stage, p, len(done), k_all, seed)
                done.add(p.GetPath())
                leaves += n
                farthest = max(farthest, reach)

    author(leaf_instancers(stage))
    with full_detail(stage):
        author(leaf_instancers(stage))
    if leaves:
        quats = flutter(spec, seed).astype(np.float32)
        with Sdf.ChangeBlock():
            for k in range(k_all):
                cls = prim(layer, class_path(k).name, specifier=Sdf.SpecifierClass)
                op = attr(cls, FLUTTER_OP, T.Quatf, Gf.Quatf(1.0, 0.0, 0.0, 0.0))
                for f, q in enumerate(quats[:, k]):
                    x, y, z, w = (float(v) for v in q)
                    layer.SetTimeSample(op.path, float(f), Gf.Quatf(w, x, y, z))
    return leaves, farthest


def _author_instancer(
    layer: Sdf.Layer, stage: Usd.Stage, p: Usd.Prim, n: int, k_all: int, seed: int
) -> tuple[int, float]:
    """The flutter overs of the leaf instancer ``p`` (the ``n``-th met): its leaves that
    flutter and how far its leaves reach from their petioles (0, 0.0: none flutters)."""
    pi = UsdGeom.PointInstancer(p)
    targets = list(pi.GetPrototypesRel().GetTargets())
    idx = np.asarray(pi.GetProtoIndicesAttr().Get() or [], dtype=np.int64)
    if not targets or not len(idx) or p.IsInstanceProxy():
        return 0, 0.0
    turns = np.array([flutters(stage.GetPrimAtPath(t)) for t in targets])
    if not turns[idx].any():
        return 0, 0.0
    over = Sdf.CreatePrimInLayer(layer, p.GetPath())
    listed = list(targets)
    first_sibling = np.zeros(len(targets), np.int64)
    for j, t in enumerate(targets):
        if not turns[j]:
            continue
        leaf = stage.GetPrimAtPath(t)
        order = [op.GetOpName() for op in UsdGeom.Xformable(leaf).GetOrderedXformOps()]
        order = Vt.TokenArray([*order, FLUTTER_OP])
        own = Sdf.CreatePrimInLayer(layer, t)
        own.inheritPathList.Prepend(class_path(0))
        attr(own, "xformOpOrder", T.TokenArray, order, uniform=True)
        first_sibling[j] = len(listed)
        for k in range(1, k_all):
            sib = Sdf.CreatePrimInLayer(
                layer, t.GetParentPath().AppendChild(f"{t.name}_flutter{k}")
            )
            sib.specifier = Sdf.SpecifierDef
            sib.typeName = leaf.GetTypeName()
            sib.referenceList.Prepend(Sdf.Reference(primPath=t))
            sib.inheritPathList.Prepend(class_path(k))
            attr(sib, "xformOpOrder", T.TokenArray, order, uniform=True)
            listed.append(sib.path)
    which = np.random.default_rng([seed, 0xF1A8, n]).integers(0, k_all, len(idx))
    moving = turns[idx] & (which > 0)
    new = np.where(moving, first_sibling[idx] + which - 1, idx)
    rel = Sdf.RelationshipSpec(over, "prototypes")
    rel.targetPathList.explicitItems = listed
    attr(over, "protoIndices", T.IntArray, ints(new))
    reach = _leaf_reach(pi)
    box = pi.GetExtentAttr().Get()
    if box is not None and len(box) == 2:
        grown = np.asarray(box, dtype=float) + np.array([[-reach] * 3, [reach] * 3])
        attr(over, "extent", T.Float3Array, extents(grown))
    return int(turns[idx].sum()), reach
