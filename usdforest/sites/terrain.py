"""The ground's shape: a height field on a regular grid, and heights on it.

A :class:`HeightField` holds elevations (metres) at the nodes of a regular grid over
``bounds = (x0, y0, x1, y1)``, row 0 along the north edge (max y), as a DEM raster is stored.
Its surface is the triangulation the ground mesh is written with: each grid cell split along
the diagonal from its south-west to its north-east corner. :meth:`HeightField.height`
interpolates on exactly those triangles, so a tree's z is on the mesh a viewer, a sensor and a
physics engine see, not on a smoother surface beside it.

A flat plane is the 2 x 2 height field of zeros.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from usdforest.errors import RecipeError

MAX_NODES = 1025  # per side of the ground mesh: a finer raster is decimated to this


@dataclass(frozen=True, eq=False)
class HeightField:
    """Elevations ``z (rows, cols)`` at grid nodes over ``bounds`` (row 0 = north)."""

    z: np.ndarray
    bounds: tuple[float, float, float, float]

    @staticmethod
    def plane(bounds: tuple[float, float, float, float], height: float = 0.0) -> HeightField:
        return HeightField(np.full((2, 2), float(height)), tuple(map(float, bounds)))

    @property
    def shape(self) -> tuple[int, int]:
        return self.z.shape

    def _cell(self, x: np.ndarray, y: np.ndarray):
        x0, y0, x1, y1 = self.bounds
        rows, cols = self.z.shape
        fx = np.clip((np.asarray(x, dtype=np.float64) - x0) / (x1 - x0), 0, 1) * (cols - 1)
        fy = np.clip((y1 - np.asarray(y, dtype=np.float64)) / (y1 - y0), 0, 1) * (rows - 1)
        c = np.minimum(fx.astype(np.int64), cols - 2)
        r = np.minimum(fy.astype(np.int64), rows - 2)
        return r, c, fx - c, fy - r

    def window(self, box: tuple[float, float, float, float]) -> HeightField:
        """The part of the field over ``box`` (x0, y0, x1, y1), on the same triangles: the
        grid's cells that meet the box (a plane: exactly the box)."""
        x0, y0, x1, y1 = self.bounds
        rows, cols = self.z.shape
        if (
            rows == 2
            and cols == 2
            and np.isclose(
                self.z[0, 0] + self.z[1, 1], self.z[0, 1] + self.z[1, 0], rtol=0, atol=1e-9
            )
        ):  # a plane: any box of it is a plane
            b = (max(box[0], x0), max(box[1], y0), min(box[2], x1), min(box[3], y1))
            gx, gy = np.array([[b[0], b[2]], [b[0], b[2]]]), np.array([[b[3], b[3]], [b[1], b[1]]])
            return HeightField(self.height(gx, gy), b)
        dx, dy = (x1 - x0) / (cols - 1), (y1 - y0) / (rows - 1)
        c0 = int(np.clip(np.floor((box[0] - x0) / dx), 0, cols - 2))
        c1 = int(np.clip(np.ceil((box[2] - x0) / dx), c0 + 1, cols - 1))
        r0 = int(np.clip(np.floor((y1 - box[3]) / dy), 0, rows - 2))
        r1 = int(np.clip(np.ceil((y1 - box[1]) / dy), r0 + 1, rows - 1))
        xs, ys = np.linspace(x0, x1, cols), np.linspace(y1, y0, rows)
        return HeightField(self.z[r0 : r1 + 1, c0 : c1 + 1], (xs[c0], ys[r1], xs[c1], ys[r0]))

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Heights at ``x, y`` on the ground mesh's triangles (clamped to the bounds)."""
        r, c, u, v = self._cell(x, y)
        z = self.z
        nw, ne = z[r, c], z[r, c + 1]  # row r is the cell's north edge
        sw, se = z[r + 1, c], z[r + 1, c + 1]
        # v runs south from the north edge; the diagonal joins sw (u=0, v=1) and ne (1, 0)
        upper = u + v <= 1.0  # the north-west triangle nw, ne, sw
        z_upper = nw + u * (ne - nw) + v * (sw - nw)
        z_lower = se + (1.0 - u) * (sw - se) + (1.0 - v) * (ne - se)
        return np.where(upper, z_upper, z_lower)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """``(points (rows*cols, 3), triangles (2*(rows-1)*(cols-1), 3))``, wound up (+Z)."""
        x0, y0, x1, y1 = self.bounds
        rows, cols = self.z.shape
        xs = np.linspace(x0, x1, cols)
        ys = np.linspace(y1, y0, rows)
        gx, gy = np.meshgrid(xs, ys)
        pts = np.stack([gx.ravel(), gy.ravel(), self.z.ravel()], axis=1)
        idx = np.arange(rows * cols).reshape(rows, cols)
        nw, ne = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        sw, se = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        # counter-clockwise seen from above: nw, sw, ne and ne, sw, se
        tri = np.concatenate([np.stack([nw, sw, ne], 1), np.stack([ne, sw, se], 1)])
        return pts, tri


MAX_ELEVATION = 12_000.0  # metres: below the deepest trench and above Everest


def load_height_field(
    path: Path,
    bounds: tuple[float, float, float, float],
    peak: float | None = None,
) -> HeightField:
    """A height field from ``.npy`` (metres; times ``peak`` if given, over ``bounds``), a
    GeoTIFF DEM (metres, times ``peak`` if given, each elevation at its cell's centre: the
    cells over ``bounds`` and one more each side, placed by its georeferencing) or an image
    (grey 0..1 times ``peak`` metres), decimated to at most ``MAX_NODES`` nodes per side."""
    from usdforest.sites.rasters import GEOTIFF, read_geotiff, read_grey, read_npy

    where = "ground.file"
    geo = read_geotiff(path, where, box=bounds) if path.suffix.lower() in GEOTIFF else None
    if geo is not None:
        z = geo.values
        bounds = geo.centres
    elif path.suffix.lower() == ".npy":
        z = read_npy(path, where)
    else:
        if peak is None:
            raise RecipeError("ground.max: an image height field needs 'max' (metres for white)")
        z = read_grey(path, where)
    if z.ndim != 2 or min(z.shape) < 2:
        raise RecipeError(
            f"{where}: {path.name} must be a 2D grid of at least 2 x 2 elevations, "
            f"got shape {z.shape}"
        )
    scale = 1.0 if peak is None else float(peak)
    bounds = tuple(map(float, bounds))
    if max(z.shape) > MAX_NODES:
        # resample the surface itself on a coarser lattice over the same bounds, reading only
        # the cells it needs from the (memory-mapped) raster
        rows, cols = (min(n, MAX_NODES) for n in z.shape)
        x0, y0, x1, y1 = bounds
        gx, gy = np.meshgrid(np.linspace(x0, x1, cols), np.linspace(y1, y0, rows))
        z = HeightField(z, bounds).height(gx, gy)
    # stored as float32 by the mesh: heights are interpolated from the same node values
    z = (np.asarray(z, dtype=np.float64) * scale).astype(np.float32).astype(np.float64)
    if not np.all(np.isfinite(z)):
        bad = int(np.count_nonzero(~np.isfinite(z)))
        raise RecipeError(f"{where}: {path.name} has {bad} missing or non-finite elevations")
    if np.abs(z).max() > MAX_ELEVATION:
        raise RecipeError(
            f"{where}: {path.name} has elevations up to {np.abs(z).max():.3g} m; the Earth's lie "
            f"within {MAX_ELEVATION:,.0f} m of sea level (wrong units or a no-data value?)"
        )
    return HeightField(z, bounds)
