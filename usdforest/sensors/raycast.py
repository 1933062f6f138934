"""First-hit ray casting on triangle soups with Embree (embreex), on every core.

Pure-Python ray casting is thousands of times slower; Embree releases the GIL, so chunks of
rays run in parallel threads.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

CHUNK = 65_536


class RayCaster:
    """Embree scene over ``triangles (m, 3, 3)``; :meth:`first_hit` returns distance and id."""

    def __init__(self, triangles: np.ndarray):
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        self.n = len(triangles)
        self._scene = rtcs.EmbreeScene()
        if self.n:
            TriangleMesh(
                scene=self._scene, vertices=np.ascontiguousarray(triangles, dtype=np.float32)
            )

    def first_hit(
        self, origins: np.ndarray, directions: np.ndarray, max_range: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each unit direction to the first triangle (inf if none within
        ``max_range``) and that triangle's index (-1 if none)."""
        n = len(origins)
        t = np.full(n, np.inf)
        prim = np.full(n, -1, dtype=np.int64)
        if n == 0 or self.n == 0:
            return t, prim
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)

        def run(start: int) -> None:
            sl = slice(start, min(start + CHUNK, n))
            res = self._scene.run(o[sl], d[sl], output=1)
            hit = res["geomID"] >= 0
            tt = np.where(hit, res["tfar"], np.inf).astype(float)
            t[sl] = tt
            prim[sl] = np.where(hit, res["primID"], -1)

        workers = max(1, min(os.cpu_count() or 1, 8))
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(run, range(0, n, CHUNK)))
        far = t > max_range
        t[far] = np.inf
        prim[far] = -1
        return t, prim


class Hits:
    """First hits of a batch of rays: distance (inf: none), class, tree id, path index and the
    hit triangle's world-space normal (unnormalised, as wound)."""

    def __init__(self, n: int):
        self.t = np.full(n, np.inf)
        self.cls = np.zeros(n, dtype=np.uint8)
        self.tree = np.full(n, -1, dtype=np.int64)
        self.path = np.full(n, -1, dtype=np.int64)
        self.normal = np.zeros((n, 3))

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.t)


def _normals(tri: np.ndarray) -> np.ndarray:
    t = tri.astype(float)
    return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])


class SceneCaster:
    """First hits on a :class:`~usdforest.sensors.scene.Scene`, following tree instances.

    World-space triangles go into one Embree scene; each tree prototype gets its own, built
    once. For every instance, the rays that pass through its bounding sphere (and could still
    beat the best hit so far) are moved into the prototype's space and cast there; the ray
    parameter is the same in both spaces, so distances compare directly.
    """

    def __init__(self, scene):
        self.scene = scene
        self.base = RayCaster(scene.triangles)
        self.protos = [RayCaster(p.triangles) for p in scene.protos]
        inst = scene.instances
        self.rot = inst.matrix[:, :3, :3]
        self.shift = inst.matrix[:, 3, :3]
        self.inv = np.linalg.inv(self.rot) if len(inst) else np.zeros((0, 3, 3))
        centres = np.array([p.centre for p in scene.protos]).reshape(-1, 3)
        radii = np.array([p.radius for p in scene.protos])
        if len(inst):
            self.centre = np.einsum("nj,njk->nk", centres[inst.proto], self.rot) + self.shift
            self.radius = radii[inst.proto] * np.linalg.norm(self.rot, axis=2).max(axis=1)
        else:
            self.centre, self.radius = np.zeros((0, 3)), np.zeros(0)

    def first_hit(
        self, origins: np.ndarray, directions: np.ndarray, max_range: float = np.inf
    ) -> Hits:
        """Unit ``directions``; hits beyond ``max_range`` are dropped."""
        o = np.asarray(origins, dtype=float)
        d = np.asarray(directions, dtype=float)
        h = Hits(len(o))
        sc = self.scene
        t, prim = self.base.first_hit(o, d)
        ok = prim >= 0
        h.t[ok] = t[ok]
        h.cls[ok], h.tree[ok], h.path[ok] = sc.cls[prim[ok]], sc.tree[prim[ok]], sc.path[prim[ok]]
        h.normal[ok] = _normals(sc.triangles[prim[ok]])
        inst = sc.instances
        for k in range(len(inst)):
            oc = self.centre[k] - o
            tca = np.sum(oc * d, axis=1)
            d2 = np.sum(oc * oc, axis=1) - tca**2
            r2 = self.radius[k] ** 2
            near = (d2 <= r2) & (tca + self.radius[k] >= 0)
            near &= tca - np.sqrt(np.maximum(r2 - d2, 0)) < np.minimum(h.t, max_range)
            idx = np.flatnonzero(near)
            if idx.size == 0:
                continue
            p = sc.protos[inst.proto[k]]
            lo = (o[idx] - self.shift[k]) @ self.inv[k]
            ld = d[idx] @ self.inv[k]
            tl, pl = self.protos[inst.proto[k]].first_hit(lo, ld)
            better = (pl >= 0) & (tl < h.t[idx])
            j, q = idx[better], pl[better]
            h.t[j] = tl[better]
            h.cls[j], h.path[j] = p.cls[q], p.path[q]
            h.tree[j] = inst.tree[k]
            h.normal[j] = _normals(p.triangles[q]) @ self.inv[k].T
        far = h.t > max_range
        h.t[far] = np.inf
        h.cls[far], h.tree[far], h.path[far] = 0, -1, -1
        return h
