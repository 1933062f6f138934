"""Skeleton: a tree's wood and leaf sites as a struct of numpy arrays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Skeleton:
    """Segments (internodes) and leaf sites produced by the turtle.

    Attributes
    ----------
    start, end
        ``float64[n, 3]`` segment end points in metres (Z up).
    radius
        ``float64[n]`` segment radius at its start.
    order
        ``int16[n]`` branching order: 0 trunk, 1 first-order branch, ...
    parent
        ``int32[n]`` index of the segment this one grows from, -1 for the root.
    axis
        ``int32[n]`` index of the axis (trunk or branch, a chain of segments) of each segment.
    axis_order
        ``int16[a]`` order of each axis; ``axis_order[axis]`` equals ``order``.
    leaf_position
        ``float64[m, 3]`` leaf attachment points.
    leaf_frame
        ``float64[m, 3, 3]`` turtle frame at each leaf; rows are heading, left and up.
    leaf_segment
        ``int32[m]`` the segment each leaf sits on (-1 if placed before any segment).
    leaf_size
        ``float64[m]`` leaf scale (the leaf module's first parameter, else 1).
    """

    start: np.ndarray
    end: np.ndarray
    radius: np.ndarray
    order: np.ndarray
    parent: np.ndarray
    axis: np.ndarray
    axis_order: np.ndarray
    leaf_position: np.ndarray
    leaf_frame: np.ndarray
    leaf_segment: np.ndarray
    leaf_size: np.ndarray

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            getattr(self, name).setflags(write=False)

    @property
    def n_segments(self) -> int:
        return int(self.start.shape[0])

    @property
    def n_leaves(self) -> int:
        return int(self.leaf_position.shape[0])

    @property
    def length(self) -> np.ndarray:
        """``float64[n]`` segment lengths."""
        return np.linalg.norm(self.end - self.start, axis=1)

    def axes_of_order(self, order: int) -> int:
        """Number of axes (trunk = 0, first-order branches = 1, ...) of a given order."""
        return int(np.count_nonzero(self.axis_order == order))

    def branch_counts(self) -> dict[int, int]:
        """Number of axes per order, e.g. ``{0: 1, 1: 8, 2: 32}``."""
        orders, counts = np.unique(self.axis_order, return_counts=True)
        return {int(o): int(c) for o, c in zip(orders, counts, strict=True)}

    def is_terminal(self) -> np.ndarray:
        """``bool[n]``: segments no other segment grows from (the youngest wood)."""
        has_child = np.zeros(self.n_segments, dtype=bool)
        p = self.parent[self.parent >= 0]
        has_child[p] = True
        return ~has_child

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds of segment end points and leaf sites (min, max)."""
        pts = np.concatenate([self.start, self.end, self.leaf_position])
        if pts.size == 0:
            return np.zeros(3), np.zeros(3)
        return pts.min(axis=0), pts.max(axis=0)

    def height(self) -> float:
        lo, hi = self.bounds()
        return float(hi[2] - lo[2])

    def stats(self) -> dict[str, object]:
        """Summary numbers for metadata and the CLI."""
        return {
            "segments": self.n_segments,
            "leaves": self.n_leaves,
            "branches_by_order": {str(k): v for k, v in self.branch_counts().items()},
            "height": round(self.height(), 6),
            "wood_length": round(float(self.length.sum()), 6),
        }
