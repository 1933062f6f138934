"""First hits through a scene's instances with NVIDIA Warp kernels: the CUDA path of
:class:`~usdforest.sensors.cast.raycast.SceneCaster` (and, for comparison, Warp on the CPU).

Built once per scene from a :class:`~usdforest.sensors.cast.rayscene.RayScene`: one grouped Warp
mesh of every wood triangle (the world's own and each tree prototype's, in its own space), one
grouped BVH of the leaf instances of the world and of each prototype, one mesh of the leaf
shapes, and the tree instances' world boxes. Each ray is one kernel thread that walks trees,
then leaves, then triangles, pruned by its nearest hit so far.

On CUDA the tree level is a loop over the instances' boxes, not a BVH query: Warp keeps a BVH
query's traversal stack in one shared-memory slot per thread, so a leaf-BVH query opened inside
a tree-BVH query's loop overwrites the outer one's stack (wrong hits, then illegal memory
accesses; measured in the project's notes on instanced ray casting). Mesh queries keep their
stack in local memory and may be nested.
"""

from __future__ import annotations

import functools
import os
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.sensors.cast.rayscene import RawHits, RayScene


@functools.cache
def warp():
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
    from usdforest.sensors.cast import warp_kernels as kernels

    return wp, kernels


def cuda_devices() -> list[str]:
    """The CUDA devices Warp sees (``["cuda:0", ...]``; empty without a GPU and driver)."""
    try:
        wp, _ = warp()
    except Exception:  # no Warp, or it cannot start: no CUDA either
        return []
    return [str(d) for d in wp.get_cuda_devices()]


class WarpCaster:
    """Raw first hits on a :class:`RayScene` with Warp on ``device`` ("cpu", "cuda:0"...)."""

    CHUNK = 8192

    def __init__(self, rs: RayScene, device: str = "cpu"):
        wp, kern = warp()
        self._wp, self._kern = wp, kern
        try:
            self.device = wp.get_device(device)
        except Exception as exc:  # an unknown or absent device
            raise UsdForestError(f"device: Warp has no device {device!r} ({exc})") from exc
        g = rs.owners
        self._wood, wood_roots = self._mesh(
            rs.wood, np.repeat(np.arange(g), np.diff(rs.wood_first)), g
        )
        shapes = np.concatenate(rs.shape_tri) if rs.shape_tri else np.zeros((0, 3, 3), np.float32)
        n_shapes = len(rs.shape_tri)
        self._shapes, shape_roots = self._mesh(
            shapes, np.repeat(np.arange(n_shapes), np.diff(rs.shape_first)), n_shapes
        )
        group = np.repeat(np.arange(g), np.diff(rs.leaf_first))
        self._leaf_bvh, leaf_roots = self._bvh(rs.leaf_lo, rs.leaf_hi, group, g)
        self._leaf_inv = self._array(rs.leaf_inv, wp.mat33)
        self._leaf_shift = self._array(rs.leaf_shift, wp.vec3)
        self._leaf_shape = self._array(shape_roots[rs.leaf_shape].astype(np.int32), wp.int32)
        w_lo, w_hi = rs.inst_lo.copy(), rs.inst_hi.copy()
        w_lo[~rs.inst_ok], w_hi[~rs.inst_ok] = np.inf, -np.inf  # a flattened tree: never entered
        self._n_inst = len(w_lo)
        self._top, _ = self._bvh(w_lo, w_hi, None, 0)
        lo32, hi32 = w_lo.astype(np.float32), w_hi.astype(np.float32)
        self._inst_lo = self._array(lo32, wp.vec3)
        self._inst_hi = self._array(hi32, wp.vec3)
        self._inst_inv = self._array(rs.inst_inv, wp.mat33)
        self._inst_shift = self._array(rs.inst_shift, wp.vec3)
        self._inst_proto = self._array(rs.inst_proto.astype(np.int32), wp.int32)
        self._wood_roots = self._array(wood_roots, wp.int32)
        self._leaf_roots = self._array(leaf_roots, wp.int32)
        self.cast(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32), np.ones(1))

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

    def cast(
        self, o: np.ndarray, d: np.ndarray, limit: np.ndarray, looped: bool | None = None
    ) -> RawHits:
        """Raw hits of rays ``o``, ``d`` (float32 (n, 3)) within ``limit``. ``looped``: the
        tree level a loop over boxes (default: on CUDA, where it must be) or a BVH walk."""
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
        cuda = self.device.is_cuda
        top = [
            0 if self._top is None else self._top.id, self._inst_lo, self._inst_hi,
            int(cuda if looped is None else looped),
        ]  # fmt: skip
        kernel = self._kern.first_hits

        def run(sl: slice) -> None:
            arrays = [
                self._array(o[sl], wp.vec3),
                self._array(d[sl], wp.vec3),
                self._array(np.asarray(limit[sl], np.float32), float),
            ]
            res = [wp.empty(sl.stop - sl.start, dtype=t, device=self.device) for t in types]
            wp.launch(
                kernel,
                dim=sl.stop - sl.start,
                inputs=[
                    *arrays, handle[0], self._wood_roots, handle[1], self._leaf_roots,
                    self._leaf_inv, self._leaf_shift, self._leaf_shape, handle[2], *top,
                    self._n_inst, self._inst_inv, self._inst_shift, self._inst_proto, *res,
                ],
                device=self.device,
            )  # fmt: skip
            for dst, src in zip(out, res, strict=True):
                dst[sl] = src.numpy()

        if cuda or n <= self.CHUNK:
            run(slice(0, n))
        else:
            workers = max(1, min(os.cpu_count() or 1, 8))
            with ThreadPoolExecutor(workers) as pool:
                list(
                    pool.map(
                        run, [slice(a, min(a + self.CHUNK, n)) for a in range(0, n, self.CHUNK)]
                    )
                )
        t, inst, leaf, face, normal = out
        return RawHits(t, inst, leaf.astype(np.int64), face.astype(np.int64), normal)
