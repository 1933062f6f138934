"""Tube skeletons of meshes: geodesic level sets from a root, split where they fork.

A trunk or branch mesh is a tube (or a tree of tubes fused together). Its vertices are banded
by their geodesic distance (along mesh edges) from a root ring; the connected pieces of each
band are the nodes of a tree (a discrete Reeb graph), each linked to the piece of the band
below that it touches most. A node whose children both reach far is a fork: the child that
reaches farthest continues the tube, the others are parts of their own (recursively). Parts
shorter than ``min_length`` stay fused to their parent (ring vertices that straddle a band
boundary make such stubs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class TubePart:
    """One tube of a split mesh.

    ``vertices`` indexes the mesh's vertices; ``centreline (k, 3)`` the centres of its bands
    from its base to its tip; ``parent`` the index of the part it grows from (-1 for the root
    part).
    """

    vertices: np.ndarray
    centreline: np.ndarray
    parent: int

    @property
    def base(self) -> np.ndarray:
        return self.centreline[0]

    @property
    def tip(self) -> np.ndarray:
        return self.centreline[-1]


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """``(k, 2)`` unique undirected edges of a triangle mesh (smaller index first)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def split_tubes(
    vertices: np.ndarray,
    faces: np.ndarray,
    root: np.ndarray,
    band: float,
    min_length: float,
    link: float | None = None,
    root_axis: np.ndarray | None = None,
    max_turn: float = 35.0,
) -> list[TubePart]:
    """Split a tube mesh into parts at its forks.

    Parameters
    ----------
    vertices, faces
        The mesh (one connected component).
    root
        ``bool[n]``: the vertices of the ring the tube grows from (e.g. the trunk's base).
    band
        Width of the geodesic bands in metres (about the tube's radius).
    min_length
        A side tube that reaches less than this beyond its fork stays fused to its parent.
    link
        Vertices of one band closer than this belong to one piece (default ``2 * band``).
    root_axis, max_turn
        If given, the root part ends where the tube ahead of it turns more than ``max_turn``
        degrees away from ``root_axis`` (a trunk that bends into a limb); the rest becomes a
        part of its own.

    Returns
    -------
    list of TubePart
        The root part first; every part after its parent.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components, dijkstra
    from scipy.spatial import cKDTree

    n = len(vertices)
    link = 2.0 * band if link is None else link
    e = mesh_edges(faces)
    w = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    graph = coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    dist = dijkstra(graph, directed=False, indices=np.flatnonzero(root), min_only=True)
    reach = np.isfinite(dist)
    b = np.where(reach, np.floor(np.where(reach, dist, 0.0) / band), -1).astype(np.int64)
    same = (b[e[:, 0]] == b[e[:, 1]]) & reach[e[:, 0]]
    # a band's piece: its vertices joined by mesh edges, or lying within ``link`` of each
    # other (on a coarse tube a ring's vertices straddle band boundaries, and the arcs of
    # one ring must not look like two tubes)
    rows, cols = [e[same, 0]], [e[same, 1]]
    for bb in np.unique(b[reach]):
        idx = np.flatnonzero(b == bb)
        if len(idx) > 1:
            pairs = cKDTree(vertices[idx]).query_pairs(link, output_type="ndarray")
            rows.append(idx[pairs[:, 0]])
            cols.append(idx[pairs[:, 1]])
    r_, c_ = np.concatenate(rows), np.concatenate(cols)
    inner = coo_matrix((np.ones(len(r_)), (r_, c_)), shape=(n, n)).tocsr()
    _, node = connected_components(inner, directed=False)
    same = node[e[:, 0]] == node[e[:, 1]]
    k = int(node.max()) + 1
    node_band = np.full(k, -1, dtype=np.int64)
    node_band[node[reach]] = b[reach]
    # parent of a node: the lower-band node it shares the most edges with
    cross = ~same & reach[e[:, 0]] & reach[e[:, 1]]
    lo = np.where(b[e[cross, 0]] < b[e[cross, 1]], e[cross, 0], e[cross, 1])
    hi = np.where(b[e[cross, 0]] < b[e[cross, 1]], e[cross, 1], e[cross, 0])
    pairs, counts = np.unique(np.stack([node[hi], node[lo]], 1), axis=0, return_counts=True)
    parent = np.full(k, -1, dtype=np.int64)
    best = np.zeros(k)
    for (child, par), c in zip(pairs.tolist(), counts.tolist(), strict=True):
        if node_band[par] < node_band[child] and c > best[child]:
            parent[child], best[child] = par, c
    centre = np.zeros((k, 3))
    np.add.at(centre, node[reach], vertices[reach])
    size = np.bincount(node[reach], minlength=k)
    centre /= np.maximum(size, 1)[:, None]
    node_dist = np.zeros(k)
    np.maximum.at(node_dist, node[reach], dist[reach])

    children: list[list[int]] = [[] for _ in range(k)]
    for c in np.argsort(node_band, kind="stable"):
        if parent[c] >= 0:
            children[int(parent[c])].append(int(c))
    # per subtree: farthest geodesic reach, vertex count and position sum (bottom-up)
    reach_of = node_dist.copy()
    sub_n = size.astype(float)
    sub_sum = centre * size[:, None]
    for c in np.argsort(-node_band, kind="stable"):
        pc = parent[c]
        if pc >= 0:
            reach_of[pc] = max(reach_of[pc], reach_of[c])
            sub_n[pc] += sub_n[c]
            sub_sum[pc] += sub_sum[c]
    node_min = np.full(k, np.inf)
    np.minimum.at(node_min, node[reach], dist[reach])

    def extent(c: int) -> float:
        return float(reach_of[c] - node_min[c])

    def unit(v: np.ndarray) -> np.ndarray:
        n_ = np.linalg.norm(v)
        return v / n_ if n_ > 1e-12 else v

    roots = [int(c) for c in np.flatnonzero((parent < 0) & (node_band >= 0))]
    part_of_node = np.full(k, -1, dtype=np.int64)
    parts: list[tuple[list[int], int]] = []  # (nodes, parent part)
    # the root part starts at every band-0 node (the root ring may be several pieces)
    queue: list[tuple[list[int], int]] = [(roots, -1)]
    while queue:
        start, parent_part = queue.pop(0)
        idx = len(parts)
        chain: list[int] = []
        frontier = list(start)
        first = np.mean(centre[start], axis=0)
        while frontier:
            for f in frontier:
                part_of_node[f] = idx
            chain.extend(frontier)
            kids = [c for f in frontier for c in children[f]]
            tubes = [c for c in kids if extent(c) >= min_length]
            stubs = [c for c in kids if c not in tubes]
            if root_axis is not None and parent_part < 0 and tubes:
                # the root part (a trunk) ends where it turns away from its axis: what
                # follows is a limb
                here = np.mean(centre[frontier], axis=0)
                main = max(tubes, key=lambda c: (reach_of[c], -c))
                ahead = unit(sub_sum[main] / sub_n[main] - here)
                if float(ahead @ root_axis) < np.cos(np.radians(max_turn)):
                    for c in tubes:
                        queue.append(([c], idx))
                    frontier = stubs
                    continue
            if len(tubes) <= 1:
                frontier = kids
                continue
            # a fork: the tube reaching farthest continues this part if it keeps its
            # direction; the others (or all) start parts of their own
            here = np.mean(centre[frontier], axis=0)
            main = max(tubes, key=lambda c: (reach_of[c], -c))
            way = unit(here - first) if np.linalg.norm(here - first) > band else None
            ahead = unit(sub_sum[main] / sub_n[main] - here)
            keeps = way is not None and float(way @ ahead) >= np.cos(np.radians(25.0))
            for c in tubes:
                if not (keeps and c == main):
                    queue.append(([c], idx))
            frontier = stubs + ([main] if keeps else [])
        parts.append((chain, parent_part))
        # stubs that never became a frontier of their own belong to this part
        todo = [c for f in chain for c in children[f] if part_of_node[c] < 0]
        while todo:
            c = todo.pop()
            if part_of_node[c] < 0 and not any(c == q[0][0] for q in queue):
                part_of_node[c] = idx
                parts[idx][0].append(c)
                todo.extend(children[c])

    out = []
    vertex_part = np.where(reach, part_of_node[node], -1)
    # unreachable vertices (a detached piece) go with the root part
    vertex_part[vertex_part < 0] = 0
    for i, (chain, parent_part) in enumerate(parts):
        chain_arr = np.array(chain)
        bands = node_band[chain_arr]
        line = []
        for bb in np.unique(bands):
            sel = chain_arr[bands == bb]
            wts = size[sel].astype(float)
            line.append((centre[sel] * wts[:, None]).sum(axis=0) / wts.sum())
        mine = np.flatnonzero(vertex_part == i)
        # the ends: the root ring's centre, and the centre of the vertices farthest along
        # (a cap's centre, or an open end's last ring)
        if parent_part < 0:
            line.insert(0, vertices[root & reach].mean(axis=0))
        on_chain = mine[np.isin(node[mine], chain_arr) & reach[mine]]
        if on_chain.size:
            far = dist[on_chain]
            line.append(vertices[on_chain[far >= far.max() - 0.25 * band]].mean(axis=0))
        out.append(TubePart(mine, np.array(line), parent_part))
    return out
