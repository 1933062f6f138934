"""Wood as finite cylinders: the sonar's trunk and branch reflectors, fitted to the stage's
own wood triangles.

Every wood prim (triangles labelled trunk or branch, grouped by prim path) is cut along its
principal axis into segments no longer than ``segment`` metres. Each segment becomes one
cylinder fitted to points spread over the prim's side wall: a circle through them in the plane
across the principal axis gives its centre and radius (so a bent branch keeps its bend). A
prim's consecutive segments make a chain (``Cylinders.joined``): a polyline through the
midpoints between their centres, each piece starting where the one before it ends, its free
ends on the prim's own end caps, so the sonar hears the prim's wall whole however it was cut
(:mod:`usdforest.sensors.sonar.backscatter`). A slice whose points do not lie on a circle (rms
misfit over 15 % of the radius: the two limbs of a fork in one prim, a stump cut across its
axis) is left out rather than fitted as a phantom cylinder. Nothing here depends on how the
tree was made: L-system trees, whole-tree CAD decompositions and a user's own meshes are
fitted alike.

Tree prototypes are fitted once in their own space and placed by each instance's transform.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usdforest.meshes import triangle_components
from usdforest.runs import run_starts
from usdforest.sensors.scene.scenetypes import CLASS_ID, Scene

WOOD = (CLASS_ID["trunk"], CLASS_ID["branch"], CLASS_ID["dead_wood"])
MAX_MISFIT = 0.15  # a slice's rms distance from its circle, as a share of the radius


@dataclass(frozen=True, eq=False)
class Cylinders:
    """Finite cylinders: centre (n, 3), unit axis (n, 3), length, radius (n,) in metres,
    class (trunk, branch or dead wood), tree id (-1: none), ``joined`` (n,): this piece
    continues the one before it in the arrays (one wood prim's chain of pieces, each
    starting where the one before it ends; default none) and ``carrier`` (n,): the index of
    the scene's instance that placed it (-1, the default: none, or found by its tree id)."""

    centre: np.ndarray
    axis: np.ndarray
    length: np.ndarray
    radius: np.ndarray
    cls: np.ndarray
    tree: np.ndarray
    joined: np.ndarray | None = None
    carrier: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.joined is None:
            object.__setattr__(self, "joined", np.zeros(len(self.radius), bool))
        if self.carrier is None:
            object.__setattr__(self, "carrier", np.full(len(self.radius), -1, np.int64))
        sizes = {f: len(getattr(self, f)) for f in _FIELDS}
        if len(set(sizes.values())) > 1:  # every field one row per cylinder
            raise ValueError(f"Cylinders: fields of different lengths {sizes}")

    def __len__(self) -> int:
        return int(self.centre.shape[0])

    def take(self, sel: np.ndarray) -> Cylinders:
        """The cylinders ``sel`` (indices, ascending, or a mask); a piece stays joined where
        the one before it is taken too."""
        sel = np.flatnonzero(sel) if np.asarray(sel).dtype == bool else np.asarray(sel, np.int64)
        joined = self.joined[sel] & np.r_[False, np.diff(sel) == 1]
        return Cylinders(*(getattr(self, f)[sel] for f in _FIELDS[:6]), joined, self.carrier[sel])

    @staticmethod
    def concat(parts: list[Cylinders]) -> Cylinders:
        if not parts:
            return Cylinders(
                np.zeros((0, 3)),
                np.zeros((0, 3)),
                np.zeros(0),
                np.zeros(0),
                np.zeros(0, np.uint8),
                np.zeros(0, np.int64),
                np.zeros(0, bool),
                np.zeros(0, np.int64),
            )
        return Cylinders(*(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS))

    def placed(
        self, m: np.ndarray, tree: np.ndarray, carrier: np.ndarray | None = None
    ) -> Cylinders:
        """Copies placed by row-vector 4x4 transforms ``m (n, 4, 4)``, one per tree id in
        ``tree (n,)`` and, where given, scene instance in ``carrier (n,)`` (a uniform scale
        assumed for the radius)."""
        rot = m[:, :3, :3]
        axis = np.einsum("cj,njk->nck", self.axis, rot)
        stretch = np.linalg.norm(axis, axis=2)
        scale = np.cbrt(np.abs(np.linalg.det(rot)))
        n, c = len(m), len(self)
        return Cylinders(
            (np.einsum("cj,njk->nck", self.centre, rot) + m[:, None, 3, :3]).reshape(-1, 3),
            (axis / np.maximum(stretch, 1e-12)[..., None]).reshape(-1, 3),
            (self.length[None, :] * stretch).ravel(),
            (self.radius[None, :] * scale[:, None]).ravel(),
            np.tile(self.cls, n),
            np.repeat(np.asarray(tree, np.int64), c),
            np.tile(self.joined, n),
            None if carrier is None else np.repeat(np.asarray(carrier, np.int64), c),
        )


