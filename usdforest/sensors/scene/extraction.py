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
(:class:`~usdforest.sensors.cast.raycast.SceneCaster`) instead of copying a million triangles per
tree and fifty per shoot. ``instancing=False`` copies every triangle instead.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from usdforest.sensors.scene.implicit import IMPLICIT, shape_triangles
from usdforest.sensors.scene.native import NativeMeshes
from usdforest.sensors.scene.reflectors import blade_reflectors
from usdforest.sensors.scene.reflectors import placed_leaves as leaves_placed
from usdforest.sensors.scene.scenecache import (
    PrototypeStore,
    adopted,
    kept,
    stored,
    valid_stored,
    valid_turns,
)
from usdforest.sensors.scene.scenetypes import (
    Instances,
    LeafInstances,
    Leaves,
    Prototype,
    Scene,
    Shape,
    Sources,
    no_leaves,
)
from usdforest.sensors.scene.stageframe import (
    animated,
    leaf_boxes,
    moved_boxes,
    stage_frame,
    stage_time,
)
from usdforest.sensors.scene.turns import moving_parts, shape_turns
from usdforest.usd.layers import class_labels, mesh_triangles, open_stage, rendered

if TYPE_CHECKING:
    from pxr import Usd

CLASSES = ("unknown", "trunk", "branch", "leaf", "ground", "dead_wood", "ground_vegetation")
CLASS_ID = {name: i for i, name in enumerate(CLASSES)}
# prototypes kept as instances (two levels) rather than copied: trees, shrubs and young trees
# (tree assets), and ground-vegetation patches (thousands of copies of four meshes of
# thousands of triangles each); only trees carry their instancer's ids as tree ids
INSTANCED = ("tree", "shrub", "regeneration", "ground_vegetation")
# ground vegetation that echoes as the rough ground under it does, not as leaves
CARPETS = ("moss",)


def class_counts(cls: np.ndarray) -> dict[str, int]:
    """How many of ``cls`` (class indices) fall in each class, by name."""
    counts = np.bincount(np.asarray(cls, dtype=np.int64), minlength=len(CLASSES))
    return {c: int(n) for c, n in zip(CLASSES, counts, strict=True)}


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
    own: np.ndarray | None = None  # the shape prim's own transform, where it moves in time


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


def _form(prim) -> str:
    """A ground-vegetation prototype's growth form (its ``usdforest:form``), else ``""``."""
    return str((prim.GetCustomDataByKey("usdforest") or {}).get("form", ""))


