"""Wood as finite cylinders: the sonar's trunk and branch reflectors, fitted to the stage's
own wood triangles.

Every wood prim (triangles labelled trunk or branch, grouped by prim path) is cut along its
principal axis into segments no longer than ``segment`` metres. Each segment becomes one
cylinder fitted to points spread over the prim's side wall: a circle through them in the plane
across the principal axis gives its centre and radius (so a bent branch keeps its bend), and
its own axis joins its neighbours' centres. A slice whose points do not lie on a circle (rms
misfit over 15 % of the radius: the two limbs of a fork in one prim, a stump cut across its
axis) is left out rather than fitted as a phantom cylinder. Nothing here depends on how the
tree was made: L-system trees, whole-tree CAD decompositions and a user's own meshes are
fitted alike.

Tree prototypes are fitted once in their own space and placed by each instance's transform.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene import CLASS_ID, Scene

WOOD = (CLASS_ID["trunk"], CLASS_ID["branch"])
MAX_MISFIT = 0.15  # a slice's rms distance from its circle, as a share of the radius


@dataclass(frozen=True, eq=False)
class Cylinders:
    """Finite cylinders: centre (n, 3), unit axis (n, 3), length, radius (n,) in metres,
    class (trunk or branch) and tree id (-1: none)."""

    centre: np.ndarray
    axis: np.ndarray
    length: np.ndarray
    radius: np.ndarray
    cls: np.ndarray
    tree: np.ndarray

    def __len__(self) -> int:
        return int(self.centre.shape[0])

    def take(self, sel: np.ndarray) -> Cylinders:
        return Cylinders(*(getattr(self, f)[sel] for f in _FIELDS))

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
            )
        return Cylinders(*(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS))

    def placed(self, m: np.ndarray, tree: np.ndarray) -> Cylinders:
        """Copies placed by row-vector 4x4 transforms ``m (n, 4, 4)``, one per tree id in
        ``tree (n,)`` (a uniform scale assumed for the radius)."""
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
        )


_FIELDS = ("centre", "axis", "length", "radius", "cls", "tree")


def fit_cylinders(
    triangles: np.ndarray,
    cls: np.ndarray,
    path: np.ndarray,
    tree: np.ndarray,
    segment: float,
) -> Cylinders:
    """Cylinders of every wood prim among ``triangles (m, 3, 3)`` (see the module docstring).

    ``cls``, ``path`` and ``tree`` label each triangle; segments are at most ``segment`` m."""
    wood = np.flatnonzero(np.isin(cls, WOOD))
    parts = []
    for p in np.unique(path[wood]):
        sel = wood[path[wood] == p]
        v, normal = surface_points(triangles[sel].astype(np.float64), segment / 4)
        if len(v) >= 4:
            parts.append(_fit_prim(v, normal, segment, int(cls[sel[0]]), int(tree[sel[0]])))
    return Cylinders.concat(parts)


def surface_points(tri: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points spread over each triangle of ``tri (m, 3, 3)``, about one per ``spacing^2`` of
    its area and at least its centroid (an R2 low-discrepancy pattern, one running sequence:
    the same points every run, no two triangles alike), with their triangles' unit normals.
    A long side face of a low-poly tube still covers every segment it spans."""
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    n = np.maximum(np.ceil(area / spacing**2).astype(np.int64), 1)
    owner = np.repeat(np.arange(len(tri)), n)
    i = np.arange(n.sum())
    g = 1.32471795724474602596  # the plastic number: R2's generator
    u, w = (0.5 + i / g) % 1.0, (0.5 + i / g**2) % 1.0
    fold = u + w > 1
    u[fold], w[fold] = 1 - u[fold], 1 - w[fold]
    single = n[owner] == 1
    u[single] = w[single] = 1 / 3
    t = tri[owner]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])
    normal = cross / np.maximum(2 * area, 1e-300)[:, None]
    return points, normal[owner]


