"""A scene laid out for ray casting, and the hits read back from it.

:class:`RayScene` is what every instanced caster (Embree on the CPU, Warp on CUDA) builds from:
the scene's *owners* (group 0 the world's own geometry, group ``p + 1`` tree prototype ``p``),
each with its wood triangles and its leaf instances in its own space, the leaf shapes, and the
tree instances. Casters return raw hits in one convention (:class:`RawHits`), turned into
:class:`Hits` by :meth:`RayScene.hits`, so both report the same classes, paths and tree ids.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from usdforest.sensors.scene.scenetypes import Scene
from usdforest.sensors.scene.stageframe import leaf_boxes, moved_boxes
from usdforest.sensors.scene.turns import relative


class Hits:
    """First hits of a batch of rays: distance (inf: none), class, tree id, path index and the
    hit triangle's unit world-space normal (as wound)."""

    def __init__(self, n: int):
        self.t = np.full(n, np.inf)
        self.cls = np.zeros(n, dtype=np.uint8)
        self.tree = np.full(n, -1, dtype=np.int64)
        self.path = np.full(n, -1, dtype=np.int64)
        self.normal = np.zeros((n, 3))

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.t)


@dataclass(frozen=True, eq=False)
class RawHits:
    """What a caster returns per ray: distance (float32, the limit when none), tree instance
    (-1: the world's own), leaf (global index, -1: wood), face (a global wood face, or a
    global face of the leaf shapes; -1: no hit) and the hit's unit world normal."""

    t: np.ndarray
    instance: np.ndarray
    leaf: np.ndarray
    face: np.ndarray
    normal: np.ndarray