_FIELDS = ("centre", "axis", "length", "radius", "cls", "tree", "joined", "carrier")


def fit_cylinders(
    triangles: np.ndarray,
    cls: np.ndarray,
    path: np.ndarray,
    tree: np.ndarray,
    segment: float,
) -> Cylinders:
    """Cylinders of every wood prim among ``triangles (m, 3, 3)`` (see the module docstring),
    in prim path order and along each prim's axis.

    ``cls``, ``path`` and ``tree`` label each triangle; segments are at most ``segment`` m.
    All prims are fitted together in flat arrays (per-prim sums by ``np.bincount``, one
    batched eigen-decomposition and one batched solve): an allometric spruce has thousands of
    wood prims."""
    wood = np.flatnonzero(np.isin(cls, WOOD))
    order = wood[np.argsort(path[wood], kind="stable")]  # each prim's triangles in turn
    _, first, per_prim = np.unique(path[order], return_index=True, return_counts=True)
    tri_prim = np.repeat(np.arange(len(first)), per_prim)
    v, normal, owner = surface_points(
        triangles[order].astype(np.float64), segment / 4, group=tri_prim
    )
    pp = tri_prim[owner]
    keep = np.bincount(pp, minlength=len(first)) >= 4
    sel = keep[pp]
    first = first[keep]
    v, normal, pp = v[sel], normal[sel], (np.cumsum(keep) - 1)[pp[sel]]
    return _fit_prims(v, normal, pp, segment, cls[order[first]], tree[order[first]])


