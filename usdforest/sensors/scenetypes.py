"""The scene a sensor sees, as plain arrays: leaves as reflectors, leaf shapes and their
instances, tree prototypes and their instances, and the whole
(:class:`Scene`, made by :func:`usdforest.sensors.scene.extract_scene`)."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class Leaves:
    """Leaves as reflectors: centre, unit normal, one-sided area (m²), tree id; ``blade``
    marks the ground vegetation's (``None``: no leaf is).

    Leaves that turn in their own frame (a forest's fluttering leaves) also keep ``shape``,
    the index of their leaf shape among the scene's (-1: the leaf does not turn), and
    ``frame``, ``(n, 4, 4)`` row-vector transforms from the shape's space to where the leaf
    is without its turn (so the leaf at another turn ``R``, its shape's own transform, is
    its shape's centre through ``R @ frame``); ``None`` when no leaf turns."""

    centre: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    tree: np.ndarray
    blade: np.ndarray | None = None
    shape: np.ndarray | None = None
    frame: np.ndarray | None = None

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
        return Leaves(
            self.centre[sel], self.normal[sel], self.area[sel], self.tree[sel], blade, shape, frame
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
        return Leaves(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("centre", "normal", "area", "tree")
            ),
            blade,
            shape,
            frame,
        )

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