def _fit_prim(v: np.ndarray, normal: np.ndarray, segment: float, cls: int, tree: int) -> Cylinders:
    mean = v.mean(axis=0)
    _, _, vt = np.linalg.svd(v - mean, full_matrices=False)
    axis, e1, e2 = vt
    t = (v - mean) @ axis
    lo, span = float(t.min()), float(t.max() - t.min())
    n = max(1, int(np.ceil(span / segment * (1 - 1e-6))))  # float32 meshes: 2.0000001 m
    step = span / n if span > 0 else 1.0
    # end caps (faces across the axis) are no part of the side wall a circle is fitted to
    side = np.abs(normal @ axis) < 0.7
    v, t = v[side], t[side]
    b = np.minimum(((t - lo) / step).astype(np.int64), n - 1)
    count = np.bincount(b, minlength=n)
    used = np.flatnonzero(count >= 3)
    # a circle through each slice's points in the plane across the axis (Kasa's algebraic
    # fit: x^2 + y^2 = A x + B y + C by least squares), exact for points on a circle however
    # unevenly they are spread round it
    x, y = (v - mean) @ e1, (v - mean) @ e2
    rhs = x * x + y * y
    cols = (x, y, np.ones_like(x))
    normal_eq = np.stack(
        [np.stack([np.bincount(b, p * q, minlength=n) for q in cols], -1) for p in cols], -2
    )[used]
    target = np.stack([np.bincount(b, p * rhs, minlength=n) for p in cols], -1)[used]
    ok = np.abs(np.linalg.det(normal_eq)) > 1e-30
    sol = np.zeros((len(used), 3))
    sol[ok] = np.linalg.solve(normal_eq[ok], target[ok][..., None])[..., 0]
    cx, cy = sol[:, 0] / 2, sol[:, 1] / 2
    radius = np.sqrt(np.maximum(sol[:, 2] + cx * cx + cy * cy, 0.0))
    mid = lo + (used + 0.5) * step
    centre = mean + np.outer(mid, axis) + np.outer(cx, e1) + np.outer(cy, e2)
    if len(used) > 1:
        local = np.gradient(centre, mid, axis=0)
        local /= np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-12)
    else:
        local = axis[None, :]
    # a slice of a bend is slanted: its length along its own axis is longer
    length = step / np.maximum(np.abs(local @ axis), 0.5)
    # a slice that is no circle (a fork's two limbs, a stump cut across) is no cylinder: the
    # points' rms distance from the fitted circle must stay within MAX_MISFIT of its radius
    slot = np.full(n, -1)
    slot[used] = np.arange(len(used))
    k = slot[b]
    inside = k >= 0
    miss = np.hypot(x[inside] - cx[k[inside]], y[inside] - cy[k[inside]]) - radius[k[inside]]
    rms = np.sqrt(np.bincount(k[inside], miss * miss, minlength=len(used)) / count[used])
    ok &= (radius > 1e-4) & (radius < span + step) & (rms <= MAX_MISFIT * radius)
    m = int(ok.sum())
    return Cylinders(
        centre[ok],
        local[ok],
        length[ok],
        radius[ok],
        np.full(m, cls, np.uint8),
        np.full(m, tree, np.int64),
    )


def scene_cylinders(scene: Scene, segment: float) -> Cylinders:
    """Every wood cylinder of ``scene``: its own triangles' and each tree instance's (the
    prototype fitted once, then placed)."""
    parts = [fit_cylinders(scene.triangles, scene.cls, scene.path, scene.tree, segment)]
    inst = scene.instances
    for k, proto in enumerate(scene.protos):
        which = np.flatnonzero(inst.proto == k)
        if which.size == 0:
            continue
        local = fit_cylinders(
            proto.triangles, proto.cls, proto.path, np.full(len(proto.cls), -1), segment
        )
        parts.append(local.placed(inst.matrix[which], inst.tree[which]))
    return Cylinders.concat(parts)