def _instanced(stage, target) -> bool:
    """Whether the prototype at ``target`` stays instanced (see :data:`INSTANCED`)."""
    labels = class_labels(stage.GetPrimAtPath(target))
    return any(label in labels for label in INSTANCED)


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
        if b.own is not None:  # a turning leaf: where it is without its turn, and its shape
            frame = np.linalg.inv(b.own) @ xf
            leaves = replace(leaves, shape=np.full(n, b.shape, np.int64), frame=frame)
    else:
        leaves = Leaves.concat([])
    if triangles != "copy":
        kept = (
            LeafInstances(np.full(n, b.shape, np.int64), xf, np.full(n, b.tree, np.int64))
            if triangles == "instance"
            else no_leaves()
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
    return leaves, part, no_leaves()


def extract_scene(
    stage_path: str | Path,
    *,
    centre: np.ndarray | None = None,
    radius: float | None = None,
    instancing: bool = True,
    leaf_triangles: bool = True,
    reflectors: bool = True,
    cache: bool = True,
    progress: Callable[[str, int, int], None] | None = None,
    time: float | None = None,
    opened: Usd.Stage | None = None,
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
    cache
        Reuse tree prototypes gathered by an earlier call on the same stage content, and keep
        the ones gathered now (:mod:`usdforest.sensors.scene.scenecache`; default).
    progress
        ``progress(stage, done, total)`` as tree prototypes are gathered and each tree's
        leaves placed as reflectors.
    time
        Seconds into the stage's animation (its time codes over ``timeCodesPerSecond``):
        instances and prims stand where the stage's time samples put them then, e.g. a
        forest's trees swaying and its leaves fluttering in its wind layer. Omitted: the
        stage's default values, the still forest.
    opened
        The stage at ``stage_path`` as :func:`open_stage` (``sound``, ``full``) opened it,
        to read instead of opening it again (seconds for a forest): a flight shares one.
    """
    from pxr import Usd, UsdGeom

    path = Path(stage_path)
    use_store = cache and instancing  # read before ``cache`` names the transform cache
    stage = opened if opened is not None else open_stage(path, sound=True, full=True)
    frame = stage_frame(path)
    when = stage_time(stage, time)
    cache = UsdGeom.XformCache(when)
    bbox = UsdGeom.BBoxCache(when, ["default", "render"], True)
    paths: list[str] = []
    path_index: dict[str, int] = {}
    memo: dict = {}
    protos: list[Prototype] = []
    proto_of: dict = {}
    unseen: list[str] = []
    placed: list[tuple[int, np.ndarray, int]] = []
    # per placed instance: its instancer's path, its row there, the transforms around the row
    # and the moving part it places (-1: the whole prototype)
    sources: list[tuple[str, int, np.ndarray, np.ndarray, int]] = []
    shapes: list[Shape] = []
    shape_of: dict = {}
    shape_keys: list[str] = []
    geometry = ("instance" if instancing else "copy") if leaf_triangles else None
    # an animated stage's prototypes move in time too (its leaves flutter): kept per time
    moves = animated(stage)
    at_time = moves and not when.IsDefault()
    store_mode = f"{geometry} at {when.GetValue():.17g}" if at_time else str(geometry)
    store_of: list = []  # the stage's prototype store, keyed when the first prototype is met
    # an animated stage's tree prototypes may have parts that move on their own (limbs that
    # sway): each part is an instance of its own, its tree's prototype gathered without it
    parted = moves
    parts_of: dict = {}
    part_rows: list[tuple[str, str]] = []  # (part prim, its prototype's prim)
    pruned: set = set()  # the parts' prims, which their prototypes' subtrees leave out

    def store_get() -> PrototypeStore | None:
        if not store_of:
            store_of.append(PrototypeStore.of(stage) if use_store else None)
        return store_of[0]

    gathered = [0, 0]  # prototypes gathered, prototypes met
    tick = progress or (lambda stage, done, total: None)

    def gather(prim, with_reflectors: bool) -> Prototype:
        """A (tree) prototype's wood and leaves, in its own space."""
        part = subtree(prim)
        realised = [_realise(b, None, None, geometry, with_reflectors) for b in part.batches]
        whole = replace(part, batches=())
        kept = LeafInstances.concat([r[2] for r in realised])
        lo, hi = leaf_boxes(kept, tuple(shapes))
        pts = np.concatenate([whole.tri.reshape(-1, 3).astype(float), lo, hi])
        lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(3),) * 2
        reflecting = [r[0] for r in realised]
        if with_reflectors and _form(prim) not in CARPETS:
            blades = whole.tri[whole.cls == CLASS_ID["ground_vegetation"]]
            reflecting.append(blade_reflectors(blades))
        return Prototype(
            whole.tri,
            whole.cls,
            whole.path,
            Leaves.concat(reflecting),
            np.array([lo, hi]),
            kept,
        )

    def prototype(prim, counted: bool = True) -> int:
        """Index of the (tree) prototype ``prim`` (or a part of one: not ``counted``),
        gathered once (or read from the store), its leaves as instances."""
        key = prim.GetPath()
        if key not in proto_of:
            store = store_get()
            moving = len(parts_of.get(key, ()))
            mode = f"{store_mode} without {moving} parts" if moving else store_mode
            entry = store.get(str(key), mode, valid_stored) if store is not None else None
            if entry is None:
                seen = (len(unseen), len(paths), len(shapes))
                proto = gather(prim, reflectors or store is not None)
                if store is not None:
                    local = stored(proto, paths, shapes, shape_keys, seen, unseen[seen[0] :])
                    store.put(str(key), mode, local)
            else:
                proto = adopted(entry, pid, add_shape)
                unseen.extend(entry["unseen"])
            if not reflectors:
                proto = replace(proto, leaves=Leaves.concat([]))
            proto_of[key] = len(protos)
            protos.append(proto)
            if counted:
                gathered[0] += 1
                tick("tree prototypes", gathered[0], gathered[1])
        return proto_of[key]

    def parts(proto) -> list[tuple[int, int, np.ndarray]]:
        """The parts of the tree prototype ``proto`` whose transforms have time samples (its
        limbs that sway), each one's prototype, its row in ``part_rows`` and its transform
        into ``proto``'s space now (row vectors); leaf instancers' own turns are not
        parts (:class:`_LeafBatch` ``own``)."""
        key = proto.GetPath()
        if key in parts_of:
            return parts_of[key]
        found = []
        if parted:  # the walk takes 0.8 s in the windy default forest: kept with its prototypes
            names = kept(
                store_get(),
                f"parts of {key}",
                "moving",
                lambda: moving_parts(proto),
                lambda v: isinstance(v, list) and all(isinstance(n, str) for n in v),
            )
            found = [stage.GetPrimAtPath(n) for n in names]
        parts_of[key] = found  # read by ``prototype(proto)``'s store key
        pruned.update(q.GetPath() for q in found)
        inv = np.linalg.inv(_m(cache.GetLocalToWorldTransform(proto)))
        out = []
        for q in found:
            part_rows.append((str(q.GetPath()), str(key)))
            rel = _m(cache.GetLocalToWorldTransform(q)) @ inv
            out.append((prototype(q, counted=False), len(part_rows) - 1, rel))
        parts_of[key] = out
        return out

    def add_shape(key: str, s: Shape) -> int:
        if key not in shape_of:
            shape_of[key] = len(shapes)
            shapes.append(s)
            shape_keys.append(key)
        return shape_of[key]

    def shape(prim, local: _Part) -> int:
        """Index of the leaf shape ``prim`` (its triangles gathered once)."""
        return add_shape(str(prim.GetPath()), Shape(local.tri, local.cls, local.path))

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
        parts: list = []
        rows: dict = {}  # native instances met: (prototype, mesh) -> their slots in ``parts``
        it = iter(Usd.PrimRange(prim, Usd.TraverseInstanceProxies()))
        for p in it:
            if (
                not rendered(p)
                or (p != prim and p.GetPath() in pruned)  # a part that moves on its own
                or (
                    p.IsA(UsdGeom.Imageable)
                    and UsdGeom.Imageable(p).ComputeVisibility() == "invisible"
                )
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
            if p.IsInstance() and not p.IsA(UsdGeom.PointInstancer):
                inner = natives.of(p.GetPrototype())
                if inner is None or moving_proxies():
                    continue  # walked proxy by proxy
                it.PruneChildren()
                to_root = _m(cache.GetLocalToWorldTransform(p)) @ inv
                outer = _class_of(p, prim) if any(c is None for *_, c in inner) else 0
                for j, (below, _, cls) in enumerate(inner):
                    row = (len(parts), to_root, pid(f"{p.GetPath()}/{below}"))
                    rows.setdefault((p.GetPrototype().GetPath(), j), []).append(
                        (*row, outer if cls is None else cls)
                    )
                    parts.append(None)
        for slot, path_id, cls, t in natives.place(rows):
            n = len(t)
            cls_tree_path = ((cls, np.uint8), (-1, np.int32), (path_id, np.int32))
            parts[slot] = _Part(t, *(np.full(n, v, d) for v, d in cls_tree_path))
        out = _Part.concat(parts)
        memo[key] = out
        return out

    natives = NativeMeshes(cache, CLASS_ID)
    proxied = [0, False]  # how many of ``pruned`` were looked at, whether one is a proxy

    def moving_proxies() -> bool:  # a part that moves on its own inside a native instance
        if proxied[0] != len(pruned):
            proxied[:] = [
                len(pruned),
                any(stage.GetPrimAtPath(q).IsInstanceProxy() for q in pruned),
            ]
        return proxied[1]

    def instances(p, to_root: np.ndarray, top: bool = False) -> _Part:
        """A PointInstancer's instances, in the space of the subtree being gathered."""
        pi = UsdGeom.PointInstancer(p)
        # without the prototypes' own transforms: ``own`` below applies each once
        alone = UsdGeom.PointInstancer.ExcludeProtoXform
        xf = pi.ComputeInstanceTransformsAtTime(when, when, alone)
        idx = pi.GetProtoIndicesAttr().Get(when)
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
        targets = pi.GetPrototypesRel().GetTargets()
        if top and instancing and "leaf" not in class_labels(p):
            met = sum(1 for t in targets if t not in proto_of and _instanced(stage, t))
            gathered[1] += met
            if met:
                tick("tree prototypes", gathered[0], gathered[1])
        for k, target in enumerate(targets):
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
                                own=own
                                if UsdGeom.Xformable(proto).TransformMightBeTimeVarying()
                                else None,
                            ),
                        ),
                    )
                )
                continue
            is_tree = "tree" in class_labels(proto)
            if centre is not None and radius is not None:  # trees, dead wood: those in reach
                ext = bbox.ComputeUntransformedBound(proto).ComputeAlignedRange()
                r_proto = float(np.linalg.norm(np.array(ext.GetMax()) - np.array(ext.GetMin())))
                world_pos = xf[sel, 3, :3] @ to_world[:3, :3] + to_world[3, :3]
                # the largest stretch of each instance (dead wood is scaled more along)
                scale = np.linalg.svd(xf[sel, :3, :3] @ to_world[:3, :3], compute_uv=False)[:, 0]
                sel = sel[np.linalg.norm(world_pos - centre, axis=1) <= radius + r_proto * scale]
                if sel.size == 0:
                    continue
            if top and instancing and _instanced(stage, target):
                moving = parts(proto)  # before the prototype: it is gathered without them
                k_proto = prototype(proto)
                for i in sel:
                    m = own @ xf[i] @ to_root
                    tree_id = int(ids[i]) if is_tree else -1
                    placed.append((k_proto, m, tree_id))
                    sources.append((str(p.GetPath()), int(i), own, to_root, -1))
                    for k_part, row, rel in moving:
                        placed.append((k_part, rel @ m, tree_id))
                        sources.append((str(p.GetPath()), int(i), own, to_root, row))
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
    placed_leaves = []
    for i, (k, m, t) in enumerate(placed if reflectors else []):
        lv = leaves_placed(protos[k], m, t, centre, radius)
        if part_rows:  # a tree is placed as more than one instance: say which placed each
            lv = replace(lv, carrier=np.full(len(lv), i, np.int64))
        placed_leaves.append(lv)
        tick("leaf reflectors", i + 1, len(placed))
    leaves = Leaves.concat([r[0] for r in realised] + placed_leaves)
    tree, leaf_tree = whole.tree, leaves.tree
    # an animated stage's shape turns and sweeps, kept (a second for the windy default forest)
    digest = hashlib.blake2b("\0".join(shape_keys).encode(), digest_size=16).hexdigest()
    turns, sweep = kept(
        store_get() if parted else None, f"shape turns {digest}", repr(when.GetValue()),
        lambda: shape_turns(stage, shape_keys, shapes, when),
        lambda v: valid_turns(v, len(shape_keys)),
    )  # fmt: skip
    turning = bool(leaves.turning.any()) or turns is not None
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
        replace(leaves, tree=leaf_tree),
        bounds,
        tuple(protos),
        inst,
        tuple(dict.fromkeys(unseen)),
        tuple(shapes)
        if world_leaves.shape.size or any(len(p.leaf_instances) for p in protos) or turning
        else (),
        world_leaves,
        Sources.of(sources, part_rows),
        tuple(shape_keys) if turning else (),
        turns,
        sweep,
    )
