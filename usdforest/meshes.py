"""Numpy helpers on triangle meshes (no CAD stack needed to author or read one): vertex
normals, and connected pieces (a template's separate leaves or blades, copies of one mesh
placed apart, a CAD file's separate parts)."""

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


def face_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """``int[m]`` connected-component label of each face of ``faces (m, 3)`` (vertex indices
    below ``n_vertices``): faces sharing a vertex connect."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    rows = np.repeat(f[:, 0], 3)
    graph = coo_matrix((np.ones(rows.size), (rows, f.ravel())), shape=(n_vertices, n_vertices))
    _, vertex_label = connected_components(graph, directed=False)
    return vertex_label[f[:, 0]]


def triangle_components(tri: np.ndarray) -> np.ndarray:
    """``int[m]`` piece of each of ``tri (m, 3, 3)``: triangles sharing a vertex position
    connect (copies of one mesh placed apart share none)."""
    t = np.asarray(tri).reshape(-1, 3)
    if not len(t):
        return np.zeros(0, dtype=np.int64)
    _, vertex = np.unique(t, axis=0, return_inverse=True)
    vertex = vertex.reshape(-1, 3)
    return face_components(vertex, int(vertex.max()) + 1)
