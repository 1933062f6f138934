"""Implicit UsdGeom shapes (Cube, Sphere, Cylinder, Capsule, Cone, Plane) as triangles, so a
simulation stage's own objects are in the sensor scene.

Each shape is tessellated with trimesh's primitives, finely enough that no point of the
triangles is more than ``TOLERANCE`` from the analytic surface (chord error), within a
triangle budget per shape. Shapes follow their ``axis`` attribute (the primitives are built
along Z and turned by a cyclic permutation of the coordinates, which keeps the winding).
"""

from __future__ import annotations

import math

import numpy as np

TOLERANCE = 2e-4  # metres between a tessellated and an analytic surface
MAX_SECTIONS = 2048  # around a circle
MAX_SUBDIVISIONS = 7  # of an icosphere (327,680 triangles)

IMPLICIT = ("Cube", "Sphere", "Cylinder", "Capsule", "Cone", "Plane")
_TO_AXIS = {"Z": [0, 1, 2], "X": [2, 0, 1], "Y": [1, 2, 0]}  # new coordinates from old


def _sections(radius: float) -> int:
    """Segments around a circle of ``radius`` whose chords stay within ``TOLERANCE``."""
    if radius <= TOLERANCE:
        return 8
    n = math.pi / math.acos(1 - TOLERANCE / radius)
    return int(min(max(8, math.ceil(n)), MAX_SECTIONS))


def _subdivisions(radius: float) -> int:
    """Icosphere subdivisions whose chords stay within ``TOLERANCE``: an icosahedron's edge
    subtends about 1.1 rad, halved by each subdivision."""
    for s in range(MAX_SUBDIVISIONS + 1):
        angle = 1.1071 / 2**s
        if radius * (1 - math.cos(angle / 2)) <= TOLERANCE:
            return s
    return MAX_SUBDIVISIONS


def shape_triangles(prim) -> np.ndarray | None:
    """``(m, 3, 3)`` triangles of an implicit shape in its own space, or None when ``prim`` is
    not one of :data:`IMPLICIT` (or has no extent to draw)."""
    import trimesh

    kind = prim.GetTypeName()
    if kind not in IMPLICIT:
        return None

    def get(name: str, default: float) -> float:
        a = prim.GetAttribute(name)
        v = a.Get() if a else None
        return float(default if v is None else v)

    axis_attr = prim.GetAttribute("axis")
    axis = str(axis_attr.Get()) if axis_attr and axis_attr.Get() else "Z"
    if kind == "Cube":
        s = get("size", 2.0)
        mesh = trimesh.creation.box(extents=[s, s, s])
    elif kind == "Sphere":
        r = get("radius", 1.0)
        mesh = trimesh.creation.icosphere(subdivisions=_subdivisions(r), radius=r)
    elif kind == "Cylinder":
        r, h = get("radius", 1.0), get("height", 2.0)
        mesh = trimesh.creation.cylinder(radius=r, height=h, sections=_sections(r))
    elif kind == "Capsule":
        r, h = get("radius", 0.5), get("height", 1.0)
        n = _sections(r)
        mesh = trimesh.creation.capsule(height=h, radius=r, count=[n, max(8, n // 2)])
    elif kind == "Cone":
        r, h = get("radius", 1.0), get("height", 2.0)
        mesh = trimesh.creation.cone(radius=r, height=h, sections=_sections(r))
        mesh.apply_translation([0.0, 0.0, -h / 2])  # USD centres the cone on its axis
    else:
        return _plane(get("width", 2.0), get("length", 2.0), axis)
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    return tri[..., _TO_AXIS.get(axis, _TO_AXIS["Z"])] if len(tri) else None


def _plane(width: float, length: float, axis: str) -> np.ndarray:
    """UsdGeomPlane: width along x (z when the axis is X), length along y (z when the axis
    is Y), facing +axis."""
    u, v = np.array([-0.5, 0.5, 0.5, -0.5]), np.array([-0.5, -0.5, 0.5, 0.5])
    zero = np.zeros(4)
    if axis == "X":
        pts = np.stack([zero, v * length, u * width], axis=1)
        quad = [[0, 3, 2], [0, 2, 1]]  # (y, z) counter-clockwise seen from +X
    elif axis == "Y":
        pts = np.stack([u * width, zero, v * length], axis=1)
        quad = [[0, 3, 2], [0, 2, 1]]
    else:
        pts = np.stack([u * width, v * length, zero], axis=1)
        quad = [[0, 1, 2], [0, 2, 3]]
    return pts[np.array(quad)]