def inverse_columns(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row-vector 4x4 transforms ``m`` (n, 4, 4) in column form: the inverse of the linear part
    (``local = inv @ (x - shift)``), the shift, and which are invertible (float32)."""
    rot = m[:, :3, :3]
    # the inverse's transpose is the cofactor matrix over the determinant: three cross
    # products instead of a LAPACK call per matrix (0.1 s for a million leaves, not 0.6 s)
    r0, r1, r2 = rot[:, 0], rot[:, 1], rot[:, 2]
    cof = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=1)
    det = np.einsum("nj,nj->n", rot[:, 0], cof[:, 0])
    ok = np.abs(det) > 1e-30
    inv = np.where(ok[:, None, None], cof / np.where(ok, det, 1.0)[:, None, None], 0.0)
    return inv.astype(np.float32), m[:, 3, :3].astype(np.float32), ok


def outward32(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes ``lo``/``hi`` in float32, rounded outward so they still contain what they held."""
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
    hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return lo32, hi32


@dataclass(frozen=True, eq=False)
class RayScene:
    """A :class:`~usdforest.sensors.scene.scenetypes.Scene` as flat arrays, grouped by owner.

    Wood: ``wood`` (m, 3, 3) float32 triangles, owner ``g``'s are
    ``wood[wood_first[g]:wood_first[g + 1]]``, with class, tree id (-1 in a prototype) and
    path per triangle. Leaves (the invertible ones): column-form inverse and shift, float32
    owner-space boxes, shape and tree id, owner ``g``'s from ``leaf_first[g]``. Shapes:
    ``shape_tri[k]`` with their faces' class and path, face ``f`` of shape ``k`` numbered
    ``shape_first[k] + f``, and ``shape_box`` (shapes, 2, 3) the box of each (float64).
    Tree instances: inverse and forward linear parts (column form), shift, prototype, tree
    id, world boxes and whether each can be entered (an uninvertible transform cannot).

    Leaf shapes that turn in time (flutter): ``shape_own``, each shape prim's own transform
    where the leaves were placed (their boxes hold them at every turn), and ``shape_turn``,
    per shape the affine from its space then to its space now (``None``: as placed;
    :func:`usdforest.sensors.scene.turns.relative`), which casters apply in the leaf's frame.
    """

    wood: np.ndarray
    wood_first: np.ndarray
    wood_cls: np.ndarray
    wood_tree: np.ndarray
    wood_path: np.ndarray
    leaf_inv: np.ndarray
    leaf_shift: np.ndarray
    leaf_lo: np.ndarray
    leaf_hi: np.ndarray
    leaf_shape: np.ndarray
    leaf_tree: np.ndarray
    leaf_first: np.ndarray
    shape_tri: tuple[np.ndarray, ...]
    shape_first: np.ndarray
    shape_cls: np.ndarray
    shape_path: np.ndarray
    shape_box: np.ndarray
    inst_inv: np.ndarray
    inst_fwd: np.ndarray
    inst_shift: np.ndarray
    inst_proto: np.ndarray
    inst_tree: np.ndarray
    inst_lo: np.ndarray
    inst_hi: np.ndarray
    inst_ok: np.ndarray
    shape_own: np.ndarray | None = None
    shape_turn: np.ndarray | None = None

    @property
    def owners(self) -> int:
        return len(self.wood_first) - 1

    @staticmethod
    def of(scene: Scene) -> RayScene:
        protos = scene.protos
        owners = [
            (scene.triangles, scene.cls, scene.tree, scene.path, scene.leaf_instances),
            *(
                (p.triangles, p.cls, np.full(len(p.cls), -1), p.path, p.leaf_instances)
                for p in protos
            ),
        ]
        n_tri = np.array([len(o[0]) for o in owners], dtype=np.int64)
        wood = np.concatenate(
            [np.asarray(o[0], np.float32).reshape(-1, 3, 3) for o in owners]
        ).reshape(-1, 3, 3)
        shapes = scene.shapes
        s_tri = tuple(np.asarray(s.triangles, np.float32).reshape(-1, 3, 3) for s in shapes)
        inv, shift, lo, hi, shape, tree, n_leaf = [], [], [], [], [], [], []
        for *_, li in owners:
            a, b, good = inverse_columns(li.matrix)
            lo_k, hi_k = leaf_boxes(li, shapes, scene.shape_sweep)
            keep = slice(None) if good.all() else good  # no copies when all are invertible
            inv.append(a[keep])
            shift.append(b[keep])
            lo.append(lo_k[keep])
            hi.append(hi_k[keep])
            shape.append(li.shape[keep])
            tree.append(li.tree[keep])
            n_leaf.append(int(good.sum()))
        leaf_lo, leaf_hi = outward32(np.concatenate(lo), np.concatenate(hi))
        return RayScene(
            wood=wood,
            wood_first=np.concatenate([[0], np.cumsum(n_tri)]),
            wood_cls=np.concatenate([o[1] for o in owners]).astype(np.uint8),
            wood_tree=np.concatenate([o[2] for o in owners]).astype(np.int64),
            wood_path=np.concatenate([o[3] for o in owners]).astype(np.int64),
            leaf_inv=np.concatenate(inv).reshape(-1, 3, 3),
            leaf_shift=np.concatenate(shift).reshape(-1, 3),
            leaf_lo=leaf_lo.reshape(-1, 3),
            leaf_hi=leaf_hi.reshape(-1, 3),
            leaf_shape=np.concatenate(shape).astype(np.int64),
            leaf_tree=np.concatenate(tree).astype(np.int64),
            leaf_first=np.concatenate([[0], np.cumsum(n_leaf)]).astype(np.int64),
            shape_tri=s_tri,
            shape_first=np.concatenate([[0], np.cumsum([len(t) for t in s_tri])]).astype(np.int64),
            shape_cls=np.concatenate([s.cls for s in shapes] or [np.zeros(0)]).astype(np.uint8),
            shape_path=np.concatenate([s.path for s in shapes] or [np.zeros(0)]).astype(np.int64),
            shape_box=np.array([s.box for s in shapes], dtype=float).reshape(-1, 2, 3),
            **_instance_fields(scene),
            shape_own=scene.shape_turns,
        )

    def moved(self, scene: Scene) -> RayScene:
        """This ray scene with ``scene``'s instance transforms and leaf shapes' turns: the
        same prototypes and instances, placed anew (a forest swaying in its wind, its leaves
        fluttering)."""
        turn = None
        if self.shape_own is not None and scene.shape_turns is not None:
            turn = relative(self.shape_own, scene.shape_turns)
        return replace(self, **_instance_fields(scene), shape_turn=turn)

    def turned(self) -> RayScene:
        """This ray scene with its leaves' turns (:attr:`shape_turn`) put into the leaves'
        own transforms and boxes (for a caster that builds its scene again for each time)."""
        if self.shape_turn is None or not len(self.leaf_shape):
            return replace(self, shape_turn=None)
        e = self.shape_turn[self.leaf_shape].astype(float)
        a, b = e[:, :9].reshape(-1, 3, 3), e[:, 9:]
        inv = np.einsum("nij,njk->nik", a, self.leaf_inv.astype(float))
        fwd = np.linalg.inv(inv)  # shape space now -> owner space, column form
        # local = inv (x - s) + b = inv (x - (s - fwd b))
        shift = self.leaf_shift - np.einsum("nij,nj->ni", fwd, b)
        box = self.shape_box[self.leaf_shape]
        m = np.zeros((len(inv), 4, 4))
        m[:, :3, :3] = fwd.transpose(0, 2, 1)
        m[:, 3, :3] = shift
        m[:, 3, 3] = 1.0
        lo, hi = outward32(*moved_boxes(box[:, 0], box[:, 1], m))
        return replace(
            self,
            leaf_inv=inv.astype(np.float32),
            leaf_shift=shift.astype(np.float32),
            leaf_lo=lo,
            leaf_hi=hi,
            shape_turn=None,
        )

    def hits(self, raw: RawHits, max_range: float) -> Hits:
        """Raw caster output as :class:`Hits`: classes, paths and tree ids looked up; hits
        beyond ``max_range`` dropped."""
        from usdforest.sensors.cast import rayscene_kernels

        # compared in float32, as the distances are
        reach = np.float32(max_range) if max_range < 3.4e38 else np.float32(np.inf)
        h = Hits(0)
        h.t, h.cls, h.tree, h.path, h.normal = rayscene_kernels.label(
            raw.t, raw.instance, raw.leaf, raw.face, raw.normal, reach,
            self.wood_cls, self.wood_path, self.wood_tree, self.shape_cls, self.shape_path,
            self.leaf_tree, self.inst_tree,
        )  # fmt: skip
        return h


def _instance_fields(scene: Scene) -> dict[str, np.ndarray]:
    """The instance arrays of :class:`RayScene` for ``scene``'s tree instances."""
    inst = scene.instances
    box = np.array([p.box for p in scene.protos]).reshape(-1, 2, 3)[inst.proto]
    a, b, good = inverse_columns(inst.matrix)
    w_lo, w_hi = moved_boxes(box[:, 0], box[:, 1], inst.matrix)
    return {
        "inst_inv": a,
        "inst_fwd": inst.matrix[:, :3, :3].transpose(0, 2, 1).astype(np.float32),
        "inst_shift": b,
        "inst_proto": inst.proto.astype(np.int64),
        "inst_tree": inst.tree.astype(np.int64),
        "inst_lo": w_lo,
        "inst_hi": w_hi,
        "inst_ok": good,
    }
