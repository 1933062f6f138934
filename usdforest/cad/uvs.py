"""Texture coordinates for template parts (``primvars:st``).

Wood: ``u`` goes once around the part's measured centreline (0 at +X, counter-clockwise seen
from the tip), ``v`` runs along the growth axis (0 at the base, 1 at the tip), so a bark
texture wraps round the stem and tiles along it. Leaves: ``u`` along the blade (+X, 0 at the
attachment, 1 at the far end), ``v`` across it (+Y, 0 to 1 over the blade's width).

Wood coordinates are face-varying: a triangle that straddles the seam at ``u = 0`` gets
``u + 1`` on its corners below the seam, so no triangle stretches across the whole texture,
and a corner on the axis (the centre of an end cap, whose angle means nothing) takes the mean
``u`` of its triangle's other corners.
"""

from __future__ import annotations

import numpy as np

from usdforest.grow import exact
from usdforest.grow.placement import centreline_of


def wood_uvs(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(3 F, 2)`` face-varying coordinates of a tube-like part in its unit frame."""
    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    line = centreline_of(p)
    z = np.clip(p[:, 2], 0.0, 1.0)
    heights = np.linspace(0.0, 1.0, len(line))
    cx = np.interp(z, heights, line[:, 0])
    cy = np.interp(z, heights, line[:, 1])
    dx, dy = p[:, 0] - cx, p[:, 1] - cy
    u = np.mod(exact.arctan2(dy, dx) / (2 * np.pi), 1.0)
    r = np.hypot(dx, dy)[f]
    rim = r >= 0.1 * r.max(axis=1, keepdims=True)
    cu = u[f]
    lo = np.where(rim, cu, np.inf).min(axis=1, keepdims=True)
    hi = np.where(rim, cu, -np.inf).max(axis=1, keepdims=True)
    cu = np.where((hi - lo > 0.5) & (cu < 0.5), cu + 1.0, cu)
    n = np.maximum(rim.sum(axis=1, keepdims=True), 1)
    centre = np.where(rim, cu, 0.0).sum(axis=1, keepdims=True) / n
    cu = np.where(rim, cu, centre)
    return np.stack([cu.ravel(), z[f].ravel()], axis=1)


def leaf_uvs(points: np.ndarray) -> np.ndarray:
    """``(V, 2)`` per-vertex coordinates of a leaf blade: its x, y bounds mapped onto [0, 1]."""
    p = np.asarray(points, dtype=np.float64)[:, :2]
    lo, hi = p.min(axis=0), p.max(axis=0)
    return (p - lo) / np.maximum(hi - lo, 1e-12)
