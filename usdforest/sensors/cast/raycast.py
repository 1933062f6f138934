"""First-hit ray casting: on triangle soups with Embree (embreex), and through a scene's
instances of trees and of leaves with Embree 4 on the CPU or NVIDIA Warp on CUDA.

Pure-Python ray casting is thousands of times slower, and a forest's leaves copied into
triangles do not fit in memory (53 M triangles for one allometric spruce), so the forest is
cast through its instances (:class:`SceneCaster`): on the CPU by Embree 4 with two instance
levels kept (:mod:`usdforest.sensors.cast.embree`), on an NVIDIA GPU by Warp kernels that walk
trees, then leaves, then triangles (:mod:`usdforest.sensors.cast.warpcast`). Both return the same
hits (to float32 rounding), classes, paths and tree ids.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.sensors.cast.rayscene import Hits, RayScene
from usdforest.sensors.scene.scenetypes import Scene

__all__ = ["Hits", "RayCaster", "SceneCaster", "resolve_device"]

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


def resolve_device(device: str | None) -> str:
    """A caster device as given by a user: ``None`` or ``"cpu"`` (Embree on every core),
    ``"cuda"`` (the first CUDA device) or ``"cuda:N"``; an unknown name, or CUDA on a
    machine without one, is a :class:`~usdforest.errors.UsdForestError` naming it."""
    if device is None or device == "cpu":
        return "cpu"
    if not isinstance(device, str) or not (
        device == "cuda" or (device.startswith("cuda:") and device[5:].isdigit())
    ):
        raise UsdForestError(f"device: expected 'cpu', 'cuda' or 'cuda:N', got {device!r}")
    from usdforest.sensors.cast.warpcast import cuda_devices

    found = cuda_devices()
    if not found:
        raise UsdForestError(
            f"device: {device!r} asked for, but Warp finds no CUDA device on this machine "
            "(an NVIDIA GPU and driver); use --device cpu"
        )
    name = found[0] if device == "cuda" else device
    if name not in found:
        raise UsdForestError(f"device: no {device!r}; this machine has {', '.join(found)}")
    return name


class SceneCaster:
    """First hits on a :class:`~usdforest.sensors.scene.scenetypes.Scene`, through its instances.

    Built once per scene. On the CPU (``device="cpu"``, the default) Embree 4 casts every
    ray on every core with both instance levels kept (trees, then leaves:
    :class:`~usdforest.sensors.cast.embree.EmbreeCaster`); ``device="cuda"`` casts on an NVIDIA
    GPU with Warp (:class:`~usdforest.sensors.cast.warpcast.WarpCaster`); ``"warp-cpu"`` runs
    those Warp kernels on the CPU (slower; kept to compare the two paths).
    ``progress(stage, done, total)`` as the CPU's scene is built.
    """

    def __init__(
        self,
        scene: Scene,
        device: str | None = None,
        progress: Callable[[str, int, int], None] | None = None,
    ):
        self.scene = scene
        self._rs = RayScene.of(scene)
        if device == "warp-cpu":
            from usdforest.sensors.cast.warpcast import WarpCaster

            self.device = device
            self._impl = WarpCaster(self._rs, "cpu")
            return
        self.device = resolve_device(device)
        if self.device == "cpu":
            from usdforest.sensors.cast.embree import EmbreeCaster

            self._impl = EmbreeCaster(self._rs, progress)
        else:
            from usdforest.sensors.cast.warpcast import WarpCaster

            self._impl = WarpCaster(self._rs, self.device)

    def moved(self, scene: Scene) -> SceneCaster:
        """A caster of ``scene``: this one's scene with its tree instances placed anew and
        its leaf shapes turned (the same prototypes, instances and leaves;
        :class:`~usdforest.sensors.scene.motion.SceneMotion`). On the CPU the prototypes' Embree
        scenes are shared, only the top level is built again and each leaf's callback turns
        the ray by its shape's turn; Warp builds its scene again, leaves turned."""
        other = object.__new__(SceneCaster)
        other.scene, other.device = scene, self.device
        other._rs = self._rs.moved(scene)
        if self.device == "cpu":
            other._impl = self._impl.moved(other._rs)
        else:
            from usdforest.sensors.cast.warpcast import WarpCaster

            other._impl = WarpCaster(
                other._rs.turned(), "cpu" if self.device == "warp-cpu" else self.device
            )
        return other

    def first_hit(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_range: float = np.inf,
        *,
        group: int = 1,
    ) -> Hits:
        """Unit ``directions``; hits beyond ``max_range`` are dropped. ``group``: the rays
        come in nearly parallel groups of this many (a lidar beam's sub-rays, one pulse
        after another), which the CPU casts together; the hits are the same."""
        o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float32).reshape(-1, 3)
        if not len(o):
            return Hits(0)
        limit = np.full(len(o), np.float32(min(max_range, np.finfo(np.float32).max)))
        if self.device == "cpu":
            raw = self._impl.cast(o, d, limit, group)
        else:
            raw = self._impl.cast(o, d, limit)
        return self._rs.hits(raw, max_range)
