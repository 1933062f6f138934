"""Vertex normals of triangle meshes (numpy only: no CAD stack needed to author a mesh)."""

from __future__ import annotations

import numpy as np


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit length; +Z for isolated vertices)."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    norm = np.linalg.norm(vn, axis=1)
    vn[norm == 0] = (0.0, 0.0, 1.0)
    norm[norm == 0] = 1.0
    return vn / norm[:, None]
