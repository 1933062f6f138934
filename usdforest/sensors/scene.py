"""World-space geometry of any stage for sensors: triangles with semantic class, tree id and
prim path, and leaves as disk reflectors.

Every PointInstancer level is expanded with ``ComputeInstanceTransformsAtTime``. Instances of
a tree prototype (a prim labelled ``tree``) carry the instancer's ``ids`` as tree ids. Culling
comes before expansion: only tree instances whose bounds come within ``radius`` of ``centre``
are kept, so a scan near one corner of a 1 km² forest does not expand the whole forest.

Instances stay instances, on two levels: each tree prototype's wood triangles are gathered
once in the prototype's own space and every tree is a transform to it (:class:`Instances`);
each leaf (or shoot) is a transform of one of a few leaf shapes (:class:`LeafInstances`,
:class:`Shape`). Ray casting follows both levels
(:class:`~usdforest.sensors.raycast.SceneCaster`) instead of copying a million triangles per
tree and fifty per shoot. ``instancing=False`` copies every triangle instead.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from usdforest.sensors.implicit import IMPLICIT, shape_triangles
from usdforest.usd.layers import class_labels, mesh_triangles, open_stage, rendered

CLASSES = ("unknown", "trunk", "branch", "leaf", "ground")
CLASS_ID = {name: i for i, name in enumerate(CLASSES)}


def class_counts(cls: np.ndarray) -> dict[str, int]:
    """How many of ``cls`` (class indices) fall in each class, by name."""
    counts = np.bincount(np.asarray(cls, dtype=np.int64), minlength=len(CLASSES))
    return {c: int(n) for c, n in zip(CLASSES, counts, strict=True)}


@dataclass(frozen=True, eq=False)
class Leaves:
    """Leaves as reflectors: centre, unit normal, one-sided area (m²), tree id."""

    centre: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    tree: np.ndarray

    def __len__(self) -> int:
        return int(self.centre.shape[0])

    @property
    def radius(self) -> np.ndarray:
        """Equivalent disk radius sqrt(area / pi)."""
        return np.sqrt(self.area / np.pi)

    @staticmethod
    def concat(parts: list[Leaves]) -> Leaves:
        if not parts:
            return Leaves(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))
        return Leaves(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("centre", "normal", "area", "tree")
            )
        )


@dataclass(frozen=True, eq=False)
class Shape:
    """A leaf (or shoot) prototype's triangles in its own space, with class and path."""

    triangles: np.ndarray
    cls: np.ndarray
    path: np.ndarray

    @functools.cached_property
    def box(self) -> np.ndarray:
        """``(2, 3)`` lower and upper corner of the shape (zeros when empty)."""
        pts = np.asarray(self.triangles, dtype=float).reshape(-1, 3)
        return np.array([pts.min(axis=0), pts.max(axis=0)]) if len(pts) else np.zeros((2, 3))


@dataclass(frozen=True, eq=False)
class LeafInstances:
    """Leaves kept as instances: shape index, row-vector 4x4 shape-to-owner transform and
    tree id (-1 inside a tree prototype: the tree instance gives it)."""

    shape: np.ndarray
    matrix: np.ndarray
    tree: np.ndarray

    def __len__(self) -> int:
        return int(self.shape.shape[0])

    @staticmethod
    def concat(parts: list[LeafInstances]) -> LeafInstances:
        if not parts:
            return LeafInstances(np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros(0, np.int64))
        return LeafInstances(
            *(np.concatenate([getattr(p, f) for p in parts]) for f in ("shape", "matrix", "tree"))
        )

    def triangles(self, shapes: tuple[Shape, ...]) -> int:
        """How many triangles these leaves stand for."""
        per = np.array([len(s.triangles) for s in shapes], dtype=np.int64)
        return int(per[self.shape].sum()) if len(self) else 0


def _no_leaves() -> LeafInstances:
    return LeafInstances.concat([])