def surface_points(
    tri: np.ndarray, spacing: float, group: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points spread over each triangle of ``tri (m, 3, 3)``, about one per ``spacing^2`` of
    its area and at least its centroid (an R2 low-discrepancy pattern, one running sequence
    per ``group`` of consecutive triangles, default one for all: the same points every run,
    no two triangles alike), their triangles' unit normals and the triangle of each point.
    A long side face of a low-poly tube still covers every segment it spans."""
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    n = np.maximum(np.ceil(area / spacing**2).astype(np.int64), 1)
    owner = np.repeat(np.arange(len(tri)), n)
    i = np.arange(n.sum())
    if group is not None and len(tri):
        starts = run_starts(group)
        tri_start = np.cumsum(n) - n
        i -= np.repeat(tri_start[starts], np.diff(np.r_[tri_start[starts], n.sum()]))
    g = 1.32471795724474602596  # the plastic number: R2's generator
    u, w = (0.5 + i / g) % 1.0, (0.5 + i / g**2) % 1.0
    fold = u + w > 1
    u[fold], w[fold] = 1 - u[fold], 1 - w[fold]
    single = n[owner] == 1
    u[single] = w[single] = 1 / 3
    t = tri[owner]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])
    normal = cross / np.maximum(2 * area, 1e-300)[:, None]
    return points, normal[owner], owner


def _sums(index: np.ndarray, columns: tuple[np.ndarray, ...], size: int) -> np.ndarray:
    """``(size, len(columns))``: each column summed per ``index``."""
    return np.stack([np.bincount(index, c, minlength=size) for c in columns], -1)


def _fit_prims(
    v: np.ndarray, normal: np.ndarray, pp: np.ndarray, segment: float, cls, tree
) -> Cylinders:
    """Cylinders of the prims ``0..P-1`` whose surface points ``v`` (sorted by prim ``pp``)
    and normals are given."""
    P = len(cls)
    cnt = np.bincount(pp, minlength=P).astype(np.float64)
    mean = _sums(pp, tuple(v.T), P) / np.maximum(cnt, 1)[:, None]
    d = v - mean[pp]
    # the principal axes: eigenvectors of the points' scatter, largest first
    scatter = np.stack(
        [_sums(pp, tuple(d[:, i] * d[:, j] for j in range(3)), P) for i in range(3)], 1
    )
    vecs = np.linalg.eigh(scatter)[1]
    axis, e1, e2 = vecs[..., 2], vecs[..., 1], vecs[..., 0]
    # a sign LAPACK does not choose: each axis's largest component positive (trunks upward)
    flip = np.take_along_axis(axis, np.abs(axis).argmax(axis=1)[:, None], 1) < 0
    axis = np.where(flip, -axis, axis)
    t = np.einsum("nk,nk->n", d, axis[pp])
    starts = run_starts(pp)
    lo = np.minimum.reduceat(t, starts) if len(pp) else np.zeros(0)
    span = (np.maximum.reduceat(t, starts) if len(pp) else np.zeros(0)) - lo
    n = np.maximum(1, np.ceil(span / segment * (1 - 1e-6)).astype(np.int64))  # float32: 2.0000001
    step = np.where(span > 0, span / n, 1.0)
    # end caps (faces across the axis) are no part of the side wall a circle is fitted to
    offset = np.cumsum(n) - n
    # every prim's slices in one numbering
    every = offset[pp] + np.minimum(((t - lo[pp]) / step[pp]).astype(np.int64), n[pp] - 1)
    ends = (mean[pp] + d, every)  # all points, caps too: where a chain's free ends lie
    side = np.abs(np.einsum("nk,nk->n", normal, axis[pp])) < 0.7
    d, t, pp, gb = d[side], t[side], pp[side], every[side]
    S = int(n.sum())
    count = np.bincount(gb, minlength=S)
    used = np.flatnonzero(count >= 3)
    sp = np.repeat(np.arange(P), n)[used]  # each used slice's prim
    # a circle through each slice's points in the plane across the axis (Kasa's algebraic
    # fit: x^2 + y^2 = A x + B y + C by least squares), exact for points on a circle however
    # unevenly they are spread round it
    x = np.einsum("nk,nk->n", d, e1[pp])
    y = np.einsum("nk,nk->n", d, e2[pp])
    rhs = x * x + y * y
    cols = (x, y, np.ones_like(x))
    normal_eq = np.stack([_sums(gb, tuple(p * q for q in cols), S) for p in cols], -2)[used]
    target = _sums(gb, tuple(p * rhs for p in cols), S)[used]
    ok = np.abs(np.linalg.det(normal_eq)) > 1e-30
    sol = np.zeros((len(used), 3))
    sol[ok] = np.linalg.solve(normal_eq[ok], target[ok][..., None])[..., 0]
    cx, cy = sol[:, 0] / 2, sol[:, 1] / 2
    radius = np.sqrt(np.maximum(sol[:, 2] + cx * cx + cy * cy, 0.0))
    mid = lo[sp] + (used - offset[sp] + 0.5) * step[sp]
    centre = mean[sp] + mid[:, None] * axis[sp] + cx[:, None] * e1[sp] + cy[:, None] * e2[sp]
    local = _gradient(centre, mid, sp, axis)
    # a slice of a bend is slanted: its length along its own axis is longer
    length = step[sp] / np.maximum(np.abs(np.einsum("nk,nk->n", local, axis[sp])), 0.5)
    # a slice that is no circle (a fork's two limbs, a stump cut across) is no cylinder: the
    # points' rms distance from the fitted circle must stay within MAX_MISFIT of its radius
    slot = np.full(S, -1)
    slot[used] = np.arange(len(used))
    k = slot[gb]
    inside = k >= 0
    k = k[inside]
    miss = np.hypot(x[inside] - cx[k], y[inside] - cy[k]) - radius[k]
    rms = np.sqrt(np.bincount(k, miss * miss, minlength=len(used)) / count[used])
    ok &= (radius > 1e-4) & (radius < span[sp] + step[sp]) & (rms <= MAX_MISFIT * radius)
    keep = np.flatnonzero(ok)
    # consecutive slices of one prim make a chain: a polyline through the midpoints between
    # their centres, so that each piece starts exactly where the one before it ends
    slice_no = used[keep] - offset[sp[keep]]
    # (sliced: no piece at all must give no flag)
    joined = np.r_[False, (np.diff(sp[keep]) == 0) & (np.diff(slice_no) == 1)][: len(slice_no)]
    start, end = _polyline(centre[keep], local[keep] * length[keep, None], joined)
    start, end = _free_ends(start, end, joined, used[keep], S, *ends)
    axis_v = end - start
    seg_len = np.linalg.norm(axis_v, axis=1)
    return Cylinders(
        (start + end) / 2,
        axis_v / np.maximum(seg_len, 1e-12)[:, None],
        seg_len,
        radius[keep],
        np.asarray(cls, np.uint8)[sp[keep]],
        np.asarray(tree, np.int64)[sp[keep]],
        joined,
    )


def _polyline(
    centre: np.ndarray, span: np.ndarray, joined: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Start and end of each piece of the chains through ``centre`` (``joined``: a piece
    continues the one before it): a joint halfway between two centres, a chain's free end as
    far beyond its last centre as the joint before it (a lone piece: its centre -+ ``span``
    / 2, ``span`` its axis times its length)."""
    nxt = np.r_[joined[1:], False]
    mid = (centre[:-1] + centre[1:]) / 2  # between piece i and i + 1
    start = centre - span / 2
    end = centre + span / 2
    i = np.flatnonzero(joined)
    start[i] = mid[i - 1]
    i = np.flatnonzero(nxt)
    end[i] = mid[i]
    i = np.flatnonzero(joined & ~nxt)  # a chain's last piece
    end[i] = 2 * centre[i] - start[i]
    i = np.flatnonzero(nxt & ~joined)  # a chain's first piece
    start[i] = 2 * centre[i] - end[i]
    return start, end


def _free_ends(
    start: np.ndarray,
    end: np.ndarray,
    joined: np.ndarray,
    slice_of: np.ndarray,
    n_slices: int,
    points: np.ndarray,
    point_slice: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Each chain's free ends moved along its end pieces to the furthest of their slices'
    ``points`` (a prim's end cap lies across its own axis, not across the principal axis it
    was sliced along, which a handful of sampled points tilts by a few mrad)."""
    piece = np.full(n_slices, -1)
    piece[slice_of] = np.arange(len(slice_of))
    pc = piece[point_slice]
    on = pc >= 0
    pc, points = pc[on], points[on]
    axis = end - start
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    first = ~joined
    last = ~np.r_[joined[1:], False]
    lo = np.full(len(start), np.inf)
    hi = np.full(len(start), -np.inf)
    np.minimum.at(lo, pc, np.einsum("nk,nk->n", points - start[pc], axis[pc]))
    np.maximum.at(hi, pc, np.einsum("nk,nk->n", points - end[pc], axis[pc]))
    start = start + np.where(first & np.isfinite(lo), lo, 0.0)[:, None] * axis
    end = end + np.where(last & np.isfinite(hi), hi, 0.0)[:, None] * axis
    return start, end


def _gradient(centre: np.ndarray, mid: np.ndarray, sp: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Unit tangents along each prim's run of slice centres (``np.gradient`` per prim:
    second-order inside, one-sided at the ends); a prim's only slice takes the prim's axis."""
    m = len(sp)
    out = axis[sp].copy()
    if m < 2:
        return out
    first = np.r_[True, sp[1:] != sp[:-1]]
    last = np.r_[sp[1:] != sp[:-1], True]
    alone = first & last
    head = first & ~alone
    tail = last & ~alone
    inner = ~first & ~last
    i = np.flatnonzero(head)
    out[i] = (centre[i + 1] - centre[i]) / (mid[i + 1] - mid[i])[:, None]
    i = np.flatnonzero(tail)
    out[i] = (centre[i] - centre[i - 1]) / (mid[i] - mid[i - 1])[:, None]
    i = np.flatnonzero(inner)
    h1, h2 = (mid[i] - mid[i - 1])[:, None], (mid[i + 1] - mid[i])[:, None]
    out[i] = (
        -h2 / (h1 * (h1 + h2)) * centre[i - 1]
        + (h2 - h1) / (h1 * h2) * centre[i]
        + h1 / (h2 * (h1 + h2)) * centre[i + 1]
    )
    moved = ~alone
    out[moved] /= np.maximum(np.linalg.norm(out[moved], axis=1, keepdims=True), 1e-12)
    return out


def scene_cylinders(scene: Scene, segment: float, trees: np.ndarray | None = None) -> Cylinders:
    """Every wood cylinder of ``scene``: its own triangles' and each tree instance's (the
    prototype fitted once, then placed); only the instances ``trees`` (a boolean per
    instance) says, where given."""
    path = scene.path
    dead = np.flatnonzero(scene.cls == CLASS_ID["dead_wood"])
    if dead.size:  # instances copied into one prim path each: one fit per piece
        path = path.astype(np.int64).copy()
        path[dead] = int(path.max()) + 1 + triangle_components(scene.triangles[dead])
    parts = [fit_cylinders(scene.triangles, scene.cls, path, scene.tree, segment)]
    inst = scene.instances
    for k, proto in enumerate(scene.protos):
        which = np.flatnonzero((inst.proto == k) & (True if trees is None else trees))
        if which.size == 0:
            continue
        local = fit_cylinders(
            proto.triangles, proto.cls, proto.path, np.full(len(proto.cls), -1), segment
        )
        parts.append(local.placed(inst.matrix[which], inst.tree[which], which))
    return Cylinders.concat(parts)
