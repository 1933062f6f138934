"""First-hit ray casting: on triangle soups with Embree (embreex), and through a scene's
instances of trees and of leaves with NVIDIA Warp, both on every core.

Pure-Python ray casting is thousands of times slower; Embree and Warp's CPU kernels release
the GIL, so chunks of rays run in parallel threads. Embree's Python binding has no
instances, and a forest's leaves copied into triangles do not fit in memory (53 M
triangles for one allometric spruce), so the forest is traced by Warp kernels
(:mod:`usdforest.sensors.kernels`) that walk trees, then leaves, then triangles.
"""

from __future__ import annotations

import functools
import os
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from usdforest.sensors.scene import Scene, leaf_boxes, moved_boxes

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
    hit triangle's unit world-space normal (as wound)."""

    def __init__(self, n: int):
        self.t = np.full(n, np.inf)
        self.cls = np.zeros(n, dtype=np.uint8)
        self.tree = np.full(n, -1, dtype=np.int64)
        self.path = np.full(n, -1, dtype=np.int64)
        self.normal = np.zeros((n, 3))

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.t)


@functools.cache
def _warp():
    """Warp and the kernels, initialised once. Warp's native library prints a CUDA warning
    to stderr on a machine without an NVIDIA driver: it is kept out of a command's output
    (and shown if initialisation fails)."""
    import warp as wp

    wp.config.log_level = wp.LOG_ERROR  # no banner, no module-load lines
    with tempfile.TemporaryFile() as err:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(err.fileno(), 2)
        try:
            wp.init()
        except Exception:
            os.dup2(saved, 2)
            err.seek(0)
            sys.stderr.write(err.read().decode(errors="replace"))
            raise
        finally:
            os.dup2(saved, 2)
            os.close(saved)
    from usdforest.sensors import kernels

    return wp, kernels


