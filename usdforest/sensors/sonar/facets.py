"""The ground as rough facets: the sonar's ground reflectors, sampled on the stage's own
ground triangles.

Around the sonar, a lattice of ``patch``-metre cells (fixed in world space, so a flight hears
the same ground at every pulse) gets one facet per cell: a point jittered inside the cell,
dropped straight down onto the triangles labelled ``ground`` (a plane, a raster height field,
an implicit Plane: anything seen from above), with that triangle's normal and the cell's
surface area ``patch^2 / |n_z|``. Each facet has a random phase (its sub-patch roughness);
jitter and phase are hashes of the cell's indices and the seed, the same on every machine.
Overhangs are not modelled (the ground is what a ray straight down meets first).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usdforest.sensors.cast.raycast import RayCaster
from usdforest.sensors.scene.scenetypes import CLASS_ID, Scene


@dataclass(frozen=True, eq=False)
class Facets:
    """Ground facets: centre (n, 3), unit upward normal (n, 3), area (m²), phase in [0, 1)."""

    centre: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    phase: np.ndarray

    def __len__(self) -> int:
        return int(self.centre.shape[0])

    def take(self, sel: np.ndarray) -> Facets:
        return Facets(self.centre[sel], self.normal[sel], self.area[sel], self.phase[sel])

    @staticmethod
    def empty() -> Facets:
        return Facets(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))


def hash_uniform(i: np.ndarray, j: np.ndarray, salt: int) -> np.ndarray:
    """Uniform numbers in [0, 1) from integer cell indices (splitmix64 finaliser)."""
    with np.errstate(over="ignore"):
        x = np.asarray(i, np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
        x ^= np.asarray(j, np.int64).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
        x ^= np.uint64(salt & 0xFFFFFFFFFFFFFFFF)
        x ^= x >> np.uint64(30)
        x *= np.uint64(0xBF58476D1CE4E5B9)
        x ^= x >> np.uint64(27)
        x *= np.uint64(0x94D049BB133111EB)
        x ^= x >> np.uint64(31)
    return (x >> np.uint64(11)).astype(np.float64) * 2.0**-53


class GroundField:
    """The ground triangles of a scene, built once and sampled around each sonar pose."""

    def __init__(self, scene: Scene, patch: float, seed: int = 0):
        sel = scene.cls == CLASS_ID["ground"]
        self.triangles = scene.triangles[sel]
        self.patch = float(patch)
        self.seed = int(seed)
        self._caster = RayCaster(self.triangles) if len(self.triangles) else None
        self._top = float(self.triangles[..., 2].max()) + 1.0 if len(self.triangles) else 0.0

    def __len__(self) -> int:
        return len(self.triangles)

    def facets(self, position: np.ndarray, max_range: float) -> Facets:
        """Facets within ``max_range`` of ``position``."""
        if self._caster is None:
            return Facets.empty()
        h = self.patch
        x0, y0 = float(position[0]), float(position[1])
        ii = np.arange(np.floor((x0 - max_range) / h), np.ceil((x0 + max_range) / h) + 1)
        jj = np.arange(np.floor((y0 - max_range) / h), np.ceil((y0 + max_range) / h) + 1)
        i, j = (a.ravel().astype(np.int64) for a in np.meshgrid(ii, jj, indexing="ij"))
        x = (i + hash_uniform(i, j, self.seed * 4 + 1)) * h
        y = (j + hash_uniform(i, j, self.seed * 4 + 2)) * h
        near = np.hypot(x - x0, y - y0) <= max_range
        i, j, x, y = i[near], j[near], x[near], y[near]
        origins = np.column_stack([x, y, np.full(x.size, self._top)])
        down = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origins.shape)
        t, prim = self._caster.first_hit(origins, down)
        hit = prim >= 0
        tri = self.triangles[prim[hit]].astype(np.float64)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
        centre = origins[hit] - np.outer(t[hit], [0.0, 0.0, 1.0])
        inside = np.linalg.norm(centre - position, axis=1) <= max_range
        nz = np.maximum(np.abs(n[:, 2]), 1e-3)
        return Facets(
            centre[inside],
            n[inside],
            (h * h / nz)[inside],
            hash_uniform(i[hit], j[hit], self.seed * 4 + 3)[inside],
        )
