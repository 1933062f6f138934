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
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_range: float = np.inf,
        *,
        beyond: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each unit direction to the first triangle (inf if none within
        ``max_range``) and that triangle's index (-1 if none). ``beyond`` (per ray): hits
        farther than this are not looked for (Embree stops there; they may be missed)."""
        n = len(origins)
        t = np.full(n, np.inf)
        prim = np.full(n, -1, dtype=np.int64)
        if n == 0 or self.n == 0:
            return t, prim
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        far = None
        if beyond is not None:  # float32, rounded up: never below the float64 limit
            b = np.asarray(beyond, dtype=np.float64)
            far = b.astype(np.float32)
            far = np.where(far < b, np.nextafter(far, np.float32(np.inf)), far)

        def run(start: int) -> None:
            sl = slice(start, min(start + CHUNK, n))
            dists = None if far is None else np.ascontiguousarray(far[sl])
            res = self._scene.run(o[sl], d[sl], dists=dists, output=1)
            hit = res["geomID"] >= 0
            tt = np.where(hit, res["tfar"], np.inf).astype(float)
            t[sl] = tt
            prim[sl] = np.where(hit, res["primID"], -1)

        if n <= CHUNK:
            run(0)
        else:
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
    once. The instances' bounding spheres are the top level: every ray's candidate instances
    (the spheres it enters before ``max_range`` and before its hit among the world
    triangles) are found at once, rays binned by direction and each sphere's cone of
    directions looked up in the bins (:meth:`_cone_pairs`). Instances are then visited
    nearest first, each with one Embree call for its candidate rays that still enter its
    sphere before their best hit so far, moved into its space (the ray parameter is the same
    in both spaces, so distances compare directly): a ray that meets a near trunk is not cast
    into the trees behind it, and no step costs time for rays an instance cannot meet.
    """

    BIN = np.radians(1.0)  # direction cells of the top level
    SPREAD = 5.0  # m: rays from origins further apart than this test every instance

    def __init__(self, scene):
        self.scene = scene
        self.base = RayCaster(scene.triangles)
        self._protos: list[RayCaster | None] = [None] * len(scene.protos)
        inst = scene.instances
        self.rot = inst.matrix[:, :3, :3]
        self.shift = inst.matrix[:, 3, :3]
        self.inv = np.linalg.inv(self.rot) if len(inst) else np.zeros((0, 3, 3))
        self.centre, self.radius = scene.instance_spheres()
        # a hair wider: a pair kept by rounding only costs a cast that misses
        self._reach = self.radius * (1 + 1e-9) + 1e-9

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
        if len(sc.instances) and len(o):
            self._instances(o, d, h, max_range)
        far = h.t > max_range
        h.t[far] = np.inf
        h.cls[far], h.tree[far], h.path[far] = 0, -1, -1
        return h

    def _cone_pairs(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ray, instance) pairs that may meet: rays binned by direction on a grid of
        ``BIN`` radians; each instance's sphere, seen from the rays' mean origin (widened by
        their spread), covers a cone of directions, whose cells' rays are its candidates (a
        superset; the exact test follows). Rays from origins far apart (beyond ``SPREAD``)
        are paired with every instance."""
        n, m = len(o), len(self.centre)
        origin = o.mean(axis=0)
        spread = float(np.sqrt(np.max(np.einsum("ij,ij->i", o - origin, o - origin))))
        if spread > self.SPREAD or n * m <= 4096:
            return np.repeat(np.arange(n), m), np.tile(np.arange(m), n)
        b = self.BIN
        naz, nel = int(np.ceil(2 * np.pi / b)), int(np.ceil(np.pi / b))
        az = np.arctan2(d[:, 1], d[:, 0])
        el = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
        cell = np.minimum(((el + np.pi / 2) / b).astype(np.int64), nel - 1) * naz + np.minimum(
            ((az + np.pi) / b).astype(np.int64), naz - 1
        )
        by_cell = np.argsort(cell, kind="stable")
        sorted_cells = cell[by_cell]
        v = self.centre - origin
        dist = np.linalg.norm(v, axis=1)
        reach = self._reach + spread
        near = dist <= reach  # the origin may be inside: every direction
        half = np.arcsin(np.clip(reach / np.maximum(dist, 1e-300), 0.0, 1.0)) + b
        c_el = np.arcsin(np.clip(v[:, 2] / np.maximum(dist, 1e-300), -1.0, 1.0))
        c_az = np.arctan2(v[:, 1], v[:, 0])
        e0 = np.clip(((c_el - half + np.pi / 2) / b).astype(np.int64), 0, nel - 1)
        e1 = np.clip(((c_el + half + np.pi / 2) / b).astype(np.int64), 0, nel - 1)
        top = np.abs(c_el) + half
        spin = np.where(
            top < np.pi / 2 - b,
            np.arcsin(np.clip(np.sin(half) / np.cos(np.minimum(top, np.pi / 2 - b)), 0, 1)) + b,
            np.pi,
        )
        full = near | (spin >= np.pi)
        e0[near], e1[near] = 0, nel - 1
        # (instance, row) spans of cells; an azimuth range that wraps is two spans
        rows = e1 - e0 + 1
        k = np.repeat(np.arange(m), rows)
        row = e0[k] + (np.arange(k.size) - np.repeat(np.cumsum(rows) - rows, rows))
        a0 = np.floor((c_az[k] - spin[k] + np.pi) / b).astype(np.int64)
        a1 = np.floor((c_az[k] + spin[k] + np.pi) / b).astype(np.int64)
        a0[full[k]], a1[full[k]] = 0, naz - 1
        wrap_lo, wrap_hi = a0 < 0, a1 >= naz
        spans = [
            (k, row, np.maximum(a0, 0), np.minimum(a1, naz - 1)),
            (k[wrap_lo], row[wrap_lo], a0[wrap_lo] + naz, np.full(wrap_lo.sum(), naz - 1)),
            (k[wrap_hi], row[wrap_hi], np.zeros(wrap_hi.sum(), np.int64), a1[wrap_hi] - naz),
        ]
        ks, lo, hi = [], [], []
        for kk, rr, x0, x1 in spans:
            ks.append(kk)
            lo.append(np.searchsorted(sorted_cells, rr * naz + x0, side="left"))
            hi.append(np.searchsorted(sorted_cells, rr * naz + x1, side="right"))
        ks, lo, hi = np.concatenate(ks), np.concatenate(lo), np.concatenate(hi)
        count = np.maximum(hi - lo, 0)
        inst = np.repeat(ks, count)
        pos = np.repeat(lo - np.cumsum(count) + count, count) + np.arange(count.sum())
        return by_cell[pos], inst

    def _proto(self, k: int) -> RayCaster:
        """Prototype ``k``'s Embree scene, built (and its BVH committed, by one ray) the first
        time a ray is cast into it."""
        if self._protos[k] is None:
            caster = RayCaster(self.scene.protos[k].triangles)
            caster.first_hit(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
            self._protos[k] = caster
        return self._protos[k]

    def _instances(self, o: np.ndarray, d: np.ndarray, h: Hits, max_range: float) -> None:
        """Cast into the instances, nearest first, each with its candidate rays that still
        enter its sphere before their best hit so far (updating ``h``).

        Instances go in waves, the casts of a wave on all cores (Embree releases the GIL)
        against the best hits before the wave, their results merged in order with a strict
        ``<``: the same hits as one instance at a time (a ray a wave casts needlessly only
        finds a hit no nearer than the one it keeps)."""
        ray, inst = self._cone_pairs(o, d)
        order = np.argsort(inst, kind="stable")
        ray, inst = ray[order], inst[order]
        starts = np.searchsorted(inst, np.arange(len(self.centre) + 1))
        gap = np.linalg.norm(self.centre - o.mean(axis=0), axis=1) - self.radius
        limit = np.minimum(h.t, max_range)
        shared = bool(np.all(o == o[0]))  # a scan or a frame: one origin for every ray
        visit = [k for k in np.argsort(gap, kind="stable") if starts[k + 1] > starts[k]]
        workers = max(1, min(os.cpu_count() or 1, 8))
        wave = 2 * workers

        def cast(k: int):
            rays = ray[starts[k] : starts[k + 1]]
            dd = d[rays]
            r = self._reach[k]
            if shared:
                oc = self.centre[k] - o[0]
                tca = dd @ oc
                inside = r * r - (oc @ oc - tca * tca)
            else:
                oc = self.centre[k] - o[rays]
                tca = np.einsum("ij,ij->i", oc, dd)
                inside = r * r - (np.einsum("ij,ij->i", oc, oc) - tca * tca)
            enter = tca - np.sqrt(np.maximum(inside, 0.0))
            keep = (inside >= 0) & (tca + r >= 0) & (enter < limit[rays])
            idx = rays[keep]
            if idx.size == 0:
                return None
            if shared:  # one origin: moved into the instance's space once
                lo = np.broadcast_to((o[:1] - self.shift[k]) @ self.inv[k], (idx.size, 3))
            else:
                lo = (o[idx] - self.shift[k]) @ self.inv[k]
            ld = dd[keep] @ self.inv[k]
            # Embree stops at each ray's best hit so far: a crown behind it is not walked
            caster = self._protos[self.scene.instances.proto[k]]
            return idx, *caster.first_hit(lo, ld, beyond=limit[idx])

        with ThreadPoolExecutor(workers) as pool:
            for w in range(0, len(visit), wave):
                ks = visit[w : w + wave]
                for k in ks:  # Embree builds a scene on its first cast: one thread at a time
                    self._proto(self.scene.instances.proto[k])
                for k, res in zip(ks, pool.map(cast, ks), strict=True):
                    if res is not None:
                        self._merge(h, limit, k, *res)

    def _merge(
        self, h: Hits, limit: np.ndarray, k: int, idx: np.ndarray, tl: np.ndarray, pl: np.ndarray
    ) -> None:
        """Keep instance ``k``'s hits that are nearer than the best so far."""
        sc = self.scene
        better = (pl >= 0) & (tl < h.t[idx])
        j, q = idx[better], pl[better]
        p = sc.protos[sc.instances.proto[k]]
        h.t[j] = limit[j] = tl[better]
        h.cls[j], h.path[j] = p.cls[q], p.path[q]
        h.tree[j] = sc.instances.tree[k]
        h.normal[j] = _normals(p.triangles[q]) @ self.inv[k].T
