"""Leaf shapes that turn in time (a windy forest's fluttering leaves), as the casters see them.

A leaf instance is its shape's triangles through the shape prim's own transform (its turn at
the scene's time, ``own``) and then the leaf's placement. Between two times only the turn
changes, so a caster built once can cast at another time by moving each ray, in the leaf's
frame, from the shape's space then into its space now (:func:`relative`): one small affine
per shape, not per leaf. Its bounding volumes must hold the leaf at every time: each turning
shape's box is taken over every turn the stage gives it (:func:`swept_boxes`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pxr import Usd


class Turns:
    """The own transforms of many prims in time (leaf shapes), each time-varying op read once
    for every prim that shares its samples (the few flutter classes a forest's thousands of
    leaf prototypes inherit).

    A prim's transform (row vectors, as :meth:`UsdGeom.Xformable.GetLocalTransformation`
    gives it) is ``inner @ op(t) @ outer``: the ops after its one time-varying op, that op at
    ``t``, the ops before it. A prim with more than one time-varying op is read whole."""

    def __init__(self, prims: list[Usd.Prim]):
        from pxr import Usd, UsdGeom

        n = len(prims)
        self.inner = np.tile(np.eye(4), (n, 1, 1))
        self.outer = np.tile(np.eye(4), (n, 1, 1))
        self.which = np.full(n, -1, np.int64)  # the varying op's index in ``_ops`` (-1: none)
        self._ops: list = []  # per distinct varying op: a representative XformOp, or a prim
        self._series: dict[int, np.ndarray] = {}
        self._whole: list[bool] = []  # per op in ``_ops``: a prim read whole
        keys: dict = {}
        # an op that does not vary has one value (a default, or a single sample)
        still = Usd.TimeCode.EarliestTime()
        for k, prim in enumerate(prims):
            if not prim:
                continue
            xf = UsdGeom.Xformable(prim)
            ops = xf.GetOrderedXformOps()
            varying = [i for i, op in enumerate(ops) if op.MightBeTimeVarying()]
            if not varying:
                self.outer[k] = np.asarray(xf.GetLocalTransformation(still), dtype=float)
                continue
            if len(varying) > 1:
                key = ("prim", str(prim.GetPath()))
                rep = xf
            else:
                i = varying[0]
                op = ops[i]
                key = (_samples_source(op.GetAttr()), str(op.GetOpType()), op.IsInverseOp())
                rep = op
                # row vectors: the transform is P_last @ ... @ P_0, each op's matrix P
                for o in ops[i + 1 :]:
                    self.inner[k] = np.asarray(o.GetOpTransform(still), dtype=float) @ self.inner[k]
                for o in ops[:i]:
                    self.outer[k] = np.asarray(o.GetOpTransform(still), dtype=float) @ self.outer[k]
            if key not in keys:
                keys[key] = len(self._ops)
                self._ops.append(rep)
                self._whole.append(len(varying) > 1)
            self.which[k] = keys[key]

    @property
    def moving(self) -> np.ndarray:
        """``bool[n]``: which prims turn in time."""
        return self.which >= 0

    def _op(self, j: int, time) -> np.ndarray:
        rep = self._ops[j]
        if self._whole[j]:
            return np.asarray(rep.GetLocalTransformation(time), dtype=float)
        return np.asarray(rep.GetOpTransform(time), dtype=float)

    def at(self, time) -> np.ndarray:
        """``(n, 4, 4)``: every prim's own transform at the ``Usd.TimeCode`` ``time``."""
        out = self.outer.copy()
        if self._ops:
            ops = np.array([self._op(j, time) for j in range(len(self._ops))])
            sel = np.flatnonzero(self.which >= 0)
            out[sel] = self.inner[sel] @ ops[self.which[sel]] @ self.outer[sel]
        return out

    def _op_series(self, j: int) -> np.ndarray:
        """``(s, 4, 4)``: varying op ``j`` at each of its time samples, in time order."""
        from pxr import Usd

        if j not in self._series:
            times = self._ops[j].GetTimeSamples()
            self._series[j] = np.array([self._op(j, Usd.TimeCode(t)) for t in times]).reshape(
                -1, 4, 4
            )
        return self._series[j]

    def series(self, k: int) -> np.ndarray:
        """``(s, 4, 4)``: prim ``k``'s own transform at each time sample of what turns it,
        in time order (none: ``(0, 4, 4)``)."""
        j = int(self.which[k])
        if j < 0:
            return np.zeros((0, 4, 4))
        return self.inner[k] @ self._op_series(j) @ self.outer[k]

    def sweeps(self, shapes: list, own: np.ndarray) -> np.ndarray:
        """``(n, 2, 3)``: each prim's shape (``shapes[k].triangles``) boxed over every turn,
        in its space at ``own[k]`` (:func:`swept_boxes`; a prim that does not turn: its
        box). Prims turned alike (the same op, the same ops about it, the same turn then)
        are boxed together, each distinct shape once."""
        out = np.array([s.box for s in shapes], dtype=float).reshape(-1, 2, 3)
        groups: dict = {}
        for k in np.flatnonzero(self.which >= 0):
            key = (int(self.which[k]), self.inner[k].tobytes(), self.outer[k].tobytes(),
                   own[k].tobytes())  # fmt: skip
            groups.setdefault(key, []).append(int(k))
        for members in groups.values():
            k0 = members[0]
            tri = [np.asarray(shapes[k].triangles, dtype=float) for k in members]
            distinct = {t.tobytes(): t for t in tri}
            boxes = swept_boxes(list(distinct.values()), own[k0], self.series(k0))
            index = {b: n for n, b in enumerate(distinct)}
            for k, t in zip(members, tri, strict=True):
                out[k] = boxes[index[t.tobytes()]]
        return out


