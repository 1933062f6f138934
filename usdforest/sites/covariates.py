"""Spatial covariates of a fit: rasters (elevation, slope, soil moisture, ...) whose values
a fitted intensity may depend on, log-linearly (``usdforest fit --covariates``).

A covariate is read over the fit's window from a GeoTIFF (georeferenced cells, which must
cover the window; rasterio), a ``.npy`` grid over the window (row 0 north) or a grey image
over the window (0..1), and is piecewise constant on its cells, as an intensity raster is.
Its values are centred and scaled (the mean and standard deviation over the window) before
they enter the model, so its coefficient is per standard deviation and the fit is well
conditioned whatever the units.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from usdforest.errors import UsdForestError

Bounds = tuple[float, float, float, float]


@dataclass(frozen=True, eq=False)
class Covariate:
    """A raster ``values (rows, cols)`` (row 0 north) over the cells' outer ``bounds``,
    named by its file's stem; ``mean`` and ``sd`` over the fit's window standardise it."""

    name: str
    values: np.ndarray
    bounds: Bounds
    mean: float
    sd: float

    def raw(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The raster's value in the cell holding each point (the nearest edge cell outside)."""
        from usdforest.sites.rasters import cell_values

        return cell_values(self.values, self.bounds, x, y)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The standardised value at each point."""
        return (self.raw(x, y) - self.mean) / self.sd

    @property
    def cell(self) -> float:
        """The raster's finer cell side (m)."""
        x0, y0, x1, y1 = self.bounds
        rows, cols = self.values.shape
        return min((x1 - x0) / cols, (y1 - y0) / rows)


def read_covariate(path: Path, window: Bounds) -> Covariate:
    """``path`` as a covariate over ``window`` (see the module docstring); an error naming the
    file when it cannot serve."""
    from usdforest.sites.rasters import GEOTIFF, covers, read_geotiff, read_grey, read_npy

    where = f"--covariates {path.name}"
    suffix = path.suffix.lower()
    geo = read_geotiff(path, where, box=window) if suffix in GEOTIFF else None
    if geo is not None:
        if not covers(geo.bounds, window):
            raise UsdForestError(
                f"{where}: covers {list(geo.extent)}, not the fit's window {list(window)} "
                f"(coordinates in the raster's CRS, {geo.crs or 'none given'})"
            )
        values, bounds = np.asarray(geo.values, dtype=float), geo.bounds
    elif suffix == ".npy":
        values, bounds = np.asarray(read_npy(path, where), dtype=float), window
    else:
        values, bounds = read_grey(path, where), window
    if values.ndim != 2 or values.size == 0:
        raise UsdForestError(
            f"{where}: a covariate is a non-empty 2D grid, got shape {values.shape}"
        )
    probe = Covariate(path.stem, values, bounds, 0.0, 1.0)
    inside = _grid(window, probe.cell)
    z = probe.raw(*inside)
    if not np.all(np.isfinite(z)):
        raise UsdForestError(
            f"{where}: has no-data, NaN or infinite cells inside the fit's window {list(window)}"
        )
    sd = float(z.std())
    if not sd > 0:
        raise UsdForestError(f"{where}: is constant over the fit's window; it explains nothing")
    return Covariate(path.stem, values, bounds, float(z.mean()), sd)


def _grid(window: Bounds, cell: float, most: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """Centres of a grid over ``window`` at about ``cell`` (half of it, so every raster cell
    holds some; at most ``most`` a side)."""
    x0, y0, x1, y1 = window
    nx = int(min(max(np.ceil(2 * (x1 - x0) / cell), 64), most))
    ny = int(min(max(np.ceil(2 * (y1 - y0) / cell), 64), most))
    gx = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    gy = y0 + (np.arange(ny) + 0.5) * (y1 - y0) / ny
    xx, yy = np.meshgrid(gx, gy)
    return xx.ravel(), yy.ravel()


def quadrature(window: Bounds, covariates: tuple[Covariate, ...]) -> tuple[np.ndarray, float]:
    """Points (n, 2) and their common weight (m²) of the midpoint rule over ``window`` at half
    the finest covariate cell: exact for the covariates' piecewise-constant cells up to the
    cells the grid's own cells straddle."""
    cell = min(c.cell for c in covariates)
    x, y = _grid(window, cell)
    x0, y0, x1, y1 = window
    return np.column_stack([x, y]), (x1 - x0) * (y1 - y0) / len(x)