def _inverse_columns(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row-vector 4x4 transforms ``m`` (n, 4, 4) as Warp wants them: the column-form inverse
    of the linear part (``local = inv @ (x - shift)``), the shift, and which are invertible."""
    rot = m[:, :3, :3]
    ok = np.abs(np.linalg.det(rot)) > 1e-30
    inv = np.zeros_like(rot)
    inv[ok] = np.linalg.inv(rot[ok]).transpose(0, 2, 1)
    return inv.astype(np.float32), m[:, 3, :3].astype(np.float32), ok


class SceneCaster:
    """First hits on a :class:`~usdforest.sensors.scene.Scene`, through its instances.

    Built once per scene: one grouped Warp mesh of every wood triangle (the world's own and
    each tree prototype's, in its own space), one grouped BVH of the leaf instances of the
    world and of each prototype, one mesh of the leaf shapes, and one BVH of the tree
    instances' world boxes. Each ray is one kernel thread that walks trees, then leaves,
    then triangles, pruned by its nearest hit so far: a leaf behind a near trunk is never
    visited. Rays go in chunks, one Warp launch per chunk, on every core (or one launch on
    a CUDA device when ``device`` names one).
    """

    CHUNK = 8192

    def __init__(self, scene: Scene, device: str | None = None):
        wp, kern = _warp()
        self.scene = scene
        self._wp, self._kern = wp, kern
        self.device = wp.get_device(device or "cpu")
        protos = scene.protos
        owners = [
            (scene.triangles, scene.cls, scene.tree, scene.path, scene.leaf_instances),
            *(
                (p.triangles, p.cls, np.full(len(p.cls), -1), p.path, p.leaf_instances)
                for p in protos
            ),
        ]
        g = len(owners)
        # wood: every owner's triangles, grouped by owner
        n_tri = np.array([len(o[0]) for o in owners])
        self._wood_cls = np.concatenate([o[1] for o in owners]).astype(np.uint8)
        self._wood_tree = np.concatenate([o[2] for o in owners]).astype(np.int64)
        self._wood_path = np.concatenate([o[3] for o in owners]).astype(np.int64)
        tri = np.concatenate([np.asarray(o[0], np.float32).reshape(-1, 3, 3) for o in owners])
        self._wood, wood_roots = self._mesh(tri, np.repeat(np.arange(g), n_tri), g)
        # leaf shapes
        shapes = scene.shapes
        s_tri = [np.asarray(s.triangles, np.float32).reshape(-1, 3, 3) for s in shapes]
        self._shape_cls = np.concatenate([s.cls for s in shapes] or [np.zeros(0)]).astype(np.uint8)
        self._shape_path = np.concatenate([s.path for s in shapes] or [np.zeros(0)]).astype(
            np.int64
        )
        self._shapes, shape_roots = self._mesh(
            np.concatenate(s_tri) if s_tri else np.zeros((0, 3, 3), np.float32),
            np.repeat(np.arange(len(shapes)), [len(t) for t in s_tri]),
            len(shapes),
        )
        # leaf instances, grouped by owner, in the owner's space
        leaves = [o[4] for o in owners]
        inv, shift, lo, hi, group, shape, tree = [], [], [], [], [], [], []
        for k, li in enumerate(leaves):
            a, b, good = _inverse_columns(li.matrix)
            lo_k, hi_k = leaf_boxes(li, shapes)
            inv.append(a[good])
            shift.append(b[good])
            lo.append(lo_k[good])
            hi.append(hi_k[good])
            group.append(np.full(int(good.sum()), k))
            shape.append(li.shape[good])
            tree.append(li.tree[good])
        self._leaf_tree = np.concatenate(tree).astype(np.int64)
        shape = np.concatenate(shape).astype(np.int64)
        group = np.concatenate(group)
        self._leaf_bvh, leaf_roots = self._bvh(np.concatenate(lo), np.concatenate(hi), group, g)
        self._leaf_inv = self._array(np.concatenate(inv), wp.mat33)
        self._leaf_shift = self._array(np.concatenate(shift), wp.vec3)
        self._leaf_shape = self._array(shape_roots[shape].astype(np.int32), wp.int32)
        # tree instances
        inst = scene.instances
        self._inst_tree = inst.tree.astype(np.int64)
        box = np.array([p.box for p in protos]).reshape(-1, 2, 3)[inst.proto]
        a, b, good = _inverse_columns(inst.matrix)
        w_lo, w_hi = moved_boxes(box[:, 0], box[:, 1], inst.matrix)
        w_lo[~good], w_hi[~good] = np.inf, -np.inf  # a flattened tree: no box, never entered
        self._n_inst = len(inst)
        self._top, _ = self._bvh(w_lo, w_hi, None, 0)
        self._inst_inv = self._array(a, wp.mat33)
        self._inst_shift = self._array(b, wp.vec3)
        self._inst_proto = self._array(inst.proto.astype(np.int32), wp.int32)
        self._wood_roots = self._array(wood_roots, wp.int32)
        self._leaf_roots = self._array(leaf_roots, wp.int32)
        self.first_hit(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))  # compile, load: once

    def _array(self, a: np.ndarray, dtype):
        return self._wp.array(np.ascontiguousarray(a), dtype=dtype, device=self.device)

    def _roots(self, kernel, handle, groups: np.ndarray, n: int) -> np.ndarray:
        """Root of each of ``n`` groups (``EMPTY`` where a group has nothing)."""
        roots = np.full(n, self._kern.EMPTY, np.int32)
        used = np.unique(groups).astype(np.int32)
        if handle is not None and used.size:
            out = self._wp.empty(used.size, dtype=self._wp.int32, device=self.device)
            self._wp.launch(
                kernel, dim=used.size, inputs=[handle.id, self._array(used, self._wp.int32), out],
                device=self.device,
            )  # fmt: skip
            roots[used] = out.numpy()
        return roots

    def _mesh(self, tri: np.ndarray, groups: np.ndarray, n: int):
        """A grouped Warp mesh of triangles ``tri`` (None when empty) and its group roots."""
        wp = self._wp
        if not len(tri):
            return None, np.full(n, self._kern.EMPTY, np.int32)
        mesh = wp.Mesh(
            points=self._array(tri.reshape(-1, 3), wp.vec3),
            indices=self._array(np.arange(tri.shape[0] * 3, dtype=np.int32), wp.int32),
            groups=self._array(groups.astype(np.int32), wp.int32),
        )
        return mesh, self._roots(self._kern.mesh_roots, mesh, groups, n)

    def _bvh(self, lo: np.ndarray, hi: np.ndarray, groups: np.ndarray | None, n: int):
        """A (grouped) Warp BVH of boxes (None when empty) and its group roots."""
        wp = self._wp
        if not len(lo):
            return None, np.full(n, self._kern.EMPTY, np.int32)
        bvh = wp.Bvh(
            self._array(lo.astype(np.float32), wp.vec3),
            self._array(hi.astype(np.float32), wp.vec3),
            groups=None if groups is None else self._array(groups.astype(np.int32), wp.int32),
        )
        if groups is None:
            return bvh, np.zeros(0, np.int32)
        return bvh, self._roots(self._kern.bvh_roots, bvh, groups, n)

    def _cast(self, o: np.ndarray, d: np.ndarray, limit: np.ndarray) -> tuple[np.ndarray, ...]:
        """Raw kernel output for rays ``o``, ``d`` (float32): t, instance, leaf, face, normal."""
        wp, n = self._wp, len(o)
        out = (
            np.empty(n, np.float32),
            np.empty(n, np.int32),
            np.empty(n, np.int32),
            np.empty(n, np.int32),
            np.empty((n, 3), np.float32),
        )
        types = (float, wp.int32, wp.int32, wp.int32, wp.vec3)
        handle = [0 if x is None else x.id for x in (self._wood, self._leaf_bvh, self._shapes)]
        top = 0 if self._top is None else self._top.id

        def run(sl: slice) -> None:
            arrays = [
                self._array(o[sl], wp.vec3),
                self._array(d[sl], wp.vec3),
                self._array(limit[sl], float),
            ]
            res = [wp.empty(sl.stop - sl.start, dtype=t, device=self.device) for t in types]
            wp.launch(
                self._kern.first_hits,
                dim=sl.stop - sl.start,
                inputs=[
                    *arrays, handle[0], self._wood_roots, handle[1], self._leaf_roots,
                    self._leaf_inv, self._leaf_shift, self._leaf_shape, handle[2], top,
                    self._n_inst, self._inst_inv, self._inst_shift, self._inst_proto, *res,
                ],
                device=self.device,
            )  # fmt: skip
            for dst, src in zip(out, res, strict=True):
                dst[sl] = src.numpy()

        if self.device.is_cuda or n <= self.CHUNK:
            run(slice(0, n))
        else:
            workers = max(1, min(os.cpu_count() or 1, 8))
            with ThreadPoolExecutor(workers) as pool:
                list(
                    pool.map(
                        run, [slice(a, min(a + self.CHUNK, n)) for a in range(0, n, self.CHUNK)]
                    )
                )
        return out

    def first_hit(
        self, origins: np.ndarray, directions: np.ndarray, max_range: float = np.inf
    ) -> Hits:
        """Unit ``directions``; hits beyond ``max_range`` are dropped."""
        o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float32).reshape(-1, 3)
        h = Hits(len(o))
        if not len(o):
            return h
        limit = np.full(len(o), np.float32(min(max_range, np.finfo(np.float32).max)))
        t, inst, leaf, face, normal = self._cast(o, d, limit)
        hit = (face >= 0) & (t <= max_range)
        wood = hit & (leaf < 0)
        green = hit & (leaf >= 0)
        h.t[hit] = t[hit]
        h.normal[hit] = normal[hit]
        h.cls[wood], h.path[wood] = self._wood_cls[face[wood]], self._wood_path[face[wood]]
        h.cls[green], h.path[green] = self._shape_cls[face[green]], self._shape_path[face[green]]
        h.tree[wood] = self._wood_tree[face[wood]]
        h.tree[green] = self._leaf_tree[leaf[green]]
        placed = hit & (inst >= 0)
        h.tree[placed] = self._inst_tree[inst[placed]]
        return h