@dataclass(frozen=True, eq=False)
class Prototype:
    """A tree prototype in its own space: wood triangles with class and path, leaf
    instances, leaves as reflectors, bounds (of wood and leaves)."""

    triangles: np.ndarray
    cls: np.ndarray
    path: np.ndarray
    leaves: Leaves
    box: np.ndarray  # (2, 3) lower and upper corner of its wood and leaves
    leaf_instances: LeafInstances = field(default_factory=_no_leaves)

    @property
    def centre(self) -> np.ndarray:
        """Centre of the bounding sphere (the box's)."""
        return self.box.mean(axis=0)

    @property
    def radius(self) -> float:
        """Radius of the bounding sphere (half the box's diagonal)."""
        return float(np.linalg.norm(self.box[1] - self.box[0]) / 2)


@dataclass(frozen=True, eq=False)
class Instances:
    """Placed prototypes: index, row-vector 4x4 prototype-to-world transform, tree id."""

    proto: np.ndarray
    matrix: np.ndarray
    tree: np.ndarray

    def __len__(self) -> int:
        return int(self.proto.shape[0])


@dataclass(frozen=True, eq=False)
class Scene:
    """World-space triangles (m, 3, 3) with class, tree id and path index, plus instances of
    tree prototypes, and every leaf in reach as a reflector."""

    triangles: np.ndarray
    cls: np.ndarray
    tree: np.ndarray
    path: np.ndarray
    paths: tuple[str, ...]
    leaves: Leaves
    bounds: np.ndarray  # (2, 3) of the whole stage (not only what was expanded)
    protos: tuple[Prototype, ...] = ()
    instances: Instances = field(
        default_factory=lambda: Instances(
            np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros(0, np.int64)
        )
    )
    unseen: tuple[str, ...] = ()  # geometry prims the scene cannot hold (curves, points...)
    shapes: tuple[Shape, ...] = ()  # leaf shapes of every LeafInstances
    leaf_instances: LeafInstances = field(default_factory=_no_leaves)  # in world space

    def instance_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space bounding spheres (centres ``(n, 3)``, radii ``(n,)``) of the tree
        instances: each prototype's sphere placed by its instance's transform."""
        inst = self.instances
        if not len(inst):
            return np.zeros((0, 3)), np.zeros(0)
        rot = inst.matrix[:, :3, :3]
        centres = np.array([p.centre for p in self.protos]).reshape(-1, 3)
        radii = np.array([p.radius for p in self.protos])
        centre = np.einsum("nj,njk->nk", centres[inst.proto], rot) + inst.matrix[:, 3, :3]
        return centre, radii[inst.proto] * np.linalg.norm(rot, axis=2).max(axis=1)

    def __len__(self) -> int:
        """Triangles in the scene, every instance (of trees and of leaves) counted."""
        per = np.array(
            [len(p.triangles) + p.leaf_instances.triangles(self.shapes) for p in self.protos],
            dtype=np.int64,
        )
        return int(
            self.triangles.shape[0]
            + self.leaf_instances.triangles(self.shapes)
            + (per[self.instances.proto].sum() if len(per) else 0)
        )


@dataclass(frozen=True, eq=False)
class _LeafBatch:
    """Instances of one leaf prototype, still as transforms (row-vector 4x4, leaf -> here)."""

    tri: np.ndarray  # (t, 3, 3) in the leaf prototype's space
    cls: np.ndarray
    path: np.ndarray
    xf: np.ndarray  # (n, 4, 4)
    unit_area: float
    centre: np.ndarray  # (3,) leaf centre in its own space
    size: float  # leaf extent in its own space
    shape: int  # index among the scene's leaf shapes
    tree: int = -1


@dataclass(frozen=True, eq=False)
class _Part:
    tri: np.ndarray
    cls: np.ndarray
    tree: np.ndarray
    path: np.ndarray
    batches: tuple[_LeafBatch, ...] = field(default=())

    def transformed(self, m: np.ndarray, tree: int | None = None) -> _Part:
        rot, t = m[:3, :3].astype(np.float32), m[3, :3].astype(np.float32)
        tri = (self.tri.reshape(-1, 3) @ rot + t).reshape(-1, 3, 3)
        trees = self.tree if tree is None else np.full_like(self.tree, tree)
        batches = tuple(
            replace(b, xf=b.xf @ m, tree=b.tree if tree is None else tree) for b in self.batches
        )
        return _Part(tri, self.cls, trees, self.path, batches)

    @staticmethod
    def concat(parts: list[_Part]) -> _Part:
        parts = [p for p in parts if len(p.tri) or p.batches]
        if not parts:
            return _Part(
                np.zeros((0, 3, 3), np.float32),
                np.zeros(0, np.uint8),
                np.zeros(0, np.int32),
                np.zeros(0, np.int32),
            )
        return _Part(
            np.concatenate([p.tri for p in parts]),
            np.concatenate([p.cls for p in parts]),
            np.concatenate([p.tree for p in parts]),
            np.concatenate([p.path for p in parts]),
            tuple(b for p in parts for b in p.batches),
        )


def _m(x) -> np.ndarray:
    return np.array(x, dtype=float).reshape(4, 4)


def _class_of(prim, stop) -> int:
    p = prim
    while p and p != stop.GetParent():
        for label in class_labels(p):
            if label in CLASS_ID:
                return CLASS_ID[label]
        p = p.GetParent()
    return 0


def _triangles(mesh_prim, to_root: np.ndarray) -> np.ndarray:
    return mesh_triangles(mesh_prim, to_root).astype(np.float32)


def _leaf_area_unit(proto, tri: np.ndarray) -> float:
    """One-sided area of a leaf prototype in its own space."""
    data = proto.GetCustomDataByKey("usdforest")
    if data and "measurements" in data and data["measurements"].get("length"):
        m = data["measurements"]
        if m.get("leaf_area"):
            return float(m["leaf_area"]) / float(m["length"]) ** 2
    t = tri.astype(float)
    return float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())


def _realise(
    b: _LeafBatch,
    centre: np.ndarray | None,
    radius: float | None,
    triangles: str | None = "copy",
    reflectors: bool = True,
) -> tuple[Leaves, _Part, LeafInstances]:
    """Leaf reflectors of a batch, keeping leaves within reach of the sensor, and their
    geometry: triangles (``"copy"``), instances of the batch's shape (``"instance"``) or
    none (``None``). Without ``reflectors`` the reflectors are left out."""
    rot = b.xf[:, :3, :3]
    c = np.einsum("j,njk->nk", b.centre, rot) + b.xf[:, 3, :3]
    scale = np.cbrt(np.abs(np.linalg.det(rot)))
    keep = np.ones(len(c), dtype=bool)
    if centre is not None and radius is not None:
        keep = np.linalg.norm(c - centre, axis=1) <= radius + b.size * scale
    rot, c, scale, xf = rot[keep], c[keep], scale[keep], b.xf[keep]
    n, t = len(xf), len(b.tri)
    if reflectors:
        normal = np.einsum(
            "j,njk->nk", np.array([0.0, 0.0, 1.0]), np.linalg.inv(rot).transpose(0, 2, 1)
        )
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        leaves = Leaves(c, normal, b.unit_area * scale**2, np.full(n, b.tree, np.int64))
    else:
        leaves = Leaves.concat([])
    if triangles != "copy":
        kept = (
            LeafInstances(np.full(n, b.shape, np.int64), xf, np.full(n, b.tree, np.int64))
            if triangles == "instance"
            else _no_leaves()
        )
        return leaves, _Part.concat([]), kept
    tri = (
        np.einsum("tvj,njk->ntvk", b.tri, rot.astype(np.float32))
        + xf[:, None, None, 3, :3].astype(np.float32)
    ).reshape(-1, 3, 3)
    part = _Part(
        tri.astype(np.float32),
        np.tile(b.cls, n),
        np.full(n * t, b.tree, np.int32),
        np.tile(b.path, n),
    )
    return leaves, part, _no_leaves()


def moved_boxes(
    lo: np.ndarray, hi: np.ndarray, matrix: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes of boxes ``lo``/``hi`` (n, 3) moved by row-vector 4x4 transforms
    ``matrix`` (n, 4, 4): the centre moved, the half extents through the absolute linear
    part (the exact box of each moved box)."""
    rot = matrix[:, :3, :3]
    c = np.einsum("nj,njk->nk", (lo + hi) / 2, rot) + matrix[:, 3, :3]
    h = np.einsum("nj,njk->nk", (hi - lo) / 2, np.abs(rot))
    return c - h, c + h


