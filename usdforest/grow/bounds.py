"""Exact bounds of instanced geometry, from the convex hulls of what is instanced.

A box rotated with its instance is up to ``sqrt(2)`` times too wide; the extreme points of a
transformed mesh are transformed vertices of its convex hull, so transforming only the hull's
vertices gives the exact extent. A forest's trees turn about Z only, so the hull of a tree's
points projected on the ground plane (its *footprint*) gives the exact x, y extent of every
yawed, scaled instance of it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from usdforest.grow import exact

CHUNK = 400_000  # transformed points held at once
SMALL = 20_000  # transformed points below which every instance is transformed


def hull_vertices(points: np.ndarray) -> np.ndarray:
    """The vertices of the convex hull of ``(n, 3)`` points (a superset for flat input: qhull's
    joggle keeps a planar leaf's outline)."""
    from scipy.spatial import ConvexHull, QhullError

    p = np.unique(np.asarray(points, dtype=np.float64).reshape(-1, 3), axis=0)
    if len(p) <= 8:
        return p
    try:
        return p[np.sort(ConvexHull(p, qhull_options="QJ").vertices)]
    except QhullError:  # collinear or a single point
        return p


def footprint_of(xy: np.ndarray) -> np.ndarray:
    """Vertices of the convex hull of ``(n, 2)`` points (all distinct points when
    degenerate)."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    idx, flat = _hull_indices(p)
    return np.unique(p[idx], axis=0) if flat else p[idx]


def _hull_indices(xy: np.ndarray) -> tuple[np.ndarray, bool]:
    """Ascending indices of the vertices of the hull of ``(n, 2)`` points, and whether the
    hull was degenerate (then the indices are every point that could be on it)."""
    from scipy.spatial import ConvexHull, QhullError

    cand = np.flatnonzero(_outside_octagon_mask(xy))
    if len(cand) <= 4:
        return cand, True
    try:
        return cand[np.sort(ConvexHull(xy[cand]).vertices)], False
    except QhullError:
        return cand, True


def _outside_octagon_mask(p: np.ndarray) -> np.ndarray:
    """Akl-Toussaint: the mask of the ``(n, 2)`` points not strictly inside the polygon of
    their extreme points along x, y and both diagonals (never a hull vertex), so qhull sees
    few of a million."""
    if len(p) < 64:
        return np.ones(len(p), dtype=bool)
    x, y = p[:, 0].copy(), p[:, 1].copy()
    keys = (x, x + y, y, y - x)
    ext = [int(np.argmax(k)) for k in keys] + [int(np.argmin(k)) for k in keys]
    ring = p[ext]  # east, north-east, north, north-west, west, ...: counter-clockwise
    edge = np.roll(ring, -1, axis=0) - ring
    inside = np.ones(len(p), dtype=bool)
    for (ex, ey), (rx, ry) in zip(edge, ring, strict=True):  # an edge at a time, in place
        inside &= ex * (y - ry) - ey * (x - rx) > 0
    return ~inside


@dataclass(frozen=True)
class Bounds:
    """An axis-aligned extent ``(2, 3)`` and the footprint ``(k, 2)`` of the same points."""

    extent: np.ndarray
    footprint: np.ndarray

    @staticmethod
    def of_points(points: np.ndarray) -> Bounds:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(p) == 0:
            return EMPTY
        return Bounds(np.stack([p.min(axis=0), p.max(axis=0)]), footprint_of(p[:, :2]))

    @staticmethod
    def union(parts: Sequence[Bounds]) -> Bounds:
        parts = [b for b in parts if len(b.footprint)]
        if not parts:
            return EMPTY
        ext = np.stack([b.extent for b in parts])
        return Bounds(
            np.stack([ext[:, 0].min(axis=0), ext[:, 1].max(axis=0)]),
            footprint_of(np.concatenate([b.footprint for b in parts])),
        )


# an empty box, as UsdGeom writes one for nothing to bound (min FLT_MAX, max -FLT_MAX)
EMPTY_EXTENT = np.array([[np.finfo(np.float32).max] * 3, [-np.finfo(np.float32).max] * 3])
EMPTY = Bounds(EMPTY_EXTENT, np.zeros((0, 2)))


def outward_f32(extents: np.ndarray) -> np.ndarray:
    """Extents ``(2 k, 3)`` (min, max pairs) as float32 rounded outward (each min down, each
    max up), so a stored box still holds what it bounds after the float64 -> float32 cast."""
    e = np.asarray(extents, dtype=np.float64).reshape(-1, 2, 3)
    f = e.astype(np.float32)
    lo = np.where(f[:, 0] > e[:, 0], np.nextafter(f[:, 0], np.float32(-np.inf)), f[:, 0])
    hi = np.where(f[:, 1] < e[:, 1], np.nextafter(f[:, 1], np.float32(np.inf)), f[:, 1])
    return np.stack([lo, hi], axis=1).reshape(-1, 3)


def instances_bounds(
    hulls: Sequence[np.ndarray],
    proto: np.ndarray,
    rows: np.ndarray,
    translate: np.ndarray,
) -> Bounds:
    """Bounds of instances: prototype ``proto[i]`` (convex hull vertices ``hulls[k]``) under
    the row-vector linear map ``rows[i] (3, 3)`` then ``translate[i]``.

    Only instances that can reach the boundary are transformed. Each instance is anchored at
    its hull's centroid (transformed), which lies inside its geometry, and every point of it
    lies within its reach (the hull's radius times the map's Frobenius norm, which bounds
    its largest singular value) of that anchor. The instances whose anchors are extreme are
    transformed first; their bounds lie inside the union's, so an instance whose anchor lies
    deeper than its own reach inside them (box and footprint) cannot move the union's
    bounds: of a 100k-leaf crown, 3 % are transformed. Worked in chunks so a million
    leaves never hold all their transformed points at once."""
    proto = np.asarray(proto)
    if len(proto) == 0:
        return EMPTY
    sizes = np.array([len(h) for h in hulls])
    if int(sizes[proto].sum()) <= SMALL:  # few enough that filtering costs more
        return _transformed(hulls, proto, rows, translate, np.arange(len(proto)))
    centre = np.array([h.mean(axis=0) if len(h) else np.zeros(3) for h in hulls])
    radius = np.array(
        [
            np.linalg.norm(h - c, axis=1).max() if len(h) else 0.0
            for h, c in zip(hulls, centre, strict=True)
        ]
    )
    anchor = np.einsum("nj,njk->nk", centre[proto], rows) + translate
    norm = np.sqrt(np.einsum("nij,nij->n", rows, rows))  # Frobenius >= largest singular value
    # and room for the rounding of the transformed points against their anchor's
    size = np.abs(centre[proto]).max(axis=1) + radius[proto]
    room = 8 * np.finfo(float).eps * (size * norm + np.abs(translate).max(axis=1))
    reach = norm * radius[proto] * (1 + 1e-9) + room
    seed = _extreme_anchors(anchor)
    inner = _transformed(hulls, proto, rows, translate, seed)
    keep = _may_reach_boundary(anchor, reach, inner)
    keep[seed] = False
    return Bounds.union([inner, _transformed(hulls, proto, rows, translate, np.flatnonzero(keep))])


def grouped_extents(
    hulls: Sequence[np.ndarray],
    proto: np.ndarray,
    rows: np.ndarray,
    translate: np.ndarray,
    group: np.ndarray,
    groups: int,
) -> np.ndarray:
    """``(groups, 2, 3)`` extents of the instances of each group (``group[i]`` in
    ``0 .. groups - 1``; -1: none), every hull vertex transformed as
    :func:`instances_bounds` transforms it (an empty group: :data:`EMPTY_EXTENT`). No
    footprints: one pass for all groups, however many. As there, only the instances that can
    reach their group's boundary are transformed: one whose anchor lies deeper than its
    reach inside the box of its group's anchors cannot move that group's extent."""
    lo = np.full((groups, 3), np.inf)
    hi = np.full((groups, 3), -np.inf)
    proto, group = np.asarray(proto), np.asarray(group)
    if len(proto) == 0:
        lo[:], hi[:] = EMPTY_EXTENT
        return np.stack([lo, hi], axis=1)
    centre = np.array([h.mean(axis=0) if len(h) else np.zeros(3) for h in hulls])
    radius = np.array(
        [
            np.linalg.norm(h - c, axis=1).max() if len(h) else 0.0
            for h, c in zip(hulls, centre, strict=True)
        ]
    )
    anchor = np.einsum("nj,njk->nk", centre[proto], rows) + translate
    norm = np.sqrt(np.einsum("nij,nij->n", rows, rows))
    size = np.abs(centre[proto]).max(axis=1) + radius[proto]
    room = 8 * np.finfo(float).eps * (size * norm + np.abs(translate).max(axis=1))
    reach = (norm * radius[proto] * (1 + 1e-9) + room)[:, None]
    mine = group >= 0
    a_lo, a_hi = lo.copy(), hi.copy()
    np.minimum.at(a_lo, group[mine], anchor[mine])
    np.maximum.at(a_hi, group[mine], anchor[mine])
    g = np.maximum(group, 0)
    edge = ((anchor - reach < a_lo[g]) | (anchor + reach > a_hi[g])).any(axis=1)
    for k, hull in enumerate(hulls):
        sel = np.flatnonzero((proto == k) & mine & edge)
        if len(sel) == 0 or len(hull) == 0:
            continue
        step = max(1, CHUNK // len(hull))
        for start in range(0, len(sel), step):
            i = sel[start : start + step]
            pts = exact.matmul(hull, rows[i]) + translate[i, None, :]
            np.minimum.at(lo, group[i], pts.min(axis=1))
            np.maximum.at(hi, group[i], pts.max(axis=1))
    empty = ~np.isfinite(lo[:, 0])
    lo[empty], hi[empty] = EMPTY_EXTENT
    return np.stack([lo, hi], axis=1)


def _transformed(
    hulls: Sequence[np.ndarray],
    proto: np.ndarray,
    rows: np.ndarray,
    translate: np.ndarray,
    which: np.ndarray,
) -> Bounds:
    """Bounds of the instances ``which``, every hull vertex transformed (up to ``CHUNK``
    points held at once, of every prototype: one footprint hull per batch, not per
    prototype)."""
    parts: list[Bounds] = []
    batch: list[np.ndarray] = []
    held = 0
    for k, hull in enumerate(hulls):
        sel = which[proto[which] == k]
        if len(sel) == 0 or len(hull) == 0:
            continue
        step = max(1, CHUNK // len(hull))
        for start in range(0, len(sel), step):
            i = sel[start : start + step]
            pts = np.einsum("cj,njk->nck", hull, rows[i]) + translate[i, None, :]
            batch.append(pts.reshape(-1, 3))
            held += len(batch[-1])
            if held >= CHUNK:
                parts.append(Bounds.of_points(np.concatenate(batch)))
                batch, held = [], 0
    if batch:
        parts.append(Bounds.of_points(np.concatenate(batch)))
    return parts[0] if len(parts) == 1 else Bounds.union(parts)


def _extreme_anchors(anchor: np.ndarray) -> np.ndarray:
    """Indices of the anchors extreme along x, y, z and the ground plane's diagonals and
    those on the hull of their x, y: their instances span most of the union's bounds."""
    keys = np.concatenate(
        [anchor, anchor[:, :1] + anchor[:, 1:2], anchor[:, 1:2] - anchor[:, :1]], 1
    )
    ext = np.concatenate([keys.argmin(axis=0), keys.argmax(axis=0)])
    ring, _ = _hull_indices(np.ascontiguousarray(anchor[:, :2]))
    return np.unique(np.concatenate([ext, ring]))


def _may_reach_boundary(origin: np.ndarray, reach: np.ndarray, inner: Bounds) -> np.ndarray:
    """Mask of the anchors within their ``reach`` of the boundary of ``inner`` (bounds that
    the union's hold): outside or near its box, or near its footprint's edges."""
    from scipy.spatial import ConvexHull, QhullError

    o = np.asarray(origin, dtype=np.float64)
    lo, hi = inner.extent
    keep = np.any((o - reach[:, None] <= lo) | (o + reach[:, None] >= hi), axis=1)
    if len(inner.footprint) < 3:
        keep[:] = True
        return keep
    try:
        eq = ConvexHull(inner.footprint).equations  # n . p + d <= 0 inside
    except QhullError:
        keep[:] = True
        return keep
    x, y = o[:, 0].copy(), o[:, 1].copy()
    depth = np.full(len(o), -np.inf)
    for a, b, c in eq:  # one edge at a time: (n, 2) @ (2, k) misses BLAS here, 20x slower
        np.maximum(depth, a * x + b * y + c, out=depth)
    return keep | (depth >= -reach)


def yawed_extent(
    footprints: Sequence[np.ndarray],
    z_ranges: np.ndarray,
    proto: np.ndarray,
    xy: np.ndarray,
    turn: tuple[np.ndarray, np.ndarray],
    scale: np.ndarray,
    base_z: np.ndarray,
) -> np.ndarray:
    """Exact extent ``(2, 3)`` of instances turned about Z by ``turn = (c, s)`` (x' = c x - s
    y, y' = s x + c y: the cosine and sine of the yaw, or what a stored quaternion makes of
    them), scaled uniformly by ``scale``, moved to ``xy`` and up to ``base_z``; prototype
    ``k`` has footprint ``footprints[k]`` and z range ``z_ranges[k] = (zmin, zmax)``."""
    if len(proto) == 0:
        return EMPTY_EXTENT.copy()
    c, s = turn
    # every turned, scaled footprint lies within its reach of its anchor (x, y): only the
    # instances within reach of the extent of the extreme ones can widen it
    radius = np.array([np.sqrt((f * f).sum(axis=1)).max() if len(f) else 0.0 for f in footprints])
    sc = np.abs(scale)
    room = 8 * np.finfo(float).eps * (radius[proto] * sc + np.abs(xy).max(axis=1))
    reach = radius[proto] * np.sqrt(c * c + s * s) * sc * (1 + 1e-9) + room
    seed = np.unique(np.concatenate([xy.argmin(axis=0), xy.argmax(axis=0)]))
    inner = _yawed(footprints, z_ranges, proto, xy, turn, scale, base_z, seed)
    near = (xy - reach[:, None] <= inner[0, :2]) | (xy + reach[:, None] >= inner[1, :2])
    near = np.flatnonzero(np.any(near, axis=1))
    rest = _yawed(footprints, z_ranges, proto, xy, turn, scale, base_z, near)
    z = np.asarray(z_ranges)[proto] * scale[:, None] + base_z[:, None]
    lo = np.minimum(inner[0], rest[0])
    hi = np.maximum(inner[1], rest[1])
    lo[2], hi[2] = z.min(), z.max()
    return np.stack([lo, hi])


def _yawed(footprints, z_ranges, proto, xy, turn, scale, base_z, which) -> np.ndarray:
    """:func:`yawed_extent` of the instances ``which``, every footprint vertex turned."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    c, s = turn
    for k, f in enumerate(footprints):
        sel = which[proto[which] == k]
        if len(sel) == 0:
            continue
        step = max(1, CHUNK // max(len(f), 1))
        for start in range(0, len(sel), step):
            i = sel[start : start + step]
            sc = scale[i, None]
            x = (c[i, None] * f[:, 0] - s[i, None] * f[:, 1]) * sc + xy[i, 0:1]
            y = (s[i, None] * f[:, 0] + c[i, None] * f[:, 1]) * sc + xy[i, 1:2]
            z = np.asarray(z_ranges[k])[None, :] * sc + base_z[i, None]
            lo = np.minimum(lo, [x.min(), y.min(), z.min()])
            hi = np.maximum(hi, [x.max(), y.max(), z.max()])
    return np.stack([lo, hi])
