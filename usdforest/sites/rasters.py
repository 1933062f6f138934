"""Reading grids from files: ``.npy`` arrays, grey images (PNG, JPEG, TIFF...) and GeoTIFFs.

Shared by the intensity raster and the ground's height field; errors are
:class:`~usdforest.errors.RecipeError` naming the recipe key.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from usdforest.errors import RecipeError
from usdforest.paths import require_file


def _require(path: Path, where: str) -> None:
    """The file exists, or an error naming the recipe key ``where`` and the file."""
    try:
        require_file(path, "raster", RecipeError)
    except RecipeError as exc:
        raise RecipeError(f"{where}: {exc}") from None


def read_npy(path: Path, where: str) -> np.ndarray:
    """A numeric ``.npy`` grid, memory-mapped (never unpickled: pickles run code)."""
    _require(path, where)
    try:
        a = np.load(path, allow_pickle=False, mmap_mode="r")
    except ValueError as exc:
        if "pickle" in str(exc):
            raise RecipeError(
                f"{where}: {path.name} holds Python objects, not numbers; save a plain "
                "numeric 2D array (numpy.save of a float array)"
            ) from None
        raise RecipeError(f"{where}: cannot read {path.name}: {exc}") from None
    except Exception as exc:
        raise RecipeError(f"{where}: cannot read {path.name}: {exc}") from None
    if a.dtype.kind not in "biuf":
        raise RecipeError(f"{where}: {path.name} holds {a.dtype} values, not numbers")
    return a


def read_grey(path: Path, where: str) -> np.ndarray:
    """An image as grey levels in 0..1: integer pixels divided by their type's maximum (so a
    16-bit TIFF and a dark 8-bit JPEG both keep their scale), float pixels as they are,
    colour channels averaged."""
    import matplotlib.image as mpimg

    _require(path, where)
    try:
        img = np.asarray(mpimg.imread(path))
    except Exception as exc:
        raise RecipeError(f"{where}: cannot read {path.name}: {exc}") from None
    if img.dtype.kind in "iu":
        grey = img.astype(np.float64) / np.iinfo(img.dtype).max
    elif img.dtype.kind == "f":
        grey = img.astype(np.float64)
    else:
        raise RecipeError(f"{where}: {path.name} holds {img.dtype} pixels, not grey levels")
    if grey.ndim == 3:
        grey = grey[..., :3].mean(axis=2)
    return grey


GEOTIFF = (".tif", ".tiff")


def cell_values(
    values: np.ndarray, bounds: tuple[float, float, float, float], x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """The value of the grid ``values`` (row 0 north, over the cells' outer ``bounds``) in the
    cell holding each point (the nearest edge cell for points outside)."""
    x0, y0, x1, y1 = bounds
    rows, cols = values.shape
    c = np.clip(((np.asarray(x) - x0) / (x1 - x0) * cols).astype(np.int64), 0, cols - 1)
    r = np.clip(((y1 - np.asarray(y)) / (y1 - y0) * rows).astype(np.int64), 0, rows - 1)
    return values[r, c]


@dataclass(frozen=True, eq=False)
class GeoGrid:
    """A georeferenced raster: ``values (rows, cols)`` (NaN where the file has no data, row 0
    north) over the cells' outer edges ``bounds = (x0, y0, x1, y1)`` in the file's ``crs``
    (a string such as ``EPSG:32633``; None when the file names none)."""

    values: np.ndarray
    bounds: tuple[float, float, float, float]
    crs: str | None
    extent: tuple[float, float, float, float]  # the whole file's cells, not only those read

    @property
    def centres(self) -> tuple[float, float, float, float]:
        """The bounds of the cells' centres (where a DEM's elevations stand)."""
        x0, y0, x1, y1 = self.bounds
        rows, cols = self.values.shape
        dx, dy = (x1 - x0) / cols, (y1 - y0) / rows
        return (x0 + dx / 2, y0 + dy / 2, x1 - dx / 2, y1 - dy / 2)


def read_geotiff(
    path: Path, where: str, box: tuple[float, float, float, float] | None = None
) -> GeoGrid | None:
    """Band 1 of a GeoTIFF with its georeferencing (rasterio): only the cells that meet
    ``box`` (x0, y0, x1, y1) and one more on each side when a box is given. None for a TIFF
    that has no georeferencing, or when rasterio is not installed (read it as an image with
    :func:`read_grey`)."""
    _require(path, where)
    try:
        import rasterio
        from rasterio.windows import Window
    except ImportError:
        return None
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(path) as ds:
                t = ds.transform
                if ds.crs is None and t.is_identity:
                    return None
                if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
                    raise RecipeError(
                        f"{where}: {path.name} is not a north-up grid (transform "
                        f"{tuple(t)[:6]}); warp it north-up first (e.g. gdalwarp)"
                    )
                crs = ds.crs.to_string() if ds.crs is not None else None
                if ds.crs is not None and ds.crs.is_geographic:
                    raise RecipeError(
                        f"{where}: {path.name} is in {crs}, a geographic CRS (degrees); "
                        "usdforest needs a projected CRS in metres (e.g. UTM): reproject it"
                    )
                c0, r0, c1, r1 = 0, 0, ds.width, ds.height
                if box is not None:  # the cells meeting the box, plus one on each side
                    c0 = max(int(np.floor((box[0] - t.c) / t.a)) - 1, 0)
                    c1 = min(int(np.ceil((box[2] - t.c) / t.a)) + 1, ds.width)
                    r0 = max(int(np.floor((box[3] - t.f) / t.e)) - 1, 0)
                    r1 = min(int(np.ceil((box[1] - t.f) / t.e)) + 1, ds.height)
                    if c1 <= c0 or r1 <= r0:
                        c0, r0, c1, r1 = 0, 0, 1, 1  # outside: the coverage check says so
                band = ds.read(1, window=Window(c0, r0, c1 - c0, r1 - r0), masked=True)
                b = ds.bounds
                x0, y1 = t.c + c0 * t.a, t.f + r0 * t.e
                x1, y0 = t.c + c1 * t.a, t.f + r1 * t.e
    except RecipeError:
        raise
    except Exception as exc:
        raise RecipeError(f"{where}: cannot read {path.name}: {exc}") from None
    if band.dtype.kind not in "biuf":
        raise RecipeError(f"{where}: {path.name} holds {band.dtype} values, not numbers")
    values = np.ma.filled(band.astype(np.float64), np.nan)
    extent = (float(b.left), float(b.bottom), float(b.right), float(b.top))
    return GeoGrid(values, (float(x0), float(y0), float(x1), float(y1)), crs, extent)


def geotiff_extent(
    path: Path, where: str
) -> tuple[tuple[float, float, float, float], str | None] | None:
    """The outer edges of a GeoTIFF's cells (x0, y0, x1, y1) and the CRS it names (None if
    none); None when the file is not georeferenced or rasterio is not installed."""
    if path.suffix.lower() not in GEOTIFF:
        return None
    grid = read_geotiff(path, where, box=(0.0, 0.0, 0.0, 0.0))  # one cell: the checks only
    return None if grid is None else (grid.extent, grid.crs)


def covers(outer: tuple[float, ...], inner: tuple[float, ...]) -> bool:
    """Whether the box ``outer`` (x0, y0, x1, y1) holds the box ``inner``."""
    return (
        outer[0] <= inner[0]
        and outer[1] <= inner[1]
        and outer[2] >= inner[2]
        and outer[3] >= inner[3]
    )