def leaf_boxes(li: LeafInstances, shapes: tuple[Shape, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes ``(lowers, uppers)``, each ``(n, 3)``, of leaf instances in their
    owner's space: each shape's box moved by its instance's transform."""
    if not len(li):
        return np.zeros((0, 3)), np.zeros((0, 3))
    box = np.array([s.box for s in shapes], dtype=float)[li.shape]  # (n, 2, 3)
    return moved_boxes(box[:, 0], box[:, 1], li.matrix)


def _placed_leaves(
    proto: Prototype, m: np.ndarray, tree: int, centre: np.ndarray | None, radius: float | None
) -> Leaves:
    """A prototype's leaves placed by ``m`` (row-vector 4x4), those within reach only."""
    lv = proto.leaves
    rot = m[:3, :3]
    c = lv.centre @ rot + m[3, :3]
    keep = np.ones(len(c), dtype=bool)
    if centre is not None and radius is not None:
        keep = np.linalg.norm(c - centre, axis=1) <= radius + 2 * np.sqrt(lv.area) + 1e-6
    n = lv.normal[keep] @ np.linalg.inv(rot).T
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    s2 = abs(np.linalg.det(rot)) ** (2 / 3)
    return Leaves(c[keep], n, lv.area[keep] * s2, np.full(int(keep.sum()), tree, np.int64))


def stage_frame(stage_path: str | Path) -> np.ndarray:
    """The row-vector 4x4 from a stage's own units and axes to the sensors' frame (metres, Z
    up): ``metersPerUnit`` and ``upAxis`` as its root layer authors them (a Y-up stage is
    turned +90 degrees about X, so its +Y becomes +Z and its +Z becomes -Y); unauthored
    metadata is taken as usdforest writes it, metres and Z up, not USD's fallbacks."""
    from pxr import Sdf

    m = np.eye(4)
    try:
        layer = Sdf.Layer.FindOrOpen(str(stage_path))
    except Exception:  # not USD: opening the stage names the problem
        return m
    if layer is None:
        return m
    root = layer.pseudoRoot
    if root.HasInfo("metersPerUnit"):
        m[:3, :3] *= float(root.GetInfo("metersPerUnit"))
    if root.HasInfo("upAxis") and str(root.GetInfo("upAxis")).upper() == "Y":
        m = m @ np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
    return m


def to_frame(points: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """``points (..., 3)`` in a stage's own units and axes, in the sensors' frame."""
    return np.asarray(points, dtype=float) @ frame[:3, :3] + frame[3, :3]


def extract_scene(
    stage_path: str | Path,
    *,
    centre: np.ndarray | None = None,
    radius: float | None = None,
    instancing: bool = True,
    leaf_triangles: bool = True,
    reflectors: bool = True,
) -> Scene:
    """Triangles and leaf reflectors of a stage, culled to a sphere around ``centre``, in
    metres with Z up whatever the stage's own units and up axis (:func:`stage_frame`).

    Parameters
    ----------
    stage_path
        Any USD stage: a tree, a forest, a simulation stage that references them.
    centre, radius
        Keep only tree instances and leaves within ``radius`` of ``centre`` (all when
        omitted), both in metres in the sensors' frame.
    instancing
        Keep tree instances as transforms of their prototypes (default) or copy triangles.
    leaf_triangles
        Give rays leaves to meet (default): as instances of their shapes, or copied into
        triangles without ``instancing``. A sonar that casts no ray needs the leaves as
        reflectors only: ``False`` skips their geometry.
    reflectors
        Gather every leaf in reach as a reflector (default; the sonar's input). A lidar or
        camera needs none: ``False`` saves a tuple of arrays per leaf.
    """
    from pxr import Usd, UsdGeom

    path = Path(stage_path)
    stage = open_stage(path, sound=True)
    frame = stage_frame(path)
    cache = UsdGeom.XformCache()
    bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"], True)
    paths: list[str] = []
    path_index: dict[str, int] = {}
    memo: dict = {}
    protos: list[Prototype] = []
    proto_of: dict = {}
    unseen: list[str] = []
    placed: list[tuple[int, np.ndarray, int]] = []
    shapes: list[Shape] = []
    shape_of: dict = {}
    geometry = ("instance" if instancing else "copy") if leaf_triangles else None

    def prototype(prim) -> int:
        """Index of the (tree) prototype ``prim``, gathered once, its leaves as instances."""
        key = prim.GetPath()
        if key not in proto_of:
            part = subtree(prim)
            realised = [_realise(b, None, None, geometry, reflectors) for b in part.batches]
            whole = replace(part, batches=())
            kept = LeafInstances.concat([r[2] for r in realised])
            lo, hi = leaf_boxes(kept, tuple(shapes))
            pts = np.concatenate([whole.tri.reshape(-1, 3).astype(float), lo, hi])
            lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(3),) * 2
            proto_of[key] = len(protos)
            protos.append(
                Prototype(
                    whole.tri,
                    whole.cls,
                    whole.path,
                    Leaves.concat([r[0] for r in realised]),
                    np.array([lo, hi]),
                    kept,
                )
            )
        return proto_of[key]

    def shape(prim, local: _Part) -> int:
        """Index of the leaf shape ``prim`` (its triangles gathered once)."""
        key = prim.GetPath()
        if key not in shape_of:
            shape_of[key] = len(shapes)
            shapes.append(Shape(local.tri, local.cls, local.path))
        return shape_of[key]

    def pid(p: str) -> int:
        if p not in path_index:
            path_index[p] = len(paths)
            paths.append(p)
        return path_index[p]

    def subtree(prim, top: bool = False) -> _Part:
        """Everything under ``prim`` in ``prim``'s own space (memoised: prototypes)."""
        key = prim.GetPath()
        if key in memo:
            return memo[key]
        inv = np.linalg.inv(_m(cache.GetLocalToWorldTransform(prim)))
        if top:  # the world: in metres, Z up
            inv = inv @ frame
        parts = []
        it = iter(Usd.PrimRange(prim, Usd.TraverseInstanceProxies()))
        for p in it:
            if not rendered(p) or (
                p.IsA(UsdGeom.Imageable) and UsdGeom.Imageable(p).ComputeVisibility() == "invisible"
            ):
                it.PruneChildren()
                continue
            if p.IsA(UsdGeom.Mesh) or p.GetTypeName() in IMPLICIT:
                to_root = _m(cache.GetLocalToWorldTransform(p)) @ inv
                if p.IsA(UsdGeom.Mesh):
                    tri = _triangles(p, to_root)
                else:  # Cube, Sphere, ...: tessellated (see sensors.implicit)
                    local = shape_triangles(p)
                    if local is None:
                        continue
                    tri = (local @ to_root[:3, :3] + to_root[3, :3]).astype(np.float32)
                n = len(tri)
                parts.append(
                    _Part(
                        tri,
                        np.full(n, _class_of(p, prim), np.uint8),
                        np.full(n, -1, np.int32),
                        np.full(n, pid(str(p.GetPath())), np.int32),
                    )
                )
            elif p.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()
                parts.append(instances(p, _m(cache.GetLocalToWorldTransform(p)) @ inv, top))
            elif p.IsA(UsdGeom.Gprim):
                unseen.append(str(p.GetPath()))
        out = _Part.concat(parts)
        memo[key] = out
        return out

    def instances(p, to_root: np.ndarray, top: bool = False) -> _Part:
        """A PointInstancer's instances, in the space of the subtree being gathered."""
        pi = UsdGeom.PointInstancer(p)
        xf = pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
        idx = pi.GetProtoIndicesAttr().Get()
        if xf is None or idx is None or len(idx) == 0:
            return _Part.concat([])
        xf = np.asarray(xf, dtype=float).reshape(-1, 4, 4)
        idx = np.asarray(idx)
        ids_attr = pi.GetIdsAttr().Get()
        ids = (
            np.asarray(ids_attr, dtype=np.int64)
            if ids_attr is not None and len(ids_attr)
            else np.arange(len(idx), dtype=np.int64)
        )
        to_world = _m(cache.GetLocalToWorldTransform(p)) @ frame
        out = []
        for k, target in enumerate(pi.GetPrototypesRel().GetTargets()):
            sel = np.flatnonzero(idx == k)
            proto = stage.GetPrimAtPath(target)
            if sel.size == 0 or not proto:
                continue
            own = _m(cache.GetLocalTransformation(proto)[0])
            if "leaf" in class_labels(p):
                local = subtree(proto)
                pts = local.tri.reshape(-1, 3).astype(float)
                lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(3),) * 2
                out.append(
                    _Part(
                        np.zeros((0, 3, 3), np.float32),
                        np.zeros(0, np.uint8),
                        np.zeros(0, np.int32),
                        np.zeros(0, np.int32),
                        (
                            _LeafBatch(
                                local.tri,
                                local.cls,
                                local.path,
                                np.einsum("ij,njk->nik", own, xf[sel]) @ to_root,
                                _leaf_area_unit(proto, local.tri),
                                (lo + hi) / 2,
                                float(np.linalg.norm(hi - lo)),
                                shape(proto, local),
                            ),
                        ),
                    )
                )
                continue
            is_tree = "tree" in class_labels(proto)
            if is_tree and centre is not None and radius is not None:
                ext = bbox.ComputeUntransformedBound(proto).ComputeAlignedRange()
                r_proto = float(np.linalg.norm(np.array(ext.GetMax()) - np.array(ext.GetMin())))
                world_pos = xf[sel, 3, :3] @ to_world[:3, :3] + to_world[3, :3]
                scale = np.cbrt(np.abs(np.linalg.det(xf[sel, :3, :3] @ to_world[:3, :3])))
                sel = sel[np.linalg.norm(world_pos - centre, axis=1) <= radius + r_proto * scale]
                if sel.size == 0:
                    continue
            if is_tree and top and instancing:
                k_proto = prototype(proto)
                for i in sel:
                    placed.append((k_proto, own @ xf[i] @ to_root, int(ids[i])))
                continue
            local = subtree(proto)
            for i in sel:
                out.append(
                    local.transformed(own @ xf[i] @ to_root, int(ids[i]) if is_tree else None)
                )
        return _Part.concat(out)

    root = stage.GetPseudoRoot()
    world_box = bbox.ComputeWorldBound(root).ComputeAlignedRange()
    if world_box.IsEmpty():
        bounds = np.zeros((2, 3))
    else:
        lo, hi = moved_boxes(
            np.array([world_box.GetMin()]), np.array([world_box.GetMax()]), frame[None]
        )
        bounds = np.concatenate([lo, hi])
    part = subtree(root, top=True)
    realised = [_realise(b, centre, radius, geometry, reflectors) for b in part.batches]
    whole = _Part.concat([part, *(r[1] for r in realised)])
    world_leaves = LeafInstances.concat([r[2] for r in realised])
    inst = Instances(
        np.array([k for k, _, _ in placed], dtype=np.int64),
        np.array([m for _, m, _ in placed]).reshape(-1, 4, 4),
        np.array([t for _, _, t in placed], dtype=np.int64),
    )
    leaves = Leaves.concat(
        [r[0] for r in realised]
        + [_placed_leaves(protos[k], m, t, centre, radius) for k, m, t in placed if reflectors]
    )
    tree, leaf_tree = whole.tree, leaves.tree
    # a stage holding one tree that is not instanced: tree id 0
    if (
        not placed
        and not (tree >= 0).any()
        and any("tree" in class_labels(p) for p in stage.Traverse())
    ):
        tree = np.zeros_like(tree)
        leaf_tree = np.zeros_like(leaf_tree)
        world_leaves = replace(world_leaves, tree=np.zeros_like(world_leaves.tree))
    return Scene(
        whole.tri,
        whole.cls,
        tree,
        whole.path,
        tuple(paths),
        Leaves(leaves.centre, leaves.normal, leaves.area, leaf_tree),
        bounds,
        tuple(protos),
        inst,
        tuple(dict.fromkeys(unseen)),
        tuple(shapes)
        if world_leaves.shape.size or any(len(p.leaf_instances) for p in protos)
        else (),
        world_leaves,
    )
