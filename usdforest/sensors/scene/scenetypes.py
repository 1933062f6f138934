"""The scene a sensor sees, as plain arrays: leaves as reflectors, leaf shapes and their
instances, tree prototypes and their instances, and the whole
(:class:`Scene`, made by :func:`usdforest.sensors.scene.extraction.extract_scene`)."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

CLASSES = ("unknown", "trunk", "branch", "leaf", "ground", "dead_wood", "ground_vegetation")
CLASS_ID = {name: i for i, name in enumerate(CLASSES)}


def class_counts(cls: np.ndarray) -> dict[str, int]:
    """How many of ``cls`` (class indices) fall in each class, by name."""
    counts = np.bincount(np.asarray(cls, dtype=np.int64), minlength=len(CLASSES))
    return {c: int(n) for c, n in zip(CLASSES, counts, strict=True)}


@dataclass(frozen=True, eq=False)
class Leaves:
    """Leaves as reflectors: centre, unit normal, one-sided area (m²), tree id; ``blade``
    marks the ground vegetation's (``None``: no leaf is).

    Leaves that turn in their own frame (a forest's fluttering leaves) also keep ``shape``,
    the index of their leaf shape among the scene's (-1: the leaf does not turn), and
    ``frame``, ``(n, 4, 4)`` row-vector transforms from the shape's space to where the leaf
    is without its turn (so the leaf at another turn ``R``, its shape's own transform, is
    its shape's centre through ``R @ frame``); ``None`` when no leaf turns.

    ``carrier`` is the index of the scene's instance that placed each leaf (-1: none), where
    a tree is placed as more than one instance (its limbs that sway on their own); ``None``:
    each leaf moves with the one instance of its tree id."""

    centre: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    tree: np.ndarray
    blade: np.ndarray | None = None
    shape: np.ndarray | None = None
    frame: np.ndarray | None = None
    carrier: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.centre.shape[0])

    @property
    def turning(self) -> np.ndarray:
        """``bool[n]``: which leaves turn in their own frame (flutter)."""
        return self.shape >= 0 if self.shape is not None else np.zeros(len(self), dtype=bool)

    @property
    def on_ground(self) -> np.ndarray:
        """``bool[n]``: which leaves are the ground vegetation's blades."""
        return self.blade if self.blade is not None else np.zeros(len(self), dtype=bool)

    def take(self, sel: np.ndarray) -> Leaves:
        """The leaves ``sel`` (indices or a mask)."""
        blade = self.blade[sel] if self.blade is not None else None
        shape = self.shape[sel] if self.shape is not None else None
        frame = self.frame[sel] if self.frame is not None else None
        carrier = self.carrier[sel] if self.carrier is not None else None
        return Leaves(
            self.centre[sel],
            self.normal[sel],
            self.area[sel],
            self.tree[sel],
            blade,
            shape,
            frame,
            carrier,
        )

    @property
    def radius(self) -> np.ndarray:
        """Equivalent disk radius sqrt(area / pi)."""
        return np.sqrt(self.area / np.pi)

    @staticmethod
    def concat(parts: list[Leaves]) -> Leaves:
        if not parts:
            return Leaves(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))
        blade = (
            np.concatenate([p.on_ground for p in parts])
            if any(p.blade is not None for p in parts)
            else None
        )
        turning = any(p.shape is not None for p in parts)
        shape = np.concatenate([p._shapes() for p in parts]) if turning else None
        frame = np.concatenate([p._frames() for p in parts]) if turning else None
        carrier = (
            np.concatenate([p._carriers() for p in parts])
            if any(p.carrier is not None for p in parts)
            else None
        )
        return Leaves(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("centre", "normal", "area", "tree")
            ),
            blade,
            shape,
            frame,
            carrier,
        )

    def _carriers(self) -> np.ndarray:
        return self.carrier if self.carrier is not None else np.full(len(self), -1, np.int64)

    def _shapes(self) -> np.ndarray:
        return self.shape if self.shape is not None else np.full(len(self), -1, np.int64)

    def _frames(self) -> np.ndarray:
        return self.frame if self.frame is not None else np.tile(np.eye(4), (len(self), 1, 1))


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


def no_leaves() -> LeafInstances:
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
    leaf_instances: LeafInstances = field(default_factory=no_leaves)

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
class Sources:
    """Where each of a scene's :class:`Instances` comes from on its stage, so that it can be
    placed again at another time: its PointInstancer (``instancer``, an index into
    ``instancers``), its row there, and the transforms before and after the instancer's own
    (row vectors: ``matrix = before @ instance row @ after``)."""

    instancers: tuple[str, ...]
    instancer: np.ndarray
    row: np.ndarray
    before: np.ndarray
    after: np.ndarray
    # a part of a prototype that moves on its own (a limb that sways): its prim and its
    # prototype's (``parts``), and per instance the part it places (-1: a whole prototype),
    # its matrix then ``part's transform in its prototype @ before @ row @ after``
    parts: tuple[tuple[str, str], ...] = ()
    part: np.ndarray | None = None

    @staticmethod
    def of(
        rows: list[tuple[str, int, np.ndarray, np.ndarray, int]], parts: list[tuple[str, str]]
    ) -> Sources:
        """From one ``(instancer, row, before, after, part)`` per instance and the parts."""
        names = tuple(dict.fromkeys(r[0] for r in rows))
        index = {n: k for k, n in enumerate(names)}
        return Sources(
            names,
            np.array([index[r[0]] for r in rows], dtype=np.int64),
            np.array([r[1] for r in rows], dtype=np.int64),
            np.array([r[2] for r in rows]).reshape(-1, 4, 4),
            np.array([r[3] for r in rows]).reshape(-1, 4, 4),
            tuple(parts),
            np.array([r[4] for r in rows], dtype=np.int64) if parts else None,
        )

    def __len__(self) -> int:
        return int(self.row.shape[0])


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
    leaf_instances: LeafInstances = field(default_factory=no_leaves)  # in world space
    sources: Sources | None = None  # where its instances come from (to move them in time)
    shape_paths: tuple[str, ...] = ()  # each leaf shape's prim (to turn it in time)
    # where shapes turn in time: each shape prim's own transform at the scene's time
    # ``(shapes, 4, 4)`` and its box over every turn, in its space then ``(shapes, 2, 3)``
    # (:mod:`usdforest.sensors.scene.turns`)
    shape_turns: np.ndarray | None = None
    shape_sweep: np.ndarray | None = None

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
