"""Walking a composed stage into the parts of a sensor scene: meshes and implicit shapes as
triangles, PointInstancers' leaves as batches of one shape each, tree prototypes gathered
once and placed by their instances, native instances read once per prototype
(:class:`StageWalk`, which :func:`~usdforest.sensors.scene.extraction.extract_scene` drives).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
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
    CLASS_ID,
    LeafInstances,
    Leaves,
    Prototype,
    Shape,
    no_leaves,
)
from usdforest.sensors.scene.stageframe import animated, leaf_boxes, moved_boxes
from usdforest.sensors.scene.turns import moving_parts, shape_turns
from usdforest.usd.layers import class_labels, mesh_triangles, rendered

if TYPE_CHECKING:
    from pxr import Usd

# prototypes kept as instances (two levels) rather than copied: trees, shrubs and young trees
# (tree assets), and ground-vegetation patches (thousands of copies of four meshes of
# thousands of triangles each); only trees carry their instancer's ids as tree ids
INSTANCED = ("tree", "shrub", "regeneration", "ground_vegetation")
# ground vegetation that echoes as the rough ground under it does, not as leaves
CARPETS = ("moss",)


@dataclass(frozen=True, eq=False)
class LeafBatch:
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
class Part:
    tri: np.ndarray
    cls: np.ndarray
    tree: np.ndarray
    path: np.ndarray
    batches: tuple[LeafBatch, ...] = field(default=())

    def transformed(self, m: np.ndarray, tree: int | None = None) -> Part:
        rot, t = m[:3, :3].astype(np.float32), m[3, :3].astype(np.float32)
        tri = (self.tri.reshape(-1, 3) @ rot + t).reshape(-1, 3, 3)
        trees = self.tree if tree is None else np.full_like(self.tree, tree)
        batches = tuple(
            replace(b, xf=b.xf @ m, tree=b.tree if tree is None else tree) for b in self.batches
        )
        return Part(tri, self.cls, trees, self.path, batches)

    @staticmethod
    def concat(parts: list[Part]) -> Part:
        parts = [p for p in parts if len(p.tri) or p.batches]
        if not parts:
            return Part(
                np.zeros((0, 3, 3), np.float32),
                np.zeros(0, np.uint8),
                np.zeros(0, np.int32),
                np.zeros(0, np.int32),
            )
        return Part(
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


def realise(
    b: LeafBatch,
    centre: np.ndarray | None,
    radius: float | None,
    triangles: str | None = "copy",
    reflectors: bool = True,
) -> tuple[Leaves, Part, LeafInstances]:
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
        return leaves, Part.concat([]), kept
    tri = (
        np.einsum("tvj,njk->ntvk", b.tri, rot.astype(np.float32))
        + xf[:, None, None, 3, :3].astype(np.float32)
    ).reshape(-1, 3, 3)
    part = Part(
        tri.astype(np.float32),
        np.tile(b.cls, n),
        np.full(n * t, b.tree, np.int32),
        np.tile(b.path, n),
    )
    return leaves, part, no_leaves()


class StageWalk:
    """One walk of a composed stage into the parts of its scene, in metres with Z up
    (``frame``) at the time code ``when``: each tree prototype gathered once (or read from
    the stage's prototype store) and placed by its instances, each leaf shape gathered once
    and placed by its leaves, everything else copied as triangles. See
    :func:`~usdforest.sensors.scene.extraction.extract_scene` for the arguments; what the
    walk met stays on it (``paths``, ``protos``, ``placed``, ``shapes``, ``unseen``, ...)
    for the scene to be assembled from."""

    def __init__(
        self,
        stage: Usd.Stage,
        frame: np.ndarray,
        when: Usd.TimeCode,
        *,
        centre: np.ndarray | None,
        radius: float | None,
        instancing: bool,
        leaf_triangles: bool,
        reflectors: bool,
        use_store: bool,
        progress: Callable[[str, int, int], None] | None,
    ):
        from pxr import UsdGeom

        self.stage, self.frame, self.when = stage, frame, when
        self.centre, self.radius = centre, radius
        self.instancing, self.reflectors, self.use_store = instancing, reflectors, use_store
        self.xforms = UsdGeom.XformCache(when)
        self.bbox = UsdGeom.BBoxCache(when, ["default", "render"], True)
        self.natives = NativeMeshes(self.xforms, CLASS_ID)
        self.paths: list[str] = []
        self.path_index: dict[str, int] = {}
        self.memo: dict = {}
        self.protos: list[Prototype] = []
        self.proto_of: dict = {}
        self.unseen: list[str] = []
        self.placed: list[tuple[int, np.ndarray, int]] = []
        # per placed instance: its instancer's path, its row there, the transforms around the
        # row and the moving part it places (-1: the whole prototype)
        self.sources: list[tuple[str, int, np.ndarray, np.ndarray, int]] = []
        self.shapes: list[Shape] = []
        self.shape_of: dict = {}
        self.shape_keys: list[str] = []
        self.geometry = ("instance" if instancing else "copy") if leaf_triangles else None
        # an animated stage's prototypes move in time too (its leaves flutter): kept per time
        moves = animated(stage)
        at_time = moves and not when.IsDefault()
        self.store_mode = (
            f"{self.geometry} at {when.GetValue():.17g}" if at_time else str(self.geometry)
        )
        self._store: list = []  # the prototype store, opened when the first prototype is met
        # an animated stage's tree prototypes may have parts that move on their own (limbs
        # that sway): each part is an instance of its own, its tree's prototype gathered
        # without it
        self.parted = moves
        self.parts_of: dict = {}
        self.part_rows: list[tuple[str, str]] = []  # (part prim, its prototype's prim)
        self.pruned: set = set()  # the parts' prims, which their prototypes' subtrees leave out
        self._proxied = [0, False]  # how many of ``pruned`` were looked at, one a proxy?
        self.gathered = [0, 0]  # prototypes gathered, prototypes met
        self.tick = progress or (lambda stage, done, total: None)

    def _m_at(self, prim) -> np.ndarray:
        return _m(self.xforms.GetLocalToWorldTransform(prim))

    def store(self) -> PrototypeStore | None:
        if not self._store:
            self._store.append(PrototypeStore.of(self.stage) if self.use_store else None)
        return self._store[0]

    def bounds(self) -> np.ndarray:
        """The stage's world bounds (2, 3) in the sensors' frame; zeros for an empty stage."""
        box = self.bbox.ComputeWorldBound(self.stage.GetPseudoRoot()).ComputeAlignedRange()
        if box.IsEmpty():
            return np.zeros((2, 3))
        lo, hi = moved_boxes(np.array([box.GetMin()]), np.array([box.GetMax()]), self.frame[None])
        return np.concatenate([lo, hi])

    def gather(self, prim, with_reflectors: bool) -> Prototype:
        """A (tree) prototype's wood and leaves, in its own space."""
        part = self.subtree(prim)
        realised = [realise(b, None, None, self.geometry, with_reflectors) for b in part.batches]
        whole = replace(part, batches=())
        kept_leaves = LeafInstances.concat([r[2] for r in realised])
        lo, hi = leaf_boxes(kept_leaves, tuple(self.shapes))
        pts = np.concatenate([whole.tri.reshape(-1, 3).astype(float), lo, hi])
        lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(3),) * 2
        reflecting = [r[0] for r in realised]
        if with_reflectors and _form(prim) not in CARPETS:
            blades = whole.tri[whole.cls == CLASS_ID["ground_vegetation"]]
            reflecting.append(blade_reflectors(blades))
        return Prototype(
            whole.tri, whole.cls, whole.path, Leaves.concat(reflecting), np.array([lo, hi]),
            kept_leaves,
        )  # fmt: skip

    def prototype(self, prim, counted: bool = True) -> int:
        """Index of the (tree) prototype ``prim`` (or a part of one: not ``counted``),
        gathered once (or read from the store), its leaves as instances."""
        key = prim.GetPath()
        if key not in self.proto_of:
            store = self.store()
            moving = len(self.parts_of.get(key, ()))
            mode = f"{self.store_mode} without {moving} parts" if moving else self.store_mode
            entry = store.get(str(key), mode, valid_stored) if store is not None else None
            if entry is None:
                seen = (len(self.unseen), len(self.paths), len(self.shapes))
                proto = self.gather(prim, self.reflectors or store is not None)
                if store is not None:
                    local = stored(
                        proto, self.paths, self.shapes, self.shape_keys, seen,
                        self.unseen[seen[0] :],
                    )  # fmt: skip
                    store.put(str(key), mode, local)
            else:
                proto = adopted(entry, self.pid, self.add_shape)
                self.unseen.extend(entry["unseen"])
            if not self.reflectors:
                proto = replace(proto, leaves=Leaves.concat([]))
            self.proto_of[key] = len(self.protos)
            self.protos.append(proto)
            if counted:
                self.gathered[0] += 1
                self.tick("tree prototypes", self.gathered[0], self.gathered[1])
        return self.proto_of[key]

    def moving_parts(self, proto) -> list[tuple[int, int, np.ndarray]]:
        """The parts of the tree prototype ``proto`` whose transforms have time samples (its
        limbs that sway), each one's prototype, its row in ``part_rows`` and its transform
        into ``proto``'s space now (row vectors); leaf instancers' own turns are not
        parts (:class:`LeafBatch` ``own``)."""
        key = proto.GetPath()
        if key in self.parts_of:
            return self.parts_of[key]
        found = []
        if self.parted:  # 0.8 s in the windy default forest: kept with its prototypes
            names = kept(
                self.store(),
                f"parts of {key}",
                "moving",
                lambda: moving_parts(proto),
                lambda v: isinstance(v, list) and all(isinstance(n, str) for n in v),
            )
            found = [self.stage.GetPrimAtPath(n) for n in names]
        self.parts_of[key] = found  # read by ``prototype(proto)``'s store key
        self.pruned.update(q.GetPath() for q in found)
        inv = np.linalg.inv(self._m_at(proto))
        out = []
        for q in found:
            self.part_rows.append((str(q.GetPath()), str(key)))
            rel = self._m_at(q) @ inv
            out.append((self.prototype(q, counted=False), len(self.part_rows) - 1, rel))
        self.parts_of[key] = out
        return out

    def add_shape(self, key: str, s: Shape) -> int:
        if key not in self.shape_of:
            self.shape_of[key] = len(self.shapes)
            self.shapes.append(s)
            self.shape_keys.append(key)
        return self.shape_of[key]

    def shape(self, prim, local: Part) -> int:
        """Index of the leaf shape ``prim`` (its triangles gathered once)."""
        return self.add_shape(str(prim.GetPath()), Shape(local.tri, local.cls, local.path))

    def pid(self, p: str) -> int:
        if p not in self.path_index:
            self.path_index[p] = len(self.paths)
            self.paths.append(p)
        return self.path_index[p]

    def moving_proxies(self) -> bool:
        """Whether a part that moves on its own lies inside a native instance."""
        if self._proxied[0] != len(self.pruned):
            self._proxied[:] = [
                len(self.pruned),
                any(self.stage.GetPrimAtPath(q).IsInstanceProxy() for q in self.pruned),
            ]
        return self._proxied[1]

    def subtree(self, prim, top: bool = False) -> Part:
        """Everything under ``prim`` in ``prim``'s own space (memoised: prototypes)."""
        from pxr import Usd, UsdGeom

        key = prim.GetPath()
        if key in self.memo:
            return self.memo[key]
        inv = np.linalg.inv(self._m_at(prim))
        if top:  # the world: in metres, Z up
            inv = inv @ self.frame
        parts: list = []
        rows: dict = {}  # native instances met: (prototype, mesh) -> their slots in ``parts``
        it = iter(Usd.PrimRange(prim, Usd.TraverseInstanceProxies()))
        for p in it:
            if (
                not rendered(p)
                or (p != prim and p.GetPath() in self.pruned)  # a part that moves on its own
                or (
                    p.IsA(UsdGeom.Imageable)
                    and UsdGeom.Imageable(p).ComputeVisibility() == "invisible"
                )
            ):
                it.PruneChildren()
                continue
            if p.IsA(UsdGeom.Mesh) or p.GetTypeName() in IMPLICIT:
                mesh = self._mesh(p, prim, self._m_at(p) @ inv)
                if mesh is not None:
                    parts.append(mesh)
            elif p.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()
                parts.append(self.instances(p, self._m_at(p) @ inv, top))
            elif p.IsA(UsdGeom.Gprim):
                self.unseen.append(str(p.GetPath()))
            if p.IsInstance() and not p.IsA(UsdGeom.PointInstancer):
                inner = self.natives.of(p.GetPrototype())
                if inner is None or self.moving_proxies():
                    continue  # walked proxy by proxy
                it.PruneChildren()
                to_root = self._m_at(p) @ inv
                outer = _class_of(p, prim) if any(c is None for *_, c in inner) else 0
                for j, (below, _, cls) in enumerate(inner):
                    row = (len(parts), to_root, self.pid(f"{p.GetPath()}/{below}"))
                    rows.setdefault((p.GetPrototype().GetPath(), j), []).append(
                        (*row, outer if cls is None else cls)
                    )
                    parts.append(None)
        for slot, path_id, cls, t in self.natives.place(rows):
            n = len(t)
            cls_tree_path = ((cls, np.uint8), (-1, np.int32), (path_id, np.int32))
            parts[slot] = Part(t, *(np.full(n, v, d) for v, d in cls_tree_path))
        out = Part.concat(parts)
        self.memo[key] = out
        return out

    def _mesh(self, p, prim, to_root: np.ndarray) -> Part | None:
        """The mesh or implicit shape ``p`` under ``prim`` as triangles in ``prim``'s space."""
        from pxr import UsdGeom

        if p.IsA(UsdGeom.Mesh):
            tri = _triangles(p, to_root)
        else:  # Cube, Sphere, ...: tessellated (see sensors.scene.implicit)
            local = shape_triangles(p)
            if local is None:
                return None
            tri = (local @ to_root[:3, :3] + to_root[3, :3]).astype(np.float32)
        n = len(tri)
        return Part(
            tri,
            np.full(n, _class_of(p, prim), np.uint8),
            np.full(n, -1, np.int32),
            np.full(n, self.pid(str(p.GetPath())), np.int32),
        )

    def instances(self, p, to_root: np.ndarray, top: bool = False) -> Part:
        """A PointInstancer's instances, in the space of the subtree being gathered: leaves
        as batches of one shape, tree prototypes (at the top) as placed instances of the
        prototypes gathered once, anything else copied."""
        from pxr import UsdGeom

        pi = UsdGeom.PointInstancer(p)
        # without the prototypes' own transforms: ``own`` below applies each once
        alone = UsdGeom.PointInstancer.ExcludeProtoXform
        xf = pi.ComputeInstanceTransformsAtTime(self.when, self.when, alone)
        idx = pi.GetProtoIndicesAttr().Get(self.when)
        if xf is None or idx is None or len(idx) == 0:
            return Part.concat([])
        xf = np.asarray(xf, dtype=float).reshape(-1, 4, 4)
        idx = np.asarray(idx)
        ids_attr = pi.GetIdsAttr().Get()
        ids = (
            np.asarray(ids_attr, dtype=np.int64)
            if ids_attr is not None and len(ids_attr)
            else np.arange(len(idx), dtype=np.int64)
        )
        to_world = self._m_at(p) @ self.frame
        out = []
        targets = pi.GetPrototypesRel().GetTargets()
        leaves = "leaf" in class_labels(p)
        if top and self.instancing and not leaves:
            met = sum(1 for t in targets if t not in self.proto_of and _instanced(self.stage, t))
            self.gathered[1] += met
            if met:
                self.tick("tree prototypes", self.gathered[0], self.gathered[1])
        for k, target in enumerate(targets):
            sel = np.flatnonzero(idx == k)
            proto = self.stage.GetPrimAtPath(target)
            if sel.size == 0 or not proto:
                continue
            own = _m(self.xforms.GetLocalTransformation(proto)[0])
            if leaves:
                out.append(
                    self._leaf_batch(proto, np.einsum("ij,njk->nik", own, xf[sel]) @ to_root)
                )
                continue
            is_tree = "tree" in class_labels(proto)
            sel = self._in_reach(proto, sel, xf, to_world)
            if sel.size == 0:
                continue
            if top and self.instancing and _instanced(self.stage, target):
                self._place(p, proto, sel, xf, ids, own, to_root, is_tree)
                continue
            local = self.subtree(proto)
            for i in sel:
                out.append(
                    local.transformed(own @ xf[i] @ to_root, int(ids[i]) if is_tree else None)
                )
        return Part.concat(out)

    def _leaf_batch(self, proto, xf: np.ndarray) -> Part:
        """The leaf prototype ``proto``'s instances at ``xf`` (n, 4, 4), as one batch."""
        from pxr import UsdGeom

        local = self.subtree(proto)
        pts = local.tri.reshape(-1, 3).astype(float)
        lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(3),) * 2
        own = _m(self.xforms.GetLocalTransformation(proto)[0])
        batch = LeafBatch(
            local.tri,
            local.cls,
            local.path,
            xf,
            _leaf_area_unit(proto, local.tri),
            (lo + hi) / 2,
            float(np.linalg.norm(hi - lo)),
            self.shape(proto, local),
            own=own if UsdGeom.Xformable(proto).TransformMightBeTimeVarying() else None,
        )
        return replace(Part.concat([]), batches=(batch,))

    def _in_reach(self, proto, sel: np.ndarray, xf: np.ndarray, to_world: np.ndarray):
        """The rows ``sel`` of instances of ``proto`` whose bounds come within the walk's
        ``radius`` of its ``centre`` (all without them)."""
        if self.centre is None or self.radius is None:
            return sel
        ext = self.bbox.ComputeUntransformedBound(proto).ComputeAlignedRange()
        r_proto = float(np.linalg.norm(np.array(ext.GetMax()) - np.array(ext.GetMin())))
        world_pos = xf[sel, 3, :3] @ to_world[:3, :3] + to_world[3, :3]
        # the largest stretch of each instance (dead wood is scaled more along)
        scale = np.linalg.svd(xf[sel, :3, :3] @ to_world[:3, :3], compute_uv=False)[:, 0]
        return sel[np.linalg.norm(world_pos - self.centre, axis=1) <= self.radius + r_proto * scale]

    def _place(self, p, proto, sel, xf, ids, own, to_root, is_tree: bool) -> None:
        """Instances ``sel`` of the tree prototype ``proto`` (and its moving parts) placed."""
        moving = self.moving_parts(proto)  # before the prototype: gathered without them
        k_proto = self.prototype(proto)
        for i in sel:
            m = own @ xf[i] @ to_root
            tree_id = int(ids[i]) if is_tree else -1
            self.placed.append((k_proto, m, tree_id))
            self.sources.append((str(p.GetPath()), int(i), own, to_root, -1))
            for k_part, row, rel in moving:
                self.placed.append((k_part, rel @ m, tree_id))
                self.sources.append((str(p.GetPath()), int(i), own, to_root, row))

    def placed_reflectors(self) -> list[Leaves]:
        """The leaves of every placed instance as reflectors, those in reach (none without
        ``reflectors``)."""
        out = []
        for i, (k, m, t) in enumerate(self.placed if self.reflectors else []):
            lv = leaves_placed(self.protos[k], m, t, self.centre, self.radius)
            if self.part_rows:  # a tree placed as more than one instance: which placed each
                lv = replace(lv, carrier=np.full(len(lv), i, np.int64))
            out.append(lv)
            self.tick("leaf reflectors", i + 1, len(self.placed))
        return out

    def turns(self):
        """An animated stage's leaf-shape turns and sweeps (kept in the store: a second for
        the windy default forest), or ``(None, None)``."""
        digest = hashlib.blake2b("\0".join(self.shape_keys).encode(), digest_size=16)
        return kept(
            self.store() if self.parted else None,
            f"shape turns {digest.hexdigest()}",
            repr(self.when.GetValue()),
            lambda: shape_turns(self.stage, self.shape_keys, self.shapes, self.when),
            lambda v: valid_turns(v, len(self.shape_keys)),
        )