def shape_turns(
    stage: Usd.Stage, keys: list[str], shapes: list, when
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Where leaf shape prims (at ``keys``, their triangles in ``shapes``) turn in time
    (flutter): every shape's own transform at the time code ``when`` and its box over all
    its turns (:meth:`Turns.sweeps`); ``(None, None)`` when none turns."""
    from usdforest.sensors.scene.stageframe import animated

    if not keys or not animated(stage):
        return None, None
    turns = Turns([stage.GetPrimAtPath(k) for k in keys])
    if not turns.moving.any():
        return None, None
    own = turns.at(when)
    return own, turns.sweeps(shapes, own)


def moving_parts(proto: Usd.Prim) -> list[str]:
    """The paths of the prims below ``proto`` whose transforms have time samples (its limbs
    that sway), none below another (leaf instancers, which turn their leaves, are not)."""
    from pxr import Usd, UsdGeom

    from usdforest.usd.layers import rendered

    found = []
    it = iter(Usd.PrimRange(proto))
    next(it)  # ``proto`` itself moves with its instance
    for q in it:
        if q.IsA(UsdGeom.PointInstancer) or not rendered(q):
            it.PruneChildren()
        elif UsdGeom.Xformable(q) and UsdGeom.Xformable(q).TransformMightBeTimeVarying():
            it.PruneChildren()
            found.append(str(q.GetPath()))
    return found


def _samples_source(attr) -> tuple[str, str]:
    """Where an attribute's time samples come from: the strongest spec that has any (its
    layer and path), so that prims inheriting one class share it."""
    for spec in attr.GetPropertyStack():
        if spec.layer.GetNumTimeSamplesForPath(spec.path):
            return spec.layer.identifier, str(spec.path)
    return "", str(attr.GetPath())


def swept_box(points: np.ndarray, own: np.ndarray, turns: np.ndarray) -> np.ndarray:
    """``(2, 3)``: the box, in a shape's space at its turn ``own``, of its ``points`` at every
    turn ``turns`` (its time samples, in time order) and in between them
    (:func:`swept_boxes` of one shape)."""
    return swept_boxes([points], own, turns)[0]


def swept_boxes(shapes: list[np.ndarray], own: np.ndarray, turns: np.ndarray) -> np.ndarray:
    """``(m, 2, 3)``: :func:`swept_box` of each point set in ``shapes``, all turned alike.

    USD interpolates a turn between two samples (a slerp of its rotation), so a point moves
    on an arc between the two places the samples put it: the arc leaves the chord by its
    sagitta, ``(c / 2) tan(theta / 4)`` for a chord ``c`` and a turn ``theta`` between the
    samples, which each box is grown by (the largest over its points and the samples)."""
    pts = [np.asarray(p, dtype=float).reshape(-1, 3) for p in shapes]
    out = np.zeros((len(pts), 2, 3))
    full = [k for k, p in enumerate(pts) if len(p)]
    for k in full:
        out[k] = [pts[k].min(axis=0), pts[k].max(axis=0)]
    if not len(turns) or not full:
        return out
    # a linear map's extremes over a point set lie on its hull
    hulls = [_hull(pts[k]) for k in full]
    starts = np.cumsum([0] + [len(h) for h in hulls[:-1]])
    cloud = np.concatenate(hulls)
    rel = turns @ np.linalg.inv(own)  # shape space at each sample -> shape space at ``own``
    lin = rel[:, :3, :3]
    lo = np.full((len(cloud), 3), np.inf)
    hi = np.full((len(cloud), 3), -np.inf)
    grow = np.zeros(len(cloud))
    if len(turns) > 1:
        # the turn between two samples: tr(R_a^T R_b) = s^2 (1 + 2 cos(theta)), each R a
        # rotation scaled by s (its rows have length s)
        sq = np.einsum("kj,kj->k", lin[:, 0], lin[:, 0])
        cos = (np.einsum("kij,kij->k", lin[:-1], lin[1:]) / np.sqrt(sq[:-1] * sq[1:]) - 1) / 2
        factor = np.tan(np.arccos(np.clip(cos, -1.0, 1.0)) / 4) / 2
    chunk = max(1, 2_000_000 // (3 * len(cloud)))
    for a in range(0, len(turns), chunk):
        b = min(len(turns), a + chunk + 1)  # one sample more: the chord to the next chunk
        moved = np.matmul(cloud[None], lin[a:b]) + rel[a:b, None, 3, :3]
        lo = np.minimum(lo, moved.min(axis=0))
        hi = np.maximum(hi, moved.max(axis=0))
        if b - a > 1:
            step = moved[1:] - moved[:-1]
            chord = np.sqrt(np.einsum("kpj,kpj->kp", step, step))
            grow = np.maximum(grow, (chord * factor[a : b - 1, None]).max(axis=0))
    lo -= grow[:, None]
    hi += grow[:, None]
    out[full, 0] = np.minimum(out[full, 0], np.minimum.reduceat(lo, starts, axis=0))
    out[full, 1] = np.maximum(out[full, 1], np.maximum.reduceat(hi, starts, axis=0))
    return out


def relative(own: np.ndarray, now: np.ndarray) -> np.ndarray | None:
    """``(shapes, 12)`` float32: per shape, the affine (column form, a 3x3 row-major then a
    shift) from its space at its turn ``own`` to its space at its turn ``now`` (both
    ``(shapes, 4, 4)``, row vectors), which a ray met in the former is moved by to meet the
    shape as it stands now; ``None`` when no shape has turned."""
    own = np.asarray(own, dtype=float)
    now = np.asarray(now, dtype=float)
    if own.shape != now.shape or np.array_equal(own, now):
        return None
    # a point x of the shape now sits at x @ now @ own^-1 in the space at ``own``: a ray
    # there is moved to the shape now by the inverse, own @ now^-1 (row vectors)
    m = own @ np.linalg.inv(now)
    out = np.empty((len(m), 12), np.float32)
    out[:, :9] = m[:, :3, :3].transpose(0, 2, 1).reshape(-1, 9)
    out[:, 9:] = m[:, 3, :3]
    return out


def _hull(pts: np.ndarray) -> np.ndarray:
    """The vertices of the convex hull of ``pts`` (n, 3) (all distinct points where they span
    no volume: a flat leaf)."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.unique(pts, axis=0)
    if len(pts) <= 8:
        return pts
    try:
        return pts[ConvexHull(pts).vertices]
    except QhullError:  # flat or degenerate: the hull of its plane's points is not worth it
        return pts
