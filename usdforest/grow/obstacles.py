"""The living stems as obstacles on the ground: what dead wood, shrubs and young trees are
placed clear of."""

from __future__ import annotations

import numpy as np

from usdforest.grow import exact


class Stems:
    """Stems as discs (centres ``xy`` (n, 2), base radii ``r``), the few near a footprint
    found by a k-d tree (a square kilometre holds 45,000 stems)."""

    def __init__(self, xy: np.ndarray, r: np.ndarray) -> None:
        from scipy.spatial import cKDTree

        self.xy = np.asarray(xy, float).reshape(-1, 2)
        self.r = np.asarray(r, float)
        self.tree = cKDTree(self.xy) if len(self.xy) else None
        self.reach = float(self.r.max()) if len(self.r) else 0.0

    def clear(self, a: np.ndarray, b: np.ndarray, r: float, gap: float) -> bool:
        """Whether the capsule ``a``-``b`` of radius ``r`` (a disc when ``a`` is ``b``) keeps
        ``gap`` from every stem's bark."""
        if self.tree is None:
            return True
        half = float(np.linalg.norm(b - a)) / 2
        near = self.tree.query_ball_point((a + b) / 2, half + r + self.reach + gap)
        # stems beyond the reach are clear of every radius; the near ones are tested exactly
        return not np.any(point_segment(self.xy[near], a, b) < r + self.r[near] + gap)


def point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances of points ``p`` (m, 2) from the segment ``a``-``b``."""
    ab = b - a
    t = np.clip(exact.dot(p - a, ab) / max(float(exact.dot(ab, ab)), 1e-18), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)
