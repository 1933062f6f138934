"""Light stand-ins for a tree (pure numpy/scipy): a crown hull, a stem prism, leaf clusters.

* **Crown**: the convex hull of the leaves' attachment points and the branch tips, built from
  their support points along 162 directions, so it has at most a few hundred triangles
  whatever the leaf count.
* **Stem**: an 8-sided prism from the trunk's base to the top of its axis, as thick as its
  base.
* **Leaf clusters** (the ``medium`` level): every k-th leaf, scaled by sqrt(k) so the leaf
  area is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.grow.placement import Placement, frames_from_directions

HULL_DIRECTIONS = 162
STEM_SIDES = 8
CLUSTER = 8  # leaves merged into one in the medium level


def _fibonacci_sphere(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def crown_hull(points: np.ndarray, budget: int = 900) -> tuple[np.ndarray, np.ndarray] | None:
    """``(vertices, triangles)`` of a convex crown around ``points``, outward winding, with
    at most about ``budget`` triangles and every point inside; None when the points span no
    volume.

    The exact hull when it is small enough; otherwise the hull of the support points along
    ``HULL_DIRECTIONS`` directions, scaled about its centre just enough to contain them all.
    """
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 4:
        return None
    try:
        hull = ConvexHull(pts)
        outer = pts[hull.vertices]  # a linear function's maximum over pts is at one of these
        if len(hull.simplices) > budget:
            dirs = _fibonacci_sphere(HULL_DIRECTIONS)
            hull = ConvexHull(pts[np.unique(np.argmax(pts @ dirs.T, axis=0))])
    except QhullError:
        return None
    used, tri = np.unique(hull.simplices, return_inverse=True)
    v = hull.points[used]
    tri = tri.reshape(-1, 3)
    c = v.mean(axis=0)
    # qhull does not orient its simplices: make each face's normal point away from the centre
    n = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    flip = np.einsum("ij,ij->i", n, v[tri[:, 0]] - c) < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    n[flip] = -n[flip]
    # grow about the centre until no point is outside any face plane
    reach = np.einsum("ij,ij->i", n, v[tri[:, 0]] - c)  # > 0 for every face
    # (einsum, not BLAS: the same bits on every machine)
    worst = float(np.max(np.einsum("pk,fk->pf", outer - c, n) / reach))
    v = c + (v - c) * max(worst, 1.0) * (1.0 + 1e-6)
    return v, tri


def stem_prism(base: np.ndarray, tip: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """An ``STEM_SIDES``-sided closed prism from ``base`` to ``tip``."""
    d = np.asarray(tip, float) - np.asarray(base, float)
    length = float(np.linalg.norm(d)) or 1e-6
    rot = frames_from_directions((d / length)[None], np.zeros(1))[0]
    a = np.linspace(0.0, 2 * math.pi, STEM_SIDES, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1) * radius
    bottom = ring @ rot.T + base
    top = ring @ rot.T + tip
    v = np.concatenate([bottom, top, [base, tip]])
    s = STEM_SIDES
    tri = []
    for j in range(s):
        k = (j + 1) % s
        tri += [[j, k, s + k], [j, s + k, s + j], [2 * s, k, j], [2 * s + 1, s + j, s + k]]
    return v, np.array(tri)


def proxy_points(p: Placement) -> np.ndarray:
    """What the crown hull wraps: leaf attachment points, or branch tips without leaves."""
    if p.n_leaves:
        return p.leaf_position
    branches = p.order > 0
    return np.concatenate([p.translate[branches], p.tip[branches]])


def leaf_clusters(p: Placement, k: int = CLUSTER) -> dict[str, np.ndarray]:
    """Every ``k``-th leaf, scaled by sqrt(k): the same leaf area from k times fewer
    instances (``leaf``: which leaf each cluster is)."""
    sel = np.arange(0, p.n_leaves, k)
    return {
        "leaf": sel,
        "position": p.leaf_position[sel],
        "orient": p.leaf_orient[sel],
        "scale": p.leaf_scale[sel] * math.sqrt(k),
        "proto": p.leaf_proto[sel],
    }


@dataclass(frozen=True, eq=False)
class Levels:
    """The geometry of the lighter levels of detail of one tree."""

    clusters: dict[str, np.ndarray]  # the medium level's leaves (see :func:`leaf_clusters`)
    stem: tuple[np.ndarray, np.ndarray]  # the proxy's (vertices, triangles)
    crown: tuple[np.ndarray, np.ndarray] | None

    def proxy_vertices(self) -> np.ndarray:
        """Every vertex of the proxy level's meshes."""
        parts = [self.stem[0]] + ([self.crown[0]] if self.crown is not None else [])
        return np.concatenate(parts)


def levels(p: Placement) -> Levels:
    """The medium leaf clusters and the proxy stem and crown of a placed tree."""
    trunk = p.trunk
    return Levels(
        leaf_clusters(p),
        stem_prism(p.translate[trunk], p.tip[trunk], float(p.radius[trunk])),
        crown_hull(proxy_points(p)),
    )
